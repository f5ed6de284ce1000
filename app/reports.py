"""The trial report: one Jinja2 template rendered as HTML and as PDF.

- :func:`build_report_data` gathers everything a report shows about one trial
  from the database (patient code, session, calibration, ``result.json``,
  marker trajectories) into a :class:`ReportData`.
- :func:`render_report_html` renders ``templates/report.html`` (a standalone
  page: inline CSS and inline SVG plots, no external resource).
- :func:`render_report_pdf` renders the same HTML with WeasyPrint; its URL
  fetcher refuses every URL, so a report can never reach the network.

:data:`METRICS` is the catalogue of metrics (label, display unit, UCUM code,
decimals, one-line definition) shared by pages, reports and FHIR exports.
"""

from __future__ import annotations

import hashlib
import json
import math
import threading
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from app import plots
from app.exports import MarkerTable, read_markers_csv


@dataclass(frozen=True)
class MetricSpec:
    """How a metric is labelled, formatted and coded.

    Attributes
    ----------
    label : str
        Short name for tables.
    unit : str
        Unit as displayed (``mm``, ``Hz``, ``mm/s``, ``mm/tap``; empty for ratios and counts).
    ucum : str
        UCUM code for FHIR (``mm``, ``Hz``, ``mm/s``, ``mm/{tap}``, ``1``).
    decimals : int
        Digits after the decimal point when displayed.
    definition : str
        One sentence a clinician can read.
    primary : bool
        Shown in the main metrics table (else under "More measurements").
    """

    label: str
    unit: str
    ucum: str
    decimals: int
    definition: str
    primary: bool = True


METRICS: dict[str, MetricSpec] = {
    "tap_count": MetricSpec(
        "Taps", "", "1", 0, "Number of complete taps (open–close cycles) in the recording."
    ),
    "frequency_hz": MetricSpec(
        "Tapping frequency",
        "Hz",
        "Hz",
        2,
        "Taps per second while moving: 1 / mean tap duration, pauses excluded.",
    ),
    "amplitude_mm_mean": MetricSpec(
        "Mean amplitude",
        "mm",
        "mm",
        1,
        "Mean peak-to-trough opening: largest thumb–index distance of a tap minus the "
        "distance at its start (the closed position).",
    ),
    "amplitude_mm_cv": MetricSpec(
        "Amplitude variability",
        "",
        "1",
        3,
        "Coefficient of variation of the tap amplitudes (standard deviation / mean).",
    ),
    "amplitude_decrement_mm_per_tap": MetricSpec(
        "Amplitude decrement",
        "mm/tap",
        "mm/{tap}",
        2,
        "Least-squares slope of amplitude against tap number; negative means the taps "
        "shrink (sequence effect).",
    ),
    "amplitude_ratio_last_first_third": MetricSpec(
        "Amplitude ratio, last/first third",
        "",
        "1",
        2,
        "Mean amplitude of the last third of the taps divided by that of the first third; "
        "below 1 means a decrement.",
    ),
    "opening_velocity_mm_s_max": MetricSpec(
        "Peak opening velocity",
        "mm/s",
        "mm/s",
        0,
        "Mean over the taps of each tap's peak opening speed.",
    ),
    "closing_velocity_mm_s_max": MetricSpec(
        "Peak closing velocity",
        "mm/s",
        "mm/s",
        0,
        "Mean over the taps of each tap's peak closing speed.",
    ),
    "inter_tap_interval_cv": MetricSpec(
        "Rhythm variability",
        "",
        "1",
        3,
        "Coefficient of variation of the intervals between tap starts, pauses included.",
    ),
    "hesitation_count": MetricSpec(
        "Hesitations",
        "",
        "1",
        0,
        "Interruptions of the rhythm: taps (without a halt) whose cycle is over 1.5 times "
        "the median of the neighbouring taps, or that follow a closed pause of at least 0.2 s.",
    ),
    "halt_count": MetricSpec(
        "Halts",
        "",
        "1",
        0,
        "Freezes: the fingers stay still for at least 0.3 s. A pause counts once, as "
        "hesitation or halt.",
    ),
    "pause_time_s": MetricSpec(
        "Pause time", "s", "s", 2, "Total duration of the hesitations and halts."
    ),
    "tap_rate_hz": MetricSpec(
        "Tap rate",
        "Hz",
        "Hz",
        2,
        "Taps per second including pauses: 1 / mean interval between tap starts.",
    ),
    # Secondary metrics (shown under "More measurements").
    "reliable_tap_count": MetricSpec(
        "Reliable taps",
        "",
        "1",
        0,
        "Taps whose peak and closures were measured, not filled in; amplitude and velocity "
        "statistics use these.",
        primary=False,
    ),
    "amplitude_mm_sd": MetricSpec(
        "Amplitude SD", "mm", "mm", 1, "Standard deviation of the tap amplitudes.", primary=False
    ),
    "amplitude_mm_max": MetricSpec(
        "Largest amplitude", "mm", "mm", 1, "Amplitude of the largest tap.", primary=False
    ),
    "amplitude_decrement_pct_per_tap": MetricSpec(
        "Amplitude decrement, relative",
        "%/tap",
        "%/{tap}",
        2,
        "Decrement slope as a percentage of the mean amplitude of the first three taps.",
        primary=False,
    ),
    "amplitude_ratio_second_first_half": MetricSpec(
        "Amplitude ratio, second/first half",
        "",
        "1",
        2,
        "Mean amplitude of the second half of the taps divided by that of the first half.",
        primary=False,
    ),
    "amplitude_decrement_onset_tap": MetricSpec(
        "Decrement onset (tap index)",
        "",
        "1",
        0,
        "The last tap (counted from 0) before the amplitude starts to fall; empty when "
        "there is no clear decrement.",
        primary=False,
    ),
    "opening_velocity_mm_s_peak": MetricSpec(
        "Fastest opening",
        "mm/s",
        "mm/s",
        0,
        "The largest single-tap peak opening speed.",
        primary=False,
    ),
    "closing_velocity_mm_s_peak": MetricSpec(
        "Fastest closing",
        "mm/s",
        "mm/s",
        0,
        "The largest single-tap peak closing speed.",
        primary=False,
    ),
    "opening_velocity_mm_s_mean": MetricSpec(
        "Mean opening velocity",
        "mm/s",
        "mm/s",
        0,
        "Mean over taps of amplitude / opening duration.",
        primary=False,
    ),
    "closing_velocity_mm_s_mean": MetricSpec(
        "Mean closing velocity",
        "mm/s",
        "mm/s",
        0,
        "Mean over taps of the closing distance / closing duration.",
        primary=False,
    ),
    "opening_velocity_decrement_mm_s_per_tap": MetricSpec(
        "Opening velocity decrement",
        "mm/s per tap",
        "mm/s/{tap}",
        1,
        "Least-squares slope of each tap's peak opening speed against tap number.",
        primary=False,
    ),
    "tap_duration_s_mean": MetricSpec(
        "Mean tap duration",
        "s",
        "s",
        3,
        "Mean duration of one open–close cycle, pauses excluded.",
        primary=False,
    ),
    "inter_tap_interval_s_mean": MetricSpec(
        "Mean interval",
        "s",
        "s",
        3,
        "Mean time between the starts of successive taps.",
        primary=False,
    ),
    "tap_duration_cv": MetricSpec(
        "Tap duration variability",
        "",
        "1",
        3,
        "Coefficient of variation of the tap durations.",
        primary=False,
    ),
    "inter_tap_interval_s_sd": MetricSpec(
        "Interval SD",
        "s",
        "s",
        3,
        "Standard deviation of the intervals between tap starts.",
        primary=False,
    ),
    "tapping_time_s": MetricSpec(
        "Tapping time",
        "s",
        "s",
        2,
        "From the start of the first tap to the end of the last.",
        primary=False,
    ),
    "opening_velocity_decrement_pct_per_tap": MetricSpec(
        "Opening velocity decrement, relative",
        "%/tap",
        "%/{tap}",
        2,
        "Opening velocity slope as a percentage of the first three taps' mean.",
        primary=False,
    ),
    "opening_velocity_ratio_last_first_third": MetricSpec(
        "Opening velocity ratio, last/first third",
        "",
        "1",
        2,
        "Mean peak opening speed of the last third of the taps divided by the first third.",
        primary=False,
    ),
    "opening_velocity_decrement_onset_tap": MetricSpec(
        "Opening velocity decrement onset (tap index)",
        "",
        "1",
        0,
        "The last tap (from 0) before the opening speed starts to fall; empty without a clear decrement.",
        primary=False,
    ),
    "closing_velocity_decrement_mm_s_per_tap": MetricSpec(
        "Closing velocity decrement",
        "mm/s per tap",
        "mm/s/{tap}",
        1,
        "Least-squares slope of each tap's peak closing speed against tap number.",
        primary=False,
    ),
    "closing_velocity_ratio_last_first_third": MetricSpec(
        "Closing velocity ratio, last/first third",
        "",
        "1",
        2,
        "Mean peak closing speed of the last third of the taps divided by the first third.",
        primary=False,
    ),
    "gap_count": MetricSpec(
        "Gaps in the recording",
        "",
        "1",
        0,
        "Stretches where a marker could not be measured; taps may be lost there.",
        primary=False,
    ),
}


def _guess_units(key: str) -> tuple[str, str]:
    """Display unit and UCUM code of a metric the catalogue does not know, from its name."""
    for suffix, unit, ucum in (
        ("_mm_s_per_tap", "mm/s per tap", "mm/s/{tap}"),
        ("_pct_per_tap", "%/tap", "%/{tap}"),
        ("_mm_per_tap", "mm/tap", "mm/{tap}"),
        ("_mm_s", "mm/s", "mm/s"),
        ("_hz", "Hz", "Hz"),
        ("_mm", "mm", "mm"),
        ("_s", "s", "s"),
        ("_px", "px", "{pixel}"),
    ):
        if key.endswith(suffix) or f"{suffix}_" in key:
            return unit, ucum
    return "", "1"


def metric_spec(key: str) -> MetricSpec:
    """The catalogue entry of ``key``, or one guessed from its name (secondary, no definition)."""
    spec = METRICS.get(key)
    if spec is not None:
        return spec
    unit, ucum = _guess_units(key)
    return MetricSpec(key.replace("_", " ").capitalize(), unit, ucum, 3, "", primary=False)


# Metrics shown in trend plots (key, label, unit).
TREND_METRICS: tuple[tuple[str, str, str], ...] = (
    ("amplitude_mm_mean", "Mean amplitude", "mm"),
    ("frequency_hz", "Tapping frequency", "Hz"),
    ("opening_velocity_mm_s_max", "Peak opening velocity", "mm/s"),
    ("amplitude_decrement_mm_per_tap", "Amplitude decrement", "mm/tap"),
    ("hesitation_count", "Hesitations and halts", "count"),
)


def format_metric(key: str, value: Any) -> str:
    """``value`` formatted with the metric's decimals (no unit); "–" when absent."""
    if value is None or isinstance(value, bool):
        return "–"
    if not isinstance(value, int | float):
        return str(value)
    if not math.isfinite(float(value)):
        return "–"
    spec = METRICS.get(key)
    decimals = spec.decimals if spec else (0 if isinstance(value, int) else 3)
    if key.endswith(("_count", "_onset_tap")) and float(value).is_integer():
        decimals = 0
    text = f"{float(value):.{decimals}f}"
    if key.endswith("_per_tap") and float(value) > 0:
        text = "+" + text
    return text


@dataclass(frozen=True)
class MetricRow:
    """One line of the metrics table."""

    key: str
    label: str
    value: str
    value_first_10: str | None
    unit: str
    definition: str


def metric_rows(
    result: Mapping[str, Any] | None, *, primary: bool | None = True
) -> list[MetricRow]:
    """Rows of the metrics table, catalogue order first, then any other number.

    Parameters
    ----------
    result : result.json document
    primary : bool or None
        True: the main metrics only; False: the others only; None: all.
    """
    result = result or {}
    metrics: Mapping[str, Any] = result.get("metrics", {}) or {}
    first10 = result.get("metrics_first_10")
    if not isinstance(first10, Mapping):
        first10 = metrics.get("metrics_first_10")
    first10 = first10 if isinstance(first10, Mapping) else {}
    keys = [k for k in METRICS if k in metrics]
    keys += [
        k
        for k, v in metrics.items()
        if k not in METRICS
        and (v is None or (isinstance(v, int | float) and not isinstance(v, bool)))
    ]
    rows = []
    for key in keys:
        spec = metric_spec(key)
        if primary is not None and spec.primary != primary:
            continue
        rows.append(
            MetricRow(
                key=key,
                label=spec.label,
                value=format_metric(key, metrics.get(key)),
                value_first_10=format_metric(key, first10[key]) if key in first10 else None,
                unit=spec.unit,
                definition=spec.definition,
            )
        )
    return rows


def result_events(result: Mapping[str, Any] | None) -> list[plots.PlotEvent]:
    """Hesitations, halts and gaps of ``result.json`` (top-level ``events``; or in ``metrics``).

    An event has ``kind`` (``hesitation``, ``halt`` or ``gap``), ``t_start_s``
    and ``duration_s`` (or ``t_end_s``).
    """
    result = result or {}
    raw = result.get("events")
    if raw is None:
        raw = (result.get("metrics") or {}).get("events")
    events = []
    for ev in raw or []:
        if not isinstance(ev, Mapping) or ev.get("t_start_s") is None:
            continue
        kind = str(ev.get("kind", "hesitation"))
        if kind not in ("hesitation", "halt", "gap"):
            continue
        start = float(ev["t_start_s"])
        if ev.get("t_end_s") is not None:
            end = float(ev["t_end_s"])
        else:
            end = start + float(ev.get("duration_s") or 0.0)
        events.append(plots.PlotEvent(kind=kind, t_start_s=start, t_end_s=max(end, start + 0.02)))
    return events


@dataclass(frozen=True)
class CalibrationInfo:
    """The calibration a trial was measured with, for the quality panel."""

    rig_name: str
    version: int | None
    valid_from: datetime | None
    rms_px: float | None
    verdict: str | None = None
    reasons: tuple[str, ...] = ()


@dataclass(frozen=True)
class ReportData:
    """Everything the report of one trial shows.

    Attributes
    ----------
    trial_id : int
    patient_code : str
        The pseudonymous code; the report holds no other identifying data.
    hand : ``"left"`` or ``"right"``
    recorded_at : datetime (UTC)
    medication_state, dbs_state : str
    updrs_34_rating : int or None
        The clinician's own MDS-UPDRS 3.4 rating, if given.
    clinician : str or None
    notes : str or None
    result : dict
        ``result.json`` (INTERFACES.md).
    markers : MarkerTable or None
        Trajectories from ``markers.csv`` (None when the file is gone).
    calibration : CalibrationInfo or None
    generated_at : datetime (UTC)
    """

    trial_id: int
    patient_code: str
    hand: str
    recorded_at: datetime
    medication_state: str
    result: dict[str, Any]
    dbs_state: str = "unknown"
    updrs_34_rating: int | None = None
    clinician: str | None = None
    notes: str | None = None
    session_id: int | None = None
    patient_id: int | None = None
    markers: MarkerTable | None = None
    calibration: CalibrationInfo | None = None
    generated_at: datetime = field(default_factory=lambda: datetime.now(UTC))


def quality_verdict(
    quality: Mapping[str, Any] | None, rms_px: float | None
) -> tuple[str, list[str]]:
    """``("good" | "poor", reasons)`` for a calibration, from ``core.calibration.quality_verdict``.

    When the calibration module does not offer a verdict, the rig's RMS
    reprojection error alone decides (good at or below 0.5 px).
    """
    doc = dict(quality or {})
    if rms_px is not None:
        doc.setdefault("rms_px", rms_px)
    core_verdict: Any
    try:
        from core.calibration import quality_verdict as core_verdict
    except ImportError:
        core_verdict = None
    if core_verdict is not None:
        verdict, reasons = core_verdict(doc)
        return str(verdict), [str(r) for r in reasons]
    rms = doc.get("rms_px")
    if rms is None:
        return "unknown", ["the calibration reports no RMS reprojection error"]
    if float(rms) <= 0.5:
        return "good", [f"RMS reprojection error {float(rms):.2f} px (at most 0.5 px is good)"]
    return "poor", [f"RMS reprojection error {float(rms):.2f} px is above 0.5 px; recalibrate"]


def build_report_data(
    db: Any,
    trial_id: int,
    *,
    settings: Any = None,
    data_dir: str | Path | None = None,
) -> ReportData:
    """Collect the report of trial ``trial_id`` from the database.

    Parameters
    ----------
    db : sqlalchemy.orm.Session
    trial_id : int
    settings : app.settings.Settings, optional
        Gives the data directory that ``Result.markers_path`` is relative to.
    data_dir : path, optional
        The data directory directly (wins over ``settings``); default: the
        environment's settings.

    Raises
    ------
    app.errors.NotFoundError
        The trial does not exist, is deleted, or has no result yet.
    """
    from app.errors import NotFoundError
    from app.models import Calibration, Trial, User

    trial = db.get(Trial, trial_id)
    if trial is None or trial.deleted_at is not None:
        raise NotFoundError(f"trial {trial_id} does not exist.")
    if trial.result is None:
        raise NotFoundError(
            f"trial {trial_id} has no result yet (status {trial.status}); wait for its analysis."
        )
    session = trial.session
    patient = session.patient
    result = trial.result
    if data_dir is None:
        if settings is None:
            from app.settings import get_settings

            settings = get_settings()
        data_dir = settings.data_dir
    markers = None
    if result.markers_path:
        path = Path(data_dir) / result.markers_path
        if path.is_file():
            markers = read_markers_csv(path, fps=float(result.document.get("fps") or 0) or None)
    cal_info = None
    cal = db.get(Calibration, result.calibration_id) if result.calibration_id else None
    if cal is None:
        cal = session.calibration
    if cal is not None:
        verdict, reasons = quality_verdict(cal.quality, cal.rms_px)
        cal_info = CalibrationInfo(
            rig_name=cal.rig.name,
            version=cal.version,
            valid_from=cal.valid_from,
            rms_px=cal.rms_px,
            verdict=verdict,
            reasons=tuple(reasons),
        )
    else:
        cal_info = CalibrationInfo(
            rig_name=session.rig.name, version=None, valid_from=None, rms_px=None
        )
    clinician = None
    if session.clinician_user_id is not None:
        user = db.get(User, session.clinician_user_id)
        if user is not None:
            clinician = user.display_name or user.email
    return ReportData(
        trial_id=trial.id,
        patient_code=patient.code,
        patient_id=patient.id,
        session_id=session.id,
        hand=trial.hand,
        recorded_at=session.recorded_at,
        medication_state=session.medication_state,
        dbs_state=session.dbs_state,
        updrs_34_rating=session.updrs_34_rating,
        clinician=clinician,
        notes=session.notes,
        result=dict(result.document),
        markers=markers,
        calibration=cal_info,
    )


@dataclass(frozen=True)
class QualityRow:
    label: str
    value: str
    warn: bool = False


def quality_rows(data: ReportData) -> list[QualityRow]:
    """Lines of the quality panel: calibration, reprojection, tracking, sync."""
    q = data.result.get("quality", {}) or {}
    rows: list[QualityRow] = []
    cal = data.calibration
    if cal is not None:
        name = cal.rig_name + (f", calibration v{cal.version}" if cal.version else "")
        if cal.valid_from is not None and cal.valid_from.year > 1980:
            name += f" (valid from {cal.valid_from:%Y-%m-%d})"
        rows.append(QualityRow("Calibration used", name))
        rms = "not reported" if cal.rms_px is None else f"{cal.rms_px:.2f} px"
        if cal.verdict and cal.verdict != "unknown":
            rms += f" — {cal.verdict}"
        rows.append(QualityRow("Calibration RMS error", rms, warn=cal.verdict == "poor"))
    reproj = q.get("reprojection_px_median")
    if reproj is not None:
        rows.append(
            QualityRow(
                "Marker reprojection error (median)", f"{float(reproj):.2f} px", float(reproj) > 1.0
            )
        )
    p95 = q.get("reprojection_px_p95")
    if isinstance(p95, int | float):
        rows.append(
            QualityRow(
                "Marker reprojection error (95th percentile)",
                f"{float(p95):.2f} px",
                float(p95) > 2.0,
            )
        )
    tracked = q.get("tracked_fraction")
    if tracked is not None:
        rows.append(
            QualityRow("Frames measured", f"{100 * float(tracked):.1f} %", float(tracked) < 0.9)
        )
    interp = q.get("interpolated_fraction")
    if interp is not None:
        rows.append(
            QualityRow("Frames interpolated", f"{100 * float(interp):.1f} %", float(interp) > 0.05)
        )
    sync = data.result.get("sync") or {}
    if "offset_frames" in sync:
        fps = float(data.result.get("fps") or 0)
        offset = float(sync["offset_frames"])
        text = f"{offset:+.2f} frames"
        if fps > 0:
            text += f" ({1000 * offset / fps:+.1f} ms)"
        method = sync.get("method")
        if method:
            text += f", {'estimated' if method == 'auto' else 'given'}"
        rows.append(QualityRow("Camera synchronisation offset", text))
    frame_rate = data.result.get("fps")
    if frame_rate:
        rows.append(QualityRow("Frame rate", f"{float(frame_rate):.1f} Hz"))
    return rows


_PLOT_CACHE: OrderedDict[str, dict[str, str]] = OrderedDict()
_PLOT_CACHE_SIZE = 16
_plot_cache_lock = threading.Lock()


def _plot_key(data: ReportData) -> str:
    digest = hashlib.sha256()
    digest.update(json.dumps(data.result, sort_keys=True, default=str).encode())
    if data.markers is not None:
        digest.update(np.ascontiguousarray(data.markers.positions_mm).tobytes())
        digest.update("".join(data.markers.status.ravel().tolist()).encode())
    return digest.hexdigest()


def report_plots(data: ReportData) -> dict[str, str]:
    """The trial's plots as inline SVG: ``aperture``, ``amplitude``, ``velocity``, ``paths``.

    Drawn once per result and kept in a small in-process cache (a page, its
    PDF and its FHIR export then share one drawing).
    """
    key = _plot_key(data)
    with _plot_cache_lock:
        cached = _PLOT_CACHE.get(key)
        if cached is not None:
            _PLOT_CACHE.move_to_end(key)
            return dict(cached)
    out = _draw_plots(data)
    with _plot_cache_lock:
        _PLOT_CACHE[key] = out
        while len(_PLOT_CACHE) > _PLOT_CACHE_SIZE:
            _PLOT_CACHE.popitem(last=False)
    return dict(out)


def _aperture(data: ReportData) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(time_s, aperture_mm, interpolated) of the trial, or None without thumb and index."""
    m = data.markers
    if m is None or not {"thumb", "index"} <= set(m.labels):
        return None
    aperture = plots.aperture_from_positions(m.positions_mm, labels=m.labels)
    i_t, i_i = m.labels.index("thumb"), m.labels.index("index")
    interp = (m.status[:, i_t] == "interpolated") | (m.status[:, i_i] == "interpolated")
    return m.time_s, aperture, interp


def _aperture_svg(data: ReportData, *, top_mm: float | None = None) -> str:
    series = _aperture(data)
    if series is None:
        return plots.aperture_plot(np.zeros(0), np.zeros(0))
    time_s, aperture, interp = series
    return plots.aperture_plot(
        time_s,
        aperture,
        taps=data.result.get("taps") or [],
        events=result_events(data.result),
        interpolated=interp,
        top_mm=top_mm,
    )


def _amplitude_svg(data: ReportData, *, top_mm: float | None = None) -> str:
    decrement = (data.result.get("metrics") or {}).get("amplitude_decrement_mm_per_tap")
    return plots.tap_amplitude_plot(
        data.result.get("taps") or [],
        decrement_mm_per_tap=float(decrement) if isinstance(decrement, int | float) else None,
        top_mm=top_mm,
    )


def _draw_plots(data: ReportData) -> dict[str, str]:
    taps: Sequence[Mapping[str, Any]] = data.result.get("taps") or []
    out: dict[str, str] = {"aperture": _aperture_svg(data), "amplitude": _amplitude_svg(data)}
    m = data.markers
    if m is not None and {"thumb", "index"} <= set(m.labels):
        keep = [i for i, name in enumerate(m.labels) if name in ("thumb", "index")]
        out["paths"] = plots.fingertip_paths_plot(
            m.positions_mm[:, keep], labels=[m.labels[i] for i in keep]
        )
    else:
        out["paths"] = plots.fingertip_paths_plot(
            np.full((0, 2, 3), np.nan), labels=["thumb", "index"]
        )
    out["velocity"] = plots.velocity_plot(taps)
    return out


def comparison_plots(
    first: ReportData, second: ReportData
) -> tuple[dict[str, str], dict[str, str]]:
    """Aperture and amplitude plots of two trials drawn on the same scales (mm).

    Returns
    -------
    (plots of ``first``, plots of ``second``), each with ``aperture`` and ``amplitude``.
    """

    def peak(values: list[float]) -> float | None:
        finite = [v for v in values if math.isfinite(v)]
        return max(finite) if finite else None

    apertures = [_aperture(d) for d in (first, second)]
    top_aperture = peak(
        [float(np.nanmax(a[1])) for a in apertures if a is not None and np.isfinite(a[1]).any()]
    )
    amplitudes = [
        float(tp["amplitude_mm"])
        for d in (first, second)
        for tp in d.result.get("taps") or []
        if isinstance(tp.get("amplitude_mm"), int | float)
    ]
    top_amplitude = peak(amplitudes)
    out = []
    for d in (first, second):
        out.append(
            {
                "aperture": _aperture_svg(
                    d, top_mm=None if top_aperture is None else 1.12 * top_aperture
                ),
                "amplitude": _amplitude_svg(
                    d, top_mm=None if top_amplitude is None else 1.2 * top_amplitude
                ),
            }
        )
    return out[0], out[1]


def report_context(data: ReportData) -> dict[str, Any]:
    """The template context shared by the report and the trial page."""
    return {
        "data": data,
        "metric_rows": metric_rows(data.result),
        "more_metric_rows": metric_rows(data.result, primary=False),
        "quality_rows": quality_rows(data),
        "warnings": list((data.result.get("quality") or {}).get("warnings") or []),
        "taps": data.result.get("taps") or [],
        "events": result_events(data.result),
        "plots": report_plots(data),
        "metric_specs": {k: v for k, v in METRICS.items() if v.primary},
    }


def render_report_html(data: ReportData) -> str:
    """The standalone HTML report of one trial (inline CSS and SVG; no external resource)."""
    from app.templating import jinja_env

    template = jinja_env.get_template("report.html")
    return template.render(**report_context(data))


def _refusing_fetcher() -> Any:
    """A WeasyPrint URL fetcher that refuses every URL except inline ``data:`` URLs."""
    from weasyprint.urls import URLFetcher

    class RefusingURLFetcher(URLFetcher):
        def fetch(self, url: str, headers: Any = None) -> Any:
            if url.startswith("data:"):
                return super().fetch(url, headers)
            raise ValueError(f"the PDF renderer does not fetch URLs (refused {url[:80]!r})")

    return RefusingURLFetcher(allowed_protocols=("data",), fail_on_errors=False)


def render_report_pdf(data: ReportData) -> bytes:
    """The report of one trial as PDF bytes (WeasyPrint; no URL is ever fetched)."""
    import weasyprint

    html = render_report_html(data)
    document = weasyprint.HTML(string=html, base_url=None, url_fetcher=_refusing_fetcher())
    return bytes(document.write_pdf())

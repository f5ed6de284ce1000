"""What a trial's report shows: :class:`ReportData` and the lines derived from it.

Plain data, no database: ``app.services.results`` fills a :class:`ReportData`
from the database, the renderers (:mod:`app.reports.rendering`) and exports
read it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from app import plots
from core.markers_csv import MarkerTable


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

"""Finger-tapping metrics: speed, amplitude, rhythm, decrement, hesitations and halts.

:func:`compute_metrics` runs the whole chain on 3D marker trajectories:
aperture signal (:mod:`core.aperture`) → taps (:mod:`core.taps`) → per-trial
metrics and located events. Every metric is defined, with its formula, unit and
references, in ``docs/metrics.md``; the names are those of result.json
(INTERFACES.md). A metric that is undefined for the recording (too few taps)
is None, never NaN.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

import numpy as np
from numpy.typing import NDArray

from core.aperture import Aperture, aperture_signal
from core.taps import Segmentation, Tap, segment_recording, still_periods

#: A tap whose closure-to-closure cycle exceeds this multiple of the local
#: median cycle is a hesitation (unless it holds a halt).
HESITATION_FACTOR = 1.5
#: A pause with the fingers closed at least this long (s) is a hesitation too.
HESITATION_MIN_PAUSE_S = 0.2
#: Taps on each side whose cycles form the local median.
HESITATION_WINDOW_TAPS = 5
#: Fingers still for at least this long (s) is a halt (freeze).
HALT_MIN_S = 0.3
#: Number of taps of the clinical test (MDS-UPDRS 3.4).
CLINICAL_TAP_COUNT = 10
#: Taps averaged as "the first taps" for the relative (%/tap) decrement.
FIRST_TAPS_FOR_PERCENT = 3
#: A decrement onset needs a fitted drop of at least this fraction of the plateau.
ONSET_MIN_DROP_FRACTION = 0.1

Number = float | int | None


@dataclass(frozen=True)
class TappingMetrics:
    """Everything measured on one finger-tapping recording.

    Attributes
    ----------
    aperture : Aperture
        The aperture signal the taps were found on.
    taps : list[Tap]
        The complete taps, in time order.
    metrics : dict[str, float | int | None]
        Per-trial metrics over the whole recording (names in docs/metrics.md).
    metrics_first_10 : dict[str, float | int | None]
        The same metrics over the first 10 taps (the clinical test).
    events : list[dict]
        Hesitations, halts and gaps, located: ``kind``, ``tap_index`` (the tap
        they precede or interrupt; None for a gap after the last tap),
        ``t_start_s``, ``duration_s``.
    segmentation : Segmentation
        The thresholds the segmentation used.
    """

    aperture: Aperture
    taps: list[Tap]
    metrics: dict[str, Number]
    metrics_first_10: dict[str, Number]
    events: list[dict[str, Any]]
    segmentation: Segmentation

    def to_result(self) -> dict[str, Any]:
        """The tapping part of result.json, JSON-serialisable (None for undefined)."""
        seg = self.segmentation
        doc: dict[str, Any] = _clean(
            {
                "metrics": self.metrics,
                "taps": [tap.to_dict() for tap in self.taps],
                "metrics_first_10": self.metrics_first_10,
                "events": self.events,
                "tapping_analysis": {
                    "definitions": "docs/metrics.md",
                    "filter_cutoff_hz": self.aperture.cutoff_hz,
                    "peak_threshold_mm": seg.peak_threshold_mm,
                    "still_velocity_mm_s": seg.still_velocity_mm_s,
                    "typical_turn_s": seg.typical_turn_s,
                    "noise_mm": self.aperture.noise_mm,
                    "velocity_noise_mm_s": self.aperture.velocity_noise_mm_s,
                    # taps estimated lost in gaps of the signal (lost frames, markers
                    # unseen) between complete taps: Tap.cycle_number counts them
                    "cycles_in_gaps": (
                        self.taps[-1].cycle_number - self.taps[-1].index if self.taps else 0
                    ),
                },
            }
        )
        return doc


def compute_metrics(
    positions_mm: NDArray[np.floating],
    fps: float,
    *,
    measured: NDArray[np.bool_] | None = None,
    merged: NDArray[np.bool_] | None = None,
    cutoff_hz: float | None = None,
) -> TappingMetrics:
    """Measure a finger-tapping recording.

    Parameters
    ----------
    positions_mm : (T, M, 3) float
        Marker centres (mm), marker axis ``thumb, index[, ...]``; NaN where missing.
    fps : float
        Frames per second.
    measured : (T, M) or (T,) bool, optional
        False where a position was filled in (interpolated) or is missing.
    merged : (T, M) or (T,) bool, optional
        True where a filled-in position was seen by one camera while the
        markers' images merged in the other (only its depth interpolated):
        such stretches keep the aperture continuous for longer
        (:func:`core.aperture.aperture_signal`).
    cutoff_hz : float, optional
        Low-pass cut-off of the aperture (Hz); default 20 Hz (see docs/metrics.md).

    Returns
    -------
    TappingMetrics
        With ``tap_count`` 0 and the other metrics None when no tap is found.
    """
    aperture = aperture_signal(
        positions_mm, fps, measured=measured, cutoff_hz=cutoff_hz, merged=merged
    )
    seg = segment_recording(aperture)
    return summarise_taps(aperture, seg, seg.taps, locate_events(aperture, seg))


def summarise_taps(
    aperture: Aperture,
    seg: Segmentation,
    taps: Sequence[Tap],
    events: Sequence[dict[str, Any]],
) -> TappingMetrics:
    """The per-trial metrics of ``taps`` and ``events`` (over all of them and the first 10).

    :func:`compute_metrics` passes every tap it found; a clinician's
    corrections (:mod:`core.corrections`) pass the taps and events that still count.
    """
    taps = list(taps)
    events = list(events)
    metrics = tapping_metrics(taps, events)
    first = taps[:CLINICAL_TAP_COUNT]
    first_idx = {t.index for t in first}
    first_events = [e for e in events if e["tap_index"] in first_idx and e["kind"] != "gap"]
    metrics_first_10 = tapping_metrics(first, first_events)
    return TappingMetrics(aperture, taps, metrics, metrics_first_10, events, seg)


def locate_events(aperture: Aperture, seg: Segmentation) -> list[dict[str, Any]]:
    """Find halts, hesitations and gaps, each attached to a tap.

    - **halt**: the fingers stay still for at least 0.3 s: a pause with the
      fingers closed before a tap (``pause_before_s >= 0.3``), or a still
      stretch inside a tap outlasting a normal turn by 0.3 s or more.
    - **hesitation**: a tap, without a halt, whose closure-to-closure cycle is
      longer than 1.5 × the median cycle of the 5 taps on each side, or that
      follows a pause with the fingers closed of at least 0.2 s.
    - **gap**: a stretch of unusable signal (missing markers) between usable ones.

    One pause is counted once: as a halt if it is long enough, else as a
    hesitation.
    """
    taps = seg.taps
    events: list[dict[str, Any]] = []
    fps = aperture.fps
    turn_s = seg.typical_turn_s

    halted: set[int] = set()
    still_runs = (
        still_periods(aperture, still_velocity_mm_s=seg.still_velocity_mm_s)
        if math.isfinite(seg.still_velocity_mm_s)
        else []
    )
    for tap in taps:
        if tap.pause_before_s is not None and tap.pause_before_s >= HALT_MIN_S:
            events.append(
                _event("halt", tap, tap.t_start_s - tap.pause_before_s, tap.pause_before_s)
            )
            halted.add(tap.index)
        for a, b in still_runs:
            t0, t1 = a / fps, (b - 1) / fps
            if t0 < tap.t_start_s or t1 > tap.t_end_s:
                continue  # closed pauses between taps are handled above
            excess = (b - a) / fps - turn_s
            if excess >= HALT_MIN_S:
                events.append(_event("halt", tap, t0 + turn_s / 2, excess))
                halted.add(tap.index)

    cycles = np.array([t.cycle_s if t.cycle_s is not None else t.duration_s for t in taps])
    for k, tap in enumerate(taps):
        if tap.index in halted:
            continue
        lo, hi = max(0, k - HESITATION_WINDOW_TAPS), min(len(taps), k + HESITATION_WINDOW_TAPS + 1)
        others = np.delete(cycles[lo:hi], k - lo)
        if others.size < 2:
            continue
        typical = float(np.median(others))
        pause = tap.pause_before_s or 0.0
        if cycles[k] > HESITATION_FACTOR * typical or pause >= HESITATION_MIN_PAUSE_S:
            excess = max(float(cycles[k]) - typical, pause)
            events.append(_event("hesitation", tap, tap.t_start_s - pause, excess))

    usable_runs = aperture.runs()
    for (_a0, b0), (a1, _b1) in pairwise(usable_runs):
        t0 = b0 / fps
        after = [t for t in taps if t.t_start_s >= a1 / fps]
        events.append(
            {
                "kind": "gap",
                "tap_index": after[0].index if after else None,
                "t_start_s": t0,
                "duration_s": (a1 - b0) / fps,
            }
        )
    events.sort(key=lambda e: (e["t_start_s"], e["kind"]))
    return events


def _event(kind: str, tap: Tap, t_start_s: float, duration_s: float) -> dict[str, Any]:
    return {
        "kind": kind,
        "tap_index": tap.index,
        "t_start_s": float(t_start_s),
        "duration_s": float(duration_s),
    }


def tapping_metrics(taps: Sequence[Tap], events: Sequence[dict[str, Any]]) -> dict[str, Number]:
    """Per-trial metrics of a list of taps (see docs/metrics.md for each definition).

    Amplitude and velocity statistics use the reliable taps only; counts and
    rhythm use every tap.
    """
    n = len(taps)
    good = [t for t in taps if t.reliable]
    x = np.array([t.cycle_number for t in good], dtype=float)
    amp = np.array([t.amplitude_mm for t in good])
    vo = np.array([t.opening_velocity_mm_s_max for t in good])
    vc = np.array([t.closing_velocity_mm_s_max for t in good])
    vo_mean = np.array([t.opening_velocity_mm_s_mean for t in good])
    vc_mean = np.array([t.closing_velocity_mm_s_mean for t in good])
    durations = np.array([t.duration_s for t in taps])
    intervals = np.array([t.interval_s for t in taps if t.interval_s is not None])

    m: dict[str, Number] = {
        "tap_count": n,
        "reliable_tap_count": len(good),
        "frequency_hz": _inv(_mean(durations)),
        "tap_duration_s_mean": _mean(durations),
        "tap_duration_cv": _cv(durations),
        "tap_rate_hz": _inv(_mean(intervals)),
        "inter_tap_interval_s_mean": _mean(intervals),
        "inter_tap_interval_s_sd": _sd(intervals),
        "inter_tap_interval_cv": _cv(intervals),
        "amplitude_mm_mean": _mean(amp),
        "amplitude_mm_sd": _sd(amp),
        "amplitude_mm_cv": _cv(amp),
        "amplitude_mm_max": _max(amp),
        "amplitude_decrement_mm_per_tap": _slope(x, amp),
        "amplitude_decrement_pct_per_tap": _pct_slope(x, amp),
        "amplitude_ratio_last_first_third": _ratio_thirds(amp),
        "amplitude_ratio_second_first_half": _ratio_halves(amp),
        "amplitude_decrement_onset_tap": _onset_tap(x, amp, good),
        "opening_velocity_mm_s_max": _mean(vo),
        "opening_velocity_mm_s_peak": _max(vo),
        "opening_velocity_mm_s_mean": _mean(vo_mean),
        "closing_velocity_mm_s_max": _mean(vc),
        "closing_velocity_mm_s_peak": _max(vc),
        "closing_velocity_mm_s_mean": _mean(vc_mean),
        "opening_velocity_decrement_mm_s_per_tap": _slope(x, vo),
        "opening_velocity_decrement_pct_per_tap": _pct_slope(x, vo),
        "opening_velocity_ratio_last_first_third": _ratio_thirds(vo),
        "opening_velocity_decrement_onset_tap": _onset_tap(x, vo, good),
        "closing_velocity_decrement_mm_s_per_tap": _slope(x, vc),
        "closing_velocity_ratio_last_first_third": _ratio_thirds(vc),
        "hesitation_count": sum(1 for e in events if e["kind"] == "hesitation"),
        "halt_count": sum(1 for e in events if e["kind"] == "halt"),
        "pause_time_s": float(
            sum(e["duration_s"] for e in events if e["kind"] in ("hesitation", "halt"))
        ),
        "gap_count": sum(1 for e in events if e["kind"] == "gap"),
        "tapping_time_s": (taps[-1].t_end_s - taps[0].t_start_s) if taps else None,
    }
    return {k: _finite_or_none(v) for k, v in m.items()}


# --- small statistics, None when undefined ---------------------------------------


def _finite_or_none(v: Number) -> Number:
    if v is None:
        return None
    if isinstance(v, (int, np.integer)):
        return int(v)
    f = float(v)
    return f if math.isfinite(f) else None


def _mean(a: NDArray[np.float64]) -> float | None:
    return float(np.mean(a)) if a.size else None


def _max(a: NDArray[np.float64]) -> float | None:
    return float(np.max(a)) if a.size else None


def _sd(a: NDArray[np.float64]) -> float | None:
    return float(np.std(a, ddof=1)) if a.size >= 2 else None


def _cv(a: NDArray[np.float64]) -> float | None:
    sd, mean = _sd(a), _mean(a)
    return sd / mean if sd is not None and mean else None


def _inv(v: float | None) -> float | None:
    return 1.0 / v if v else None


def _slope(x: NDArray[np.float64], y: NDArray[np.float64]) -> float | None:
    """Least-squares slope of ``y`` over ``x``; None for fewer than 3 points."""
    if y.size < 3 or np.ptp(x) == 0:
        return None
    xc = x - x.mean()
    return float(np.sum(xc * (y - y.mean())) / np.sum(xc * xc))


def _pct_slope(x: NDArray[np.float64], y: NDArray[np.float64]) -> float | None:
    s = _slope(x, y)
    ref = float(np.mean(y[:FIRST_TAPS_FOR_PERCENT])) if y.size else 0.0
    return 100.0 * s / ref if s is not None and ref > 0 else None


def _ratio_thirds(y: NDArray[np.float64]) -> float | None:
    k = y.size // 3
    if k == 0:
        return None
    first = float(np.mean(y[:k]))
    return float(np.mean(y[-k:])) / first if first > 0 else None


def _ratio_halves(y: NDArray[np.float64]) -> float | None:
    k = y.size // 2
    if k == 0:
        return None
    first = float(np.mean(y[:k]))
    return float(np.mean(y[-k:])) / first if first > 0 else None


def decrement_onset(x: NDArray[np.float64], y: NDArray[np.float64]) -> int | None:
    """Breakpoint of a plateau-then-linear-decline fit, as a position in ``y``.

    Fits ``y = c`` for ``x <= x_k`` and ``y = c + s (x - x_k)`` after it, for
    every candidate ``k`` with at least two points after it, by least squares,
    and keeps the ``k`` of smallest residual. Returns None (no decrement) with
    fewer than 5 points, when ``s >= 0``, when the fitted drop
    ``-s (x_last - x_k)`` is under 10 % of the plateau ``c``, or when it is
    under twice the residual standard deviation.
    """
    n = y.size
    if n < 5:
        return None
    best: tuple[float, int, float, float] | None = None
    for k in range(n - 2):
        z = np.maximum(0.0, x - x[k])
        design = np.column_stack([np.ones(n), z])
        coef, *_ = np.linalg.lstsq(design, y, rcond=None)
        sse = float(np.sum((design @ coef - y) ** 2))
        if best is None or sse < best[0] - 1e-12:
            best = (sse, k, float(coef[0]), float(coef[1]))
    assert best is not None
    sse, k, c, s = best
    drop = -s * float(x[-1] - x[k])
    resid_sd = math.sqrt(sse / (n - 2))
    if s >= 0 or c <= 0 or drop < ONSET_MIN_DROP_FRACTION * c or drop < 2 * resid_sd:
        return None
    return k


def _onset_tap(x: NDArray[np.float64], y: NDArray[np.float64], taps: Sequence[Tap]) -> int | None:
    k = decrement_onset(x, y)
    return None if k is None else taps[k].index


def json_ready(obj: Any) -> Any:
    """``obj`` with numpy scalars as Python numbers and NaN/inf as None (JSON has no NaN)."""
    return _clean(obj)


def _clean(obj: Any) -> Any:
    """Recursively turn numpy scalars into Python numbers and NaN/inf into None."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    return obj


__all__ = [
    "TappingMetrics",
    "compute_metrics",
    "decrement_onset",
    "json_ready",
    "locate_events",
    "summarise_taps",
    "tapping_metrics",
]

"""Cycle metrics of every task: the same segmentation and statistics, in the task's unit.

Finger tapping (:mod:`core.metrics`) measures the thumb–index aperture. The
other tasks measure their protocol's cycle signal (:mod:`core.protocols`): the
finger–wrist distance (hand movements, mm), the rotation about the forearm axis
(pronation–supination, degrees), the toe lift (toe tapping, mm). The signal
goes through the aperture's filter (:func:`core.aperture.signal_aperture`), the
tap segmentation (:mod:`core.taps`: a cycle runs from one turn at the closed /
pronated / lowered end to the next, through the other end) and the tapping
statistics (:func:`core.metrics.summarise_taps`), so every definition of
``docs/metrics.md`` carries over; only the names change.

Every task's ``metrics`` hold the common keys of docs/interfaces.md
(:data:`COMMON_KEYS`); finger tapping keeps its own names as well.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from core.aperture import Aperture, default_cutoff_hz, signal_aperture
from core.metrics import Number, TappingMetrics, json_ready, locate_events, summarise_taps
from core.protocols import CycleSignal, cycle_signal
from core.taps import Tap, segment_recording
from core.tasks import Task, task_key

#: The keys every task's ``metrics`` hold (docs/interfaces.md).
COMMON_KEYS = (
    "cycle_count",
    "frequency_hz",
    "amplitude_mean",
    "amplitude_unit",
    "amplitude_cv",
    "amplitude_decrement_per_cycle",
    "hesitation_count",
    "halt_count",
)


def common_metrics(metrics: dict[str, Number], unit: str) -> dict[str, Number | str]:
    """The common keys from finger-tapping-named metrics (``core.metrics.tapping_metrics``)."""
    return {
        "cycle_count": metrics["tap_count"],
        "frequency_hz": metrics["frequency_hz"],
        "amplitude_mean": metrics["amplitude_mm_mean"],
        "amplitude_unit": unit,
        "amplitude_cv": metrics["amplitude_mm_cv"],
        "amplitude_decrement_per_cycle": metrics["amplitude_decrement_mm_per_tap"],
        "hesitation_count": metrics["hesitation_count"],
        "halt_count": metrics["halt_count"],
    }


def with_common_keys(result: dict[str, Any], tapping: TappingMetrics) -> dict[str, Any]:
    """Finger tapping's ``result`` (:meth:`TappingMetrics.to_result`) with the common keys of
    every task added to ``metrics`` and ``metrics_first_10``, beside its own names."""
    out = dict(result)
    out["metrics"] = {**result.get("metrics", {}), **common_metrics(tapping.metrics, "mm")}
    out["metrics_first_10"] = {
        **result.get("metrics_first_10", {}),
        **common_metrics(tapping.metrics_first_10, "mm"),
    }
    return out


def cycle_rows(taps: Sequence[Tap], task: Task) -> list[dict[str, Any]]:
    """One dict per cycle: the fields of ``core.taps.Tap`` under the task's names."""
    return [{task_key(k, task): v for k, v in tap.to_dict().items()} for tap in taps]


def cycle_events(events: Sequence[Mapping[str, Any]], task: Task) -> list[dict[str, Any]]:
    """Hesitations, halts and gaps with the cycle they precede (``cycle_index``; finger
    tapping keeps ``tap_index``)."""
    if task is Task.FINGER_TAPPING:
        return [dict(e) for e in events]
    return [{("cycle_index" if k == "tap_index" else k): v for k, v in e.items()} for e in events]


@dataclass(frozen=True)
class TaskMetrics:
    """The cycles and metrics of one recording of a task other than finger tapping.

    Attributes
    ----------
    task : Task
    signal : CycleSignal
        The protocol's cycle signal.
    tapping : TappingMetrics
        The segmentation and statistics, in finger tapping's names (the
        aperture holds the cycle signal, in the task's unit).
    """

    task: Task
    signal: CycleSignal
    tapping: TappingMetrics

    @property
    def metrics(self) -> dict[str, Number | str]:
        """Per-trial metrics (task names) with the common keys."""
        return self._named(self.tapping.metrics)

    @property
    def metrics_first_10(self) -> dict[str, Number | str]:
        """The same over the first 10 cycles (the clinical test)."""
        return self._named(self.tapping.metrics_first_10)

    def _named(self, metrics: dict[str, Number]) -> dict[str, Number | str]:
        out: dict[str, Number | str] = {task_key(k, self.task): v for k, v in metrics.items()}
        out.update(common_metrics(metrics, self.signal.unit))
        return out

    @property
    def cycles(self) -> list[dict[str, Any]]:
        """One dict per cycle (the task's names of ``core.taps.Tap`` fields)."""
        return cycle_rows(self.tapping.taps, self.task)

    @property
    def events(self) -> list[dict[str, Any]]:
        """Hesitations, halts and gaps with the cycle they precede (``cycle_index``)."""
        return cycle_events(self.tapping.events, self.task)

    def to_result(self) -> dict[str, Any]:
        """The task's part of result.json (JSON-ready; None for undefined)."""
        base = self.tapping.to_result()
        analysis = dict(base["tapping_analysis"])
        analysis["peak_threshold"] = analysis.pop("peak_threshold_mm")
        analysis["still_velocity_per_s"] = analysis.pop("still_velocity_mm_s")
        analysis["noise"] = analysis.pop("noise_mm")
        analysis["velocity_noise_per_s"] = analysis.pop("velocity_noise_mm_s")
        analysis["unit"] = self.signal.unit
        analysis["signal"] = self.signal.details
        return dict(
            json_ready(
                {
                    "metrics": self.metrics,
                    "cycles": self.cycles,
                    "metrics_first_10": self.metrics_first_10,
                    "events": self.events,
                    "cycle_analysis": analysis,
                }
            )
        )


def task_signal(
    task: Task | str,
    positions_mm: NDArray[np.floating],
    fps: float,
    *,
    measured: NDArray[np.bool_] | None = None,
    side: str = "right",
    cutoff_hz: float | None = None,
) -> tuple[CycleSignal, Aperture]:
    """The protocol's cycle signal of ``task`` and its filtered form, on which cycles are found.

    The first step of :func:`compute_task_metrics` (parameters as there); a
    clinician's corrections (:mod:`core.corrections`) measure from the same.

    Returns
    -------
    (CycleSignal, Aperture)
        The raw signal (in its unit) and finger tapping's filtered signal of it.
    """
    task = Task(task)
    if task is Task.FINGER_TAPPING:
        raise ValueError("finger tapping is measured by core.metrics.compute_metrics")
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be a positive number, got {fps}")
    pos = np.asarray(positions_mm, dtype=np.float64)
    signal = cycle_signal(task, pos, side=side)
    meas = None
    if measured is not None:
        m = np.asarray(measured, dtype=bool)
        if m.shape != pos.shape[:2]:
            raise ValueError(f"measured must have shape {pos.shape[:2]}, got {m.shape}")
        meas = np.all(m, axis=1)
    cutoff = default_cutoff_hz(fps) if cutoff_hz is None else float(cutoff_hz)
    if not 0 < cutoff < fps / 2:
        raise ValueError(f"cutoff_hz must lie in (0, fps/2) = (0, {fps / 2}), got {cutoff}")
    return signal, signal_aperture(signal.values, fps, measured=meas, cutoff_hz=cutoff)


def compute_task_metrics(
    task: Task | str,
    positions_mm: NDArray[np.floating],
    fps: float,
    *,
    measured: NDArray[np.bool_] | None = None,
    side: str = "right",
    cutoff_hz: float | None = None,
) -> TaskMetrics:
    """Measure a recording of ``task`` (not finger tapping: see :func:`core.metrics.compute_metrics`).

    Parameters
    ----------
    task : Task or str
    positions_mm : ndarray, shape (T, M, 3)
        The protocol's markers (mm), in its label order; NaN where missing.
    fps : float
    measured : ndarray, shape (T, M), optional
        False where a marker was filled in or is missing.
    side : {"right", "left"}
        The side examined (the direction of supination, 3.6).
    cutoff_hz : float, optional
        Low-pass cut-off (Hz); default as the aperture's (20 Hz, at most 0.4 fps).

    Returns
    -------
    TaskMetrics
    """
    task = Task(task)
    signal, aperture = task_signal(
        task, positions_mm, fps, measured=measured, side=side, cutoff_hz=cutoff_hz
    )
    seg = segment_recording(aperture)
    tapping = summarise_taps(aperture, seg, seg.taps, locate_events(aperture, seg))
    return TaskMetrics(task, signal, tapping)


__all__ = [
    "COMMON_KEYS",
    "TaskMetrics",
    "common_metrics",
    "compute_task_metrics",
    "cycle_events",
    "cycle_rows",
    "task_key",
    "task_signal",
    "with_common_keys",
]

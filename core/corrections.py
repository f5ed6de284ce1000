"""A clinician's corrections of a measurement of any task, and the metrics they give.

The clinician reviews a trial against its video and may say: this tap (or
cycle) is not one (exclude it), this pause was the patient talking (not a
hesitation or a halt), only this stretch of the recording counts (the analysis
window), or the two markers' labels are the wrong way round (thumb and index;
finger and wrist). :func:`correct_metrics` takes the stored trajectories
(:class:`core.markers_csv.MarkerTable`, what ``markers.csv`` holds), the task
and :class:`Corrections`, and measures again:

1. The task's signal, the taps (cycles) and the pauses are found exactly as the
   analysis finds them on the same trajectories
   (:func:`core.metrics.compute_metrics` for finger tapping, the first step of
   :func:`core.cycles.compute_task_metrics`, :func:`core.cycles.task_signal`,
   for the other tasks), so tap numbers (``Tap.index``) are those the
   clinician saw.
2. Taps excluded by the clinician, and taps not wholly inside the window, are
   removed from the list of taps; hesitations and halts of a removed tap, and
   those the clinician dismissed, are removed from the events; gaps outside
   the window are removed.
3. The per-trial metrics are :func:`core.metrics.summarise_taps` of what
   remains: every statistic (counts, amplitudes, velocities, rhythm, decrement)
   is computed as if the removed taps and pauses had not been detected. The
   remaining taps keep their measured values (amplitude, velocities, interval
   to the next detected tap, cycle number), so the decrement's tap axis keeps
   the recording's order.

Every task's corrected ``metrics`` hold its own names and the common keys
(:mod:`core.cycles`), as its analysis does.

Swapping the labels of a two-marker protocol does not change the signal (a
distance) and so no metric; it changes which trajectory is called which in the
marker file, the exports and the plots (:func:`swap_labels`). The three
markers of pronation–supination and toe tapping are named by their distances
(:mod:`core.protocols`) and are not swapped.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from core.aperture import Aperture, aperture_signal
from core.cycles import TaskMetrics, cycle_events, cycle_rows, task_signal, with_common_keys
from core.markers_csv import MEASURED, MarkerTable
from core.metrics import TappingMetrics, _clean, locate_events, summarise_taps
from core.protocols import CycleSignal, marker_columns, protocol_for
from core.resample import uniform_trajectories
from core.taps import Tap, segment_recording
from core.tasks import Task

PAUSE_KINDS = ("hesitation", "halt")


@dataclass(frozen=True)
class Corrections:
    """What the clinician changed about a measurement.

    Attributes
    ----------
    exclude_taps : tuple of int
        ``Tap.index`` (0-based) of the taps that do not count.
    dismiss_pauses : tuple of int
        ``Tap.index`` of the taps whose hesitation or halt is not one (e.g. the
        patient was talking): those events no longer count.
    window_s : (float, float) or None
        Only taps wholly inside ``[t0, t1]`` (s, left-video time) count; None:
        the whole recording.
    swap_labels : bool
        The labels of the two markers (thumb and index; finger and wrist) are exchanged.
    """

    exclude_taps: tuple[int, ...] = ()
    dismiss_pauses: tuple[int, ...] = ()
    window_s: tuple[float, float] | None = None
    swap_labels: bool = False

    def __post_init__(self) -> None:
        for name in ("exclude_taps", "dismiss_pauses"):
            values = getattr(self, name)
            if any(isinstance(v, bool) or not isinstance(v, int) or v < 0 for v in values):
                raise ValueError(f"{name} must hold tap numbers (integers >= 0), got {values}")
            object.__setattr__(self, name, tuple(sorted(set(values))))
        if self.window_s is not None:
            t0, t1 = (float(v) for v in self.window_s)
            if not (math.isfinite(t0) and math.isfinite(t1) and 0 <= t0 < t1):
                raise ValueError(
                    f"window_s must be [start, end] in s with 0 <= start < end, got {self.window_s}"
                )
            object.__setattr__(self, "window_s", (t0, t1))

    @property
    def is_empty(self) -> bool:
        """No correction at all."""
        return self == Corrections()

    def to_dict(self) -> dict[str, Any]:
        """JSON form (the ``corrections`` object of a revised result.json)."""
        return {
            "exclude_taps": list(self.exclude_taps),
            "dismiss_pauses": list(self.dismiss_pauses),
            "window_s": None if self.window_s is None else list(self.window_s),
            "swap_labels": self.swap_labels,
        }

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any] | None) -> Corrections:
        """Read :meth:`to_dict`'s form (missing keys: no correction)."""
        doc = doc or {}
        window = doc.get("window_s")
        return cls(
            exclude_taps=tuple(doc.get("exclude_taps") or ()),
            dismiss_pauses=tuple(doc.get("dismiss_pauses") or ()),
            window_s=None if window is None else (float(window[0]), float(window[1])),
            swap_labels=bool(doc.get("swap_labels", False)),
        )


@dataclass(frozen=True)
class CorrectedMetrics:
    """The metrics after a clinician's corrections.

    Attributes
    ----------
    metrics : TappingMetrics
        Taps, events and per-trial metrics that count.
    corrections : Corrections
    excluded_taps : tuple of Tap
        Taps the clinician excluded.
    outside_window_taps : tuple of Tap
        Taps not wholly inside the analysis window.
    dismissed_events : tuple of dict
        Hesitations and halts the clinician dismissed, or that belonged to a removed tap.
    task : Task
        The task measured.
    signal : CycleSignal or None
        The cycle signal of a task other than finger tapping (None for finger tapping).
    """

    metrics: TappingMetrics
    corrections: Corrections
    excluded_taps: tuple[Tap, ...]
    outside_window_taps: tuple[Tap, ...]
    dismissed_events: tuple[dict[str, Any], ...]
    task: Task = Task.FINGER_TAPPING
    signal: CycleSignal | None = None

    def to_result(self) -> dict[str, Any]:
        """The task's part of result.json, as its analysis writes it (finger tapping:
        :meth:`TappingMetrics.to_result` with the common keys; the other tasks:
        :meth:`core.cycles.TaskMetrics.to_result`), plus ``corrections``,
        ``excluded_taps``, ``outside_window_taps`` and ``dismissed_events`` (the
        removed taps or cycles under the task's names)."""
        if self.signal is None:
            doc = with_common_keys(self.metrics.to_result(), self.metrics)
        else:
            doc = TaskMetrics(self.task, self.signal, self.metrics).to_result()
        doc["corrections"] = self.corrections.to_dict()
        doc["excluded_taps"] = _clean(cycle_rows(self.excluded_taps, self.task))
        doc["outside_window_taps"] = _clean(cycle_rows(self.outside_window_taps, self.task))
        doc["dismissed_events"] = _clean(cycle_events(self.dismissed_events, self.task))
        return doc


def swappable_labels(task: Task | str) -> tuple[str, str] | None:
    """The two labels a clinician may swap (a two-marker protocol), None for the others."""
    labels = protocol_for(task).labels
    return (labels[0], labels[1]) if len(labels) == 2 else None


def swap_labels(table: MarkerTable, task: Task | str = Task.FINGER_TAPPING) -> MarkerTable:
    """``table`` with the labels of ``task``'s two markers exchanged (the data stay in place).

    Raises
    ------
    ValueError
        The task has more than two markers (named by their distances), or the
        table lacks one of the two.
    """
    task = Task(task)
    pair = swappable_labels(task)
    if pair is None:
        raise ValueError(
            f"the {task.label.lower()} markers ({', '.join(protocol_for(task).labels)}) are named"
            " by their distances and cannot be swapped"
        )
    a, b = pair
    labels = list(table.labels)
    if a not in labels or b not in labels:
        raise ValueError(f"the markers {table.labels} have no {a} and {b} to swap")
    i, j = labels.index(a), labels.index(b)
    labels[i], labels[j] = b, a
    return replace(table, labels=tuple(labels))


def swap_thumb_index(table: MarkerTable) -> MarkerTable:
    """``table`` with the labels ``thumb`` and ``index`` exchanged (:func:`swap_labels`)."""
    return swap_labels(table, Task.FINGER_TAPPING)


def _protocol_markers(
    table: MarkerTable, task: Task
) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Positions ``(T, M, 3)`` and measured flags ``(T, M)`` in the order of the task's labels."""
    cols = marker_columns(table.labels, task)
    return table.positions_mm[:, cols, :], table.status[:, cols] == MEASURED


def _signal(
    table: MarkerTable, task: Task, *, side: str, cutoff_hz: float | None
) -> tuple[Aperture, CycleSignal | None]:
    """The filtered signal the analysis found the taps on (and a task's raw cycle signal)."""
    positions, measured = _protocol_markers(table, task)
    # At the frames' real times, as the analysis measured them (core.resample).
    even = uniform_trajectories(positions, measured, table.time_s, table.fps)
    if task is Task.FINGER_TAPPING:
        aperture = aperture_signal(
            even.positions_mm, even.fps, measured=even.measured, cutoff_hz=cutoff_hz
        )
        return aperture, None
    signal, aperture = task_signal(
        task, even.positions_mm, even.fps, measured=even.measured, side=side, cutoff_hz=cutoff_hz
    )
    return aperture, signal


def _numbered(indices: list[int]) -> str:
    """Taps as a clinician counts them (from 1) and as the API numbers them (from 0):
    ``3 (index 2)``, ``3 and 5 (indices 2 and 4)``."""
    ones = [str(i + 1) for i in indices]
    zeros = [str(i) for i in indices]
    if len(indices) == 1:
        return f"{ones[0]} (index {zeros[0]})"
    return (
        f"{', '.join(ones[:-1])} and {ones[-1]} (indices {', '.join(zeros[:-1])} and {zeros[-1]})"
    )


def correct_metrics(
    table: MarkerTable,
    corrections: Corrections,
    *,
    task: Task | str = Task.FINGER_TAPPING,
    side: str = "right",
    cutoff_hz: float | None = None,
) -> CorrectedMetrics:
    """Measure the trajectories of ``table`` again with the clinician's corrections.

    Parameters
    ----------
    table : MarkerTable
        The tracked trajectories (``markers.csv``); labels must include the
        task's (``thumb`` and ``index`` for finger tapping, docs/protocols.md).
    corrections : Corrections
        Tap (cycle) numbers refer to those the analysis finds on these
        trajectories.
    task : Task or str
        The task recorded (result.json ``task``).
    side : {"right", "left"}
        The side examined (the direction of supination, 3.6), as for the analysis.
    cutoff_hz : float, optional
        Low-pass cut-off of the signal (Hz), as for the analysis.

    Returns
    -------
    CorrectedMetrics

    Raises
    ------
    ValueError
        A tap number does not exist, a dismissed tap has no hesitation or halt,
        no tap is left, or the labels cannot be swapped (a clinician-readable sentence).
    """
    task = Task(task)
    word = task.cycle_word
    if corrections.swap_labels:
        table = swap_labels(table, task)
    aperture, signal = _signal(table, task, side=side, cutoff_hz=cutoff_hz)
    seg = segment_recording(aperture)
    events = locate_events(aperture, seg)
    known = {t.index for t in seg.taps}
    unknown = sorted(set(corrections.exclude_taps) - known)
    if unknown:
        n = len(seg.taps)
        raise ValueError(
            f"there is no {word} {_numbered(unknown)} in this recording (it has {n} {word}s"
            + (f", indices 0–{n - 1})." if n else ").")
        )
    paused = {e["tap_index"] for e in events if e["kind"] in PAUSE_KINDS}
    not_paused = sorted(set(corrections.dismiss_pauses) - paused)
    if not_paused:
        raise ValueError(f"{word} {_numbered(not_paused)} has no hesitation or halt to dismiss.")

    excluded = set(corrections.exclude_taps)
    window = corrections.window_s
    inside = _inside(seg.taps, window)
    kept = [t for t in seg.taps if t.index not in excluded and t.index in inside]
    kept_idx = {t.index for t in kept}
    dismissed = set(corrections.dismiss_pauses)
    kept_events: list[dict[str, Any]] = []
    dropped_events: list[dict[str, Any]] = []
    for e in events:
        if e["kind"] in PAUSE_KINDS:
            keep = e["tap_index"] in kept_idx and e["tap_index"] not in dismissed
        else:  # a gap counts when it starts inside the window
            keep = window is None or window[0] <= e["t_start_s"] <= window[1]
        (kept_events if keep else dropped_events).append(e)
    if not kept:
        raise ValueError(
            f"no {word} would be left to measure; exclude fewer {word}s or widen the window."
        )
    metrics = summarise_taps(aperture, seg, kept, kept_events)
    return CorrectedMetrics(
        metrics=metrics,
        corrections=corrections,
        excluded_taps=tuple(t for t in seg.taps if t.index in excluded),
        outside_window_taps=tuple(
            t for t in seg.taps if t.index not in inside and t.index not in excluded
        ),
        dismissed_events=tuple(e for e in dropped_events if e["kind"] in PAUSE_KINDS),
        task=task,
        signal=signal,
    )


def _inside(taps: Sequence[Tap], window: tuple[float, float] | None) -> set[int]:
    if window is None:
        return {t.index for t in taps}
    t0, t1 = window
    return {t.index for t in taps if t.t_start_s >= t0 and t.t_end_s <= t1}


def revised_document(base: Mapping[str, Any], corrected: CorrectedMetrics) -> dict[str, Any]:
    """``result.json`` of a correction: ``base`` (the analysis) with the task's part measured again.

    Everything core measured about the recording itself (``fps``, ``sync``,
    ``quality``, ``markers``...) is kept; the keys of
    :meth:`CorrectedMetrics.to_result` replace the analysis's.
    """
    doc = {k: v for k, v in base.items()}
    doc.update(corrected.to_result())
    pair = swappable_labels(corrected.task)
    if corrected.corrections.swap_labels and pair and isinstance(doc.get("markers"), list):
        a, b = pair
        doc["markers"] = [b if m == a else a if m == b else m for m in doc["markers"]]
    return doc


__all__ = [
    "CorrectedMetrics",
    "Corrections",
    "correct_metrics",
    "revised_document",
    "swap_labels",
    "swap_thumb_index",
    "swappable_labels",
]

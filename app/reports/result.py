"""``result.json`` as the service reads it: :class:`TrialResult`, typed and frozen.

The worker stores the document that ``core.pipeline.Analysis.result_document``
writes (docs/interfaces.md); the pages, reports and exports read it through
:func:`read_result`, once, instead of probing the dictionary. Each field is
read from the one place core writes it; a field core did not write (an older
result, an analysis without metrics) reads as empty or None, never as an error.

``taps`` stay the document's own objects: the taps table and the plots show
any field a tap carries (``reliable``, velocities...), as the document gives it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from app.plots import PlotEvent
from core.tasks import Task, parse_task, task_key

Number = int | float


def _number(value: object) -> Number | None:
    """A JSON number (not a bool), else None."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return value


def _mapping(value: object) -> Mapping[str, Any]:
    return value if isinstance(value, Mapping) else {}


def _list(value: object) -> list[object] | tuple[object, ...]:
    """A JSON array, else empty (a string is not a list of its characters)."""
    return value if isinstance(value, list | tuple) else ()


def _text(value: object) -> str | None:
    """A JSON string, else None."""
    return value if isinstance(value, str) and value else None


def _numbers(value: object) -> dict[str, Number | None]:
    """The numeric (or null) entries of a JSON object; other kinds are not metrics."""
    return {
        str(k): _number(v)
        for k, v in _mapping(value).items()
        if v is None or _number(v) is not None
    }


@dataclass(frozen=True)
class SyncSummary:
    """The ``sync`` object: offset of the right camera in frames, and how it was found.

    The time model's figures (docs/sync.md) are None, or empty, in results older
    than the model: ``offset_s`` and ``drift_ppm`` (the right clock on the left
    one), the frames after which frames were lost in each camera, where each
    camera's frame times came from (``fps``, ``container`` or ``file``), the
    rolling-shutter readout compensated (ms, left and right) and the epipolar
    residual before and after the model (px).
    """

    offset_frames: float | None = None
    method: str | None = None  # "auto" (estimated) or "given"
    offset_s: float | None = None
    drift_ppm: float | None = None
    dropped_frames_left: tuple[int, ...] = ()
    dropped_frames_right: tuple[int, ...] = ()
    time_source: tuple[str, ...] = ()
    readout_ms: tuple[float, ...] = ()
    confidence: float | None = None
    epipolar_px_before: float | None = None
    epipolar_px_after: float | None = None
    fps_right: float | None = None


@dataclass(frozen=True)
class ResultQuality:
    """The ``quality`` object: fractions 0–1, reprojection errors in px, warnings."""

    tracked_fraction: float | None = None
    #: frames x markers measured by both cameras (the rest interpolated or missing)
    measured_fraction: float | None = None
    interpolated_fraction: float | None = None
    reprojection_px_median: float | None = None
    reprojection_px_p95: float | None = None
    warnings: tuple[str, ...] = ()
    #: camera frames with a marker image set aside as partly hidden or merged, and left
    #: frames where the two markers' images touched in a camera (not measured there)
    set_aside_frames: int | None = None
    overlap_frames: int | None = None
    #: camera frames whose merged or touching marker images were measured as two discs
    #: along the rays from the other camera (core.merged)
    merged_measured_frames: int | None = None
    frames: int | None = None


@dataclass(frozen=True)
class TrialResult:
    """A trial's ``result.json``, typed.

    Attributes
    ----------
    fps : float or None
        Frame rate of the left video (Hz).
    sync : SyncSummary
    metrics : dict of str to number or None
        The numeric metrics (``null`` in the document: None, an undefined metric).
    metrics_first_10 : dict of str to number or None
        The same metrics over the first ten taps, where core gives them.
    taps : tuple of mappings
        The taps as the document gives them (``index``, ``t_start_s``, ``amplitude_mm``...).
    events : tuple of PlotEvent
        Hesitations, halts and gaps, in s.
    quality : ResultQuality
    software_version, algorithm_version : str or None
        The ``software`` object: package and algorithm version that measured it
        (None for results older than that key).
    calibration_id : int or None
        The id of the calibration the worker measured with (``calibration.id``).
    task : str
        The task measured (``task``; results older than tasks are finger tapping).
    cycles : tuple of mappings
        The cycles of a task other than finger tapping, as the document gives them.
    side : str or None
        The side the cycle signal was measured for (``cycle_analysis.signal.side``:
        pronation–supination's direction of supination); None when the document does
        not say.
    removed_cycles : int
        Complete taps (cycles) a correction left out: excluded by the clinician or
        outside the chosen window (``excluded_taps``, ``outside_window_taps``).
    cycles_in_gaps : int
        Taps (cycles) made but not measured whole: lost in gaps of the signal (lost
        frames, markers unseen) between complete ones (``tapping_analysis`` or
        ``cycle_analysis``, ``cycles_in_gaps``; 0 when the document does not say).
    """

    fps: float | None = None
    sync: SyncSummary = field(default_factory=SyncSummary)
    metrics: dict[str, Number | None] = field(default_factory=dict)
    metrics_first_10: dict[str, Number | None] = field(default_factory=dict)
    taps: tuple[Mapping[str, object], ...] = ()
    events: tuple[PlotEvent, ...] = ()
    quality: ResultQuality = field(default_factory=ResultQuality)
    software_version: str | None = None
    algorithm_version: str | None = None
    calibration_id: int | None = None
    task: str = "finger_tapping"
    cycles: tuple[Mapping[str, object], ...] = ()
    side: str | None = None
    removed_cycles: int = 0
    cycles_in_gaps: int = 0

    def metric(self, key: str) -> float | None:
        """The metric ``key`` as a float, None when absent or undefined."""
        value = self.metrics.get(key)
        return None if value is None else float(value)

    @property
    def task_cycles(self) -> tuple[Mapping[str, object], ...]:
        """The taps of finger tapping, the cycles of the other tasks."""
        return self.taps if parse_task(self.task) is Task.FINGER_TAPPING else self.cycles

    def counted_position(self, index: int) -> int:
        """Where the tap (cycle) ``index`` (the document's, from 0) stands among the taps
        counted, from 1: those a correction left out before it do not count."""
        before = (_number(c.get("index")) for c in self.task_cycles)
        return 1 + sum(1 for i in before if i is not None and i < index)

    @property
    def cycle_amplitudes(self) -> list[float]:
        """The amplitude of every tap (cycle) that has one, in the task's unit (mm or deg)."""
        key = task_key("amplitude_mm", parse_task(self.task))
        return [float(a) for tp in self.task_cycles if (a := _number(tp.get(key))) is not None]


def result_events(result: Mapping[str, Any] | None) -> list[PlotEvent]:
    """Hesitations, halts and gaps of a ``result.json`` document (its top-level ``events``).

    An event has ``kind`` (``hesitation``, ``halt`` or ``gap``), ``t_start_s``
    and ``duration_s`` (or ``t_end_s``).
    """
    events = []
    for ev in _list((result or {}).get("events")):
        if not isinstance(ev, Mapping) or _number(ev.get("t_start_s")) is None:
            continue
        kind = str(ev.get("kind", "hesitation"))
        if kind not in ("hesitation", "halt", "gap"):
            continue
        start = float(ev["t_start_s"])
        end_s = _number(ev.get("t_end_s"))
        end = float(end_s) if end_s is not None else start + float(ev.get("duration_s") or 0.0)
        events.append(PlotEvent(kind=kind, t_start_s=start, t_end_s=max(end, start + 0.02)))
    return events


def _float(value: object) -> float | None:
    number = _number(value)
    return None if number is None else float(number)


def _sync_summary(sync: Mapping[str, Any], offset: Number | None) -> SyncSummary:
    """The ``sync`` object read (each list only when every entry has its type)."""

    def frames(key: str) -> tuple[int, ...]:
        values = _list(sync.get(key))
        ok = all(isinstance(v, int) and not isinstance(v, bool) for v in values)
        return tuple(int(v) for v in values if isinstance(v, int)) if ok else ()

    readout = _list(sync.get("readout_ms"))
    sources = _list(sync.get("time_source"))
    return SyncSummary(
        offset_frames=None if offset is None else float(offset),
        method=str(sync["method"]) if sync.get("method") else None,
        offset_s=_float(sync.get("offset_s")),
        drift_ppm=_float(sync.get("drift_ppm")),
        dropped_frames_left=frames("dropped_frames_left"),
        dropped_frames_right=frames("dropped_frames_right"),
        time_source=tuple(str(v) for v in sources)
        if all(isinstance(v, str) for v in sources)
        else (),
        readout_ms=tuple(float(v) for v in numbers if v is not None)
        if None not in (numbers := [_number(v) for v in readout])
        else (),
        confidence=_float(sync.get("confidence")),
        epipolar_px_before=_float(sync.get("epipolar_px_before")),
        epipolar_px_after=_float(sync.get("epipolar_px_after")),
        fps_right=_float(sync.get("fps_right")),
    )


def _count(quality: Mapping[str, Any], *keys: str) -> int | None:
    """The sum of integer quality fields; None when none of them is there."""
    values = [_number(quality.get(k)) for k in keys]
    present = [int(v) for v in values if v is not None]
    return sum(present) if present else None


def _gap_cycles(doc: Mapping[str, Any]) -> int:
    """``cycles_in_gaps`` of the document's analysis part, 0 when absent or not a count."""
    analysis = _mapping(doc.get("tapping_analysis") or doc.get("cycle_analysis"))
    n = analysis.get("cycles_in_gaps")
    return n if isinstance(n, int) and not isinstance(n, bool) and n > 0 else 0


def read_result(document: Mapping[str, Any] | None) -> TrialResult:
    """Read a ``result.json`` document (see the module docstring)."""
    doc = document or {}
    sync = _mapping(doc.get("sync"))
    quality = _mapping(doc.get("quality"))
    taps = doc.get("taps")
    offset = _number(sync.get("offset_frames"))
    fps = _number(doc.get("fps"))

    def fraction(key: str) -> float | None:
        value = _number(quality.get(key))
        return None if value is None else float(value)

    warnings = quality.get("warnings")
    software = _mapping(doc.get("software"))
    cal_id = _number(_mapping(doc.get("calibration")).get("id"))
    return TrialResult(
        fps=float(fps) if fps else None,
        sync=_sync_summary(sync, offset),
        metrics=_numbers(doc.get("metrics")),
        metrics_first_10=_numbers(doc.get("metrics_first_10")),
        taps=tuple(tp for tp in _list(taps) if isinstance(tp, Mapping)),
        events=tuple(result_events(doc)),
        software_version=_text(software.get("version")),
        algorithm_version=_text(software.get("algorithm")),
        calibration_id=int(cal_id) if isinstance(cal_id, int) else None,
        task=_text(doc.get("task")) or "finger_tapping",
        cycles=tuple(c for c in _list(doc.get("cycles")) if isinstance(c, Mapping)),
        side=_text(_mapping(_mapping(doc.get("cycle_analysis")).get("signal")).get("side")),
        removed_cycles=len(_list(doc.get("excluded_taps")))
        + len(_list(doc.get("outside_window_taps"))),
        cycles_in_gaps=_gap_cycles(doc),
        quality=ResultQuality(
            tracked_fraction=fraction("tracked_fraction"),
            measured_fraction=fraction("measured_fraction"),
            interpolated_fraction=fraction("interpolated_fraction"),
            reprojection_px_median=fraction("reprojection_px_median"),
            reprojection_px_p95=fraction("reprojection_px_p95"),
            warnings=tuple(str(w) for w in _list(warnings)),
            set_aside_frames=_count(quality, "set_aside_frames_left", "set_aside_frames_right"),
            overlap_frames=_count(quality, "overlap_frames"),
            merged_measured_frames=_count(
                quality, "merged_measured_frames_left", "merged_measured_frames_right"
            ),
            frames=_count(quality, "frames_left"),
        ),
    )

"""When each frame of one recording was captured: the per-video half of the time model.

A frame's time is its capture time on that camera's own clock (INTERFACES.md):

- from a timestamps file given with the video (``frame,time_s`` CSV, what the
  capture page writes), when there is one;
- otherwise from the container's presentation timestamps when they carry
  per-frame information (variable frame rate: intervals that differ);
- otherwise ``i / fps`` from the first frame.

The decoder hands out the presentation timestamp of every frame it decodes
(``core.video.iter_frames(times_out=...)``; OpenCV's ``CAP_PROP_POS_MSEC``,
which gray frames from PyAV's decoder reproduce to the bit, agrees with the
container's own timestamps read by PyAV to the time base's resolution, which
``tests/core/test_timing.py`` checks), so timestamps cost nothing extra.

Lost frames show in timestamps that carry information as room in the time line
(:attr:`FrameTimes.dropped_after`): each frame is put in a slot of a regular grid
fitted to the times, and a frame is lost where the grid has a slot that no frame
takes. A late frame followed by an early one (53 ms then 14 ms at 33.7 ms) sits in
two consecutive slots, so jitter is not taken for lost frames. With constant
timestamps they are invisible here; :mod:`core.clock` finds them where the offset
between the cameras steps by whole frames.

The other half of the time model, how the right camera's clock maps to the
left one's, is :mod:`core.clock`.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core.errors import InputError

FloatArray = NDArray[np.float64]

#: Timestamps that deviate from a constant rate by more than this share of a
#: frame interval carry per-frame information (variable frame rate).
VFR_TOLERANCE = 0.05
#: Only times with an interval this many nominal intervals long (or longer) can hold
#: lost frames; where they do is said by the grid (:func:`_gaps`).
DROP_FACTOR = 1.5
#: The grid's period is searched within this share of the median interval.
GRID_SEARCH = 0.1

FROM_FILE = "file"
FROM_CONTAINER = "container"
FROM_FPS = "fps"


@dataclass(frozen=True)
class FrameTimes:
    """Capture times of the frames of one video, on that camera's own clock.

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Capture time of each frame (s), the first at 0; strictly increasing.
    fps : float
        Nominal frame rate (Hz): the container's for constant timestamps,
        ``1 / median interval`` otherwise.
    source : str
        ``"file"`` (timestamps file), ``"container"`` (variable frame rate
        presentation timestamps) or ``"fps"`` (``i / fps``).
    """

    t_s: FloatArray
    fps: float
    source: str = FROM_FPS
    _dropped: tuple[tuple[int, int], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, dtype=np.float64).reshape(-1)
        if t.size and not np.all(np.isfinite(t)):
            raise ValueError("frame times must be finite")
        if t.size > 1 and np.any(np.diff(t) <= 0):
            raise ValueError("frame times must increase strictly")
        if not (self.fps > 0 and np.isfinite(self.fps)):
            raise ValueError(f"fps must be positive, got {self.fps}")
        t = t - t[0] if t.size else t
        t.setflags(write=False)
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "_dropped", tuple(_gaps(t, self.fps)))

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def interval_s(self) -> float:
        """Nominal frame interval (s)."""
        return 1.0 / self.fps

    @property
    def variable(self) -> bool:
        """Whether the times carry per-frame information (not ``i / fps``)."""
        return self.source != FROM_FPS

    @property
    def dropped_after(self) -> list[int]:
        """Frame numbers after which frames were lost (one entry per lost frame)."""
        return [i for i, n in self._dropped for _ in range(n)]

    @property
    def gap_after(self) -> NDArray[np.bool_]:
        """``(T,)``: True where the interval to the next frame is a gap (lost frames)."""
        out = np.zeros(len(self.t_s), dtype=bool)
        for i, _ in self._dropped:
            out[i] = True
        return out

    def truncated(self, n: int) -> FrameTimes:
        """The times of the first ``n`` frames."""
        return FrameTimes(self.t_s[:n], self.fps, self.source)


def _gaps(t: FloatArray, fps: float) -> list[tuple[int, int]]:
    """``(frame, frames lost after it)`` by :func:`lost_after`."""
    lost = lost_after(t, fps)
    return [(int(i), int(lost[i])) for i in np.flatnonzero(lost)]


def lost_after(t_s: ArrayLike, fps: float) -> NDArray[np.int64]:
    """How many frames were lost after each frame: the slots of the grid fitted to the
    times (:func:`grid_slots`) that no frame takes before the next frame's.

    Times without an interval of ``DROP_FACTOR`` nominal intervals (``1 / fps``) have
    no room for a lost frame: none is looked for.

    Parameters
    ----------
    t_s : array_like, shape (T,)
        Capture times (s), strictly increasing.
    fps : float
        Nominal frame rate (Hz).

    Returns
    -------
    ndarray of int64, shape (T,)
        Frames lost between each frame and the next (0 for the last).
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    out = np.zeros(len(t), dtype=np.int64)
    if len(t) < 2 or float(np.max(np.diff(t))) * fps < DROP_FACTOR:
        return out
    out[:-1] = np.diff(grid_slots(t, fps)) - 1
    return out


def grid_slots(t_s: ArrayLike, fps: float) -> NDArray[np.int64]:
    """The slot of each frame in the regular grid that fits its capture times best.

    The grid ``a + k · period`` is fitted to the times, not to their intervals: its
    period is where the frames' phases agree best (the peak of
    ``|Σ exp(2πi t / period)|`` within ``GRID_SEARCH`` of ``1 / fps``, which neither
    lost frames nor jitter displace), then each frame's count of earlier lost frames
    ``c_i = k_i − i`` is the non-decreasing whole-number sequence nearest (least squares)
    to ``(t_i − a) / period − i`` (isotonic regression, rounded), and the grid is refitted
    to the slots by least squares (a clock running a little fast or slow), until the slots
    stay. A late frame and an early one after it pool to consecutive slots; a lost frame
    moves every later frame a period on, which the jitter of single frames does not.

    Parameters
    ----------
    t_s : array_like, shape (T,)
        Capture times (s), strictly increasing.
    fps : float
        Nominal frame rate (Hz), e.g. ``1 / median interval``.

    Returns
    -------
    ndarray of int64, shape (T,)
        Strictly increasing slots, the first 0.
    """
    # Imported here: scipy.optimize costs ~0.4 s, which the web app's start-up does not need.
    from scipy.optimize import isotonic_regression

    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    if not (fps > 0 and np.isfinite(fps)):
        raise ValueError(f"fps must be positive, got {fps}")
    n = len(t)
    if n < 2:
        return np.zeros(n, dtype=np.int64)
    t = t - t[0]
    freq, offset = _grid_by_phase(t, float(fps))
    index = np.arange(n)
    slots = index.astype(np.int64)
    for _ in range(5):
        ahead = isotonic_regression((t - offset) * freq - index).x
        lost = np.rint(ahead).astype(np.int64)
        new = index + lost - lost[0]
        if np.array_equal(new, slots):
            break
        slots = new
        period, offset = np.polyfit(slots, t, 1)
        freq = 1.0 / float(period)
    return slots


def _grid_by_phase(t: FloatArray, fps: float) -> tuple[float, float]:
    """The grid's frequency (Hz) and its time at slot 0 (s, within half a period of the
    first frame): the frequency within ``GRID_SEARCH`` of ``fps`` at which the frames'
    phases agree best, searched on the first frames' span first and narrowed on longer
    spans (the peak narrows as ``1 / span``)."""
    lo, hi = fps * (1 - GRID_SEARCH), fps * (1 + GRID_SEARCH)
    span = min(float(t[-1]), 1000.0 / fps)  # s: the first ~1000 frames' span first
    while True:
        part = t[t <= span]
        step = 0.25 / max(span, 1.0 / fps)  # Hz: a quarter of the peak's width
        freqs = np.arange(lo, hi + step, step)
        power = np.abs(np.exp(2j * np.pi * np.outer(freqs, part)).sum(axis=1))
        best = int(np.argmax(power))
        freq = float(freqs[best])
        if span >= t[-1]:
            break
        lo, hi = freq - 2 * step, freq + 2 * step
        span = min(float(t[-1]), 8 * span)
    phase = float(np.angle(np.exp(2j * np.pi * freq * t).sum()))
    return freq, phase / (2 * np.pi * freq)


def lost_frame_gaps(dropped_after: Sequence[int]) -> list[tuple[int, int]]:
    """``(frame, frames lost after it)`` of a list with one entry per lost frame
    (:attr:`FrameTimes.dropped_after`, ``sync.dropped_frames_*`` of result.json): a frame
    number repeated ``n`` times is one gap of ``n`` lost frames."""
    counts: dict[int, int] = {}
    for i in dropped_after:
        counts[int(i)] = counts.get(int(i), 0) + 1
    return sorted(counts.items())


def describe_lost_frames(
    dropped_after: Sequence[int], *, fps: float | None = None, most_gaps: int = 3
) -> str:
    """The lost frames of one camera in words, for a clinician or technician.

    ``dropped_after`` has one entry per lost frame (a frame number repeated for each
    frame lost after it). Up to ``most_gaps`` gaps are each named ("3 frames lost after
    frame 2 and 1 after frame 17"); more are summed up: how many frames in how many
    gaps, and the longest (its length in ms when ``fps``, the camera's nominal rate,
    is given: the time between the frames on either side of it) and where.
    """
    gaps = lost_frame_gaps(dropped_after)
    if not gaps:
        return "no frames lost"
    total = sum(n for _, n in gaps)

    def frames(n: int) -> str:
        return f"{n} frame{'s' if n != 1 else ''}"

    if len(gaps) <= most_gaps:
        parts = [f"{frames(n) if k == 0 else n} after frame {i}" for k, (i, n) in enumerate(gaps)]
        parts[0] = parts[0].replace(" after", " lost after", 1)
        return parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]
    at, longest = max(gaps, key=lambda g: (g[1], -g[0]))
    span = f" ({1000.0 * (longest + 1) / fps:.0f} ms)" if fps and fps > 0 else ""
    return (
        f"{frames(total)} lost in {len(gaps)} gaps; the longest, {frames(longest)}{span},"
        f" after frame {at}"
    )


def uniform_times(n_frames: int, fps: float) -> FrameTimes:
    """``i / fps`` for ``n_frames`` frames (constant frame rate)."""
    if n_frames < 0:
        raise ValueError(f"n_frames must be >= 0, got {n_frames}")
    return FrameTimes(np.arange(n_frames) / float(fps), float(fps), FROM_FPS)


def frame_times_from_timestamps(
    timestamps_s: ArrayLike, *, fps: float | None, name: str = "the video"
) -> FrameTimes:
    """The frame times of a video from the presentation timestamps of its decoded frames.

    Parameters
    ----------
    timestamps_s : array_like, shape (T,)
        Presentation timestamp of each decoded frame (s), in display order;
        NaN where the container gave none.
    fps : float or None
        The frame rate the container states (None or 0 if it states none).
    name : str
        The video's name, for messages.

    Returns
    -------
    FrameTimes
        ``source="container"`` when the timestamps deviate from a constant
        rate by more than ``VFR_TOLERANCE`` of an interval (variable frame
        rate, lost frames), else ``i / fps`` (``source="fps"``).

    Raises
    ------
    InputError
        Neither usable timestamps nor a frame rate.
    """
    ts = np.asarray(timestamps_s, dtype=np.float64).reshape(-1)
    n = len(ts)
    rate = float(fps) if fps is not None and np.isfinite(fps) and fps > 0 else None
    usable = n >= 2 and bool(np.all(np.isfinite(ts))) and bool(np.all(np.diff(ts) > 0))
    if not usable:
        if rate is None:
            raise InputError(
                f"{name} has neither frame timestamps nor a frame rate; give its capture times"
                " in a timestamps file (frame,time_s) or re-export it with a fixed frame rate."
            )
        return uniform_times(n, rate)
    t = ts - ts[0]
    dt = float(np.median(np.diff(t)))
    nominal = rate if rate is not None and abs(rate * dt - 1.0) < 0.02 else 1.0 / dt
    deviation = np.abs(t - np.arange(n) / nominal) * nominal
    if float(deviation.max()) <= VFR_TOLERANCE:
        return uniform_times(n, nominal)
    return FrameTimes(t, 1.0 / dt, FROM_CONTAINER)


def read_times_csv(path: str | Path, *, n_frames: int | None = None) -> FrameTimes:
    """Read a timestamps file: header ``frame,time_s``, one row per frame of the video.

    Parameters
    ----------
    path : str or Path
    n_frames : int, optional
        The number of frames of the video it belongs to; a file that covers a
        different number of frames (beyond two, the slack of damaged files)
        is refused.

    Raises
    ------
    InputError
        Missing file, wrong header, unparsable or non-increasing times,
        frame numbers that are not ``0, 1, 2, ...``, or a frame count that
        does not fit the video.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise InputError(f"cannot read the timestamps file {p.name}: {exc.strerror}.") from exc
    except UnicodeDecodeError as exc:
        raise InputError(f"{p.name} is not a text file; expected a frame,time_s CSV.") from exc
    rows = list(csv.reader(text.splitlines()))
    if not rows or [c.strip() for c in rows[0]][:2] != ["frame", "time_s"]:
        raise InputError(f"{p.name} must start with the header frame,time_s.")
    frames, times = [], []
    for k, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        try:
            frames.append(int(row[0]))
            times.append(float(row[1]))
        except (ValueError, IndexError) as exc:
            raise InputError(
                f"line {k} of {p.name} is not 'frame,time_s' with a whole frame number and a time"
                " in seconds."
            ) from exc
    if len(times) < 2:
        raise InputError(f"{p.name} holds fewer than two frame times.")
    if frames != list(range(len(frames))):
        raise InputError(f"the frame numbers of {p.name} must run 0, 1, 2, ... without gaps.")
    t = np.array(times)
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise InputError(f"the times of {p.name} must be finite and increase from frame to frame.")
    out = FrameTimes(t, 1.0 / float(np.median(np.diff(t))), FROM_FILE)
    if n_frames is not None:
        check_frame_count(out, n_frames, p.name)
    return out


def check_frame_count(times: FrameTimes, n_frames: int, name: str) -> None:
    """Refuse a timestamps file (``name``) whose frames are not its video's ``n_frames``,
    two frames of slack for a damaged container (:func:`read_times_csv`)."""
    if abs(len(times.t_s) - n_frames) > 2:
        raise InputError(
            f"{name} gives the times of {len(times.t_s)} frames but its video has {n_frames};"
            " give the timestamps file recorded with this video."
        )


def fit_to_frames(times: FrameTimes, n_frames: int) -> FrameTimes:
    """``times`` for exactly ``n_frames`` decoded frames (a damaged file may decode a
    frame or two fewer or more than its timestamps say): cut, or continued at the
    nominal rate."""
    n = len(times)
    if n >= n_frames:
        return times.truncated(n_frames)
    last = times.t_s[-1] if n else -times.interval_s
    extra = last + (np.arange(n_frames - n) + 1) * times.interval_s
    return FrameTimes(np.concatenate([times.t_s, extra]), times.fps, times.source)

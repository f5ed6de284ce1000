"""When each simulated camera captures its frames: free-running cameras.

The left camera's clock is the reference (the "true" time of the truth and of
the tapping model). Each camera captures frame ``k`` (counting every frame its
sensor took, lost ones included) at the true time

    T(k) = start_s + (1 + drift_ppm·1e-6) · k / fps + jitter_k

(``jitter_k ~ N(0, jitter_s)``); its own clock reads ``τ(k) = (T(k) − start_s)
/ (1 + drift_ppm·1e-6)``, so the map from the camera's clock to the left one is
``T = start_s + (1 + drift_ppm·1e-6) · τ`` exactly: the time model that
:mod:`core.clock` estimates. Frames listed in ``drop_after`` are lost (the
video holds the others), and the container's timestamps are either the
capture times ``τ`` (``vfr=True``: variable frame rate, lost frames show as
longer intervals) or ``i / fps`` over the frames that were written (constant
frame rate: a lost frame is invisible in the file, as with most webcams).

Rolling shutter: row ``y`` of a frame is read ``readout_s · (y / (H − 1) −
0.5)`` after the frame's time, so the frame's time is that of its middle row
(:func:`rolling_shutter_times` solves for the instant at which each marker is
on the row read at that instant).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from core.camera import Camera, ImageSize

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CameraTiming:
    """How one simulated camera runs.

    Attributes
    ----------
    fps : float or None
        Frame rate (Hz); None = the tapping scenario's.
    start_s : float
        True time (left camera's clock) of this camera's first frame (s).
    drift_ppm : float
        Clock-rate error: the true frame interval is ``(1 + drift_ppm·1e-6) / fps``.
    drop_after : tuple of int
        Frame numbers of the written video after which one frame was lost
        (repeat a number for several lost frames in a row).
    jitter_s : float
        Standard deviation of the capture-time jitter (s).
    vfr : bool
        The container's timestamps are the capture times (variable frame
        rate); otherwise ``i / fps``.
    readout_ms : float
        Rolling-shutter readout time, top row to bottom row (ms); 0 = global shutter.
    image_size : ImageSize or None
        This camera's image size; None = the imaging scenario's.
    """

    fps: float | None = None
    start_s: float = 0.0
    drift_ppm: float = 0.0
    drop_after: tuple[int, ...] = ()
    jitter_s: float = 0.0
    vfr: bool = False
    readout_ms: float = 0.0
    image_size: ImageSize | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "drop_after", tuple(sorted(int(v) for v in self.drop_after)))
        if self.image_size is not None:
            object.__setattr__(self, "image_size", ImageSize(*(int(v) for v in self.image_size)))
        if self.fps is not None and not (self.fps > 0 and np.isfinite(self.fps)):
            raise ValueError(f"fps must be positive, got {self.fps}")
        if not np.isfinite(self.start_s):
            raise ValueError(f"start_s must be finite, got {self.start_s}")
        if not abs(self.drift_ppm) <= 1e4:
            raise ValueError(f"drift_ppm must be within ±10000, got {self.drift_ppm}")
        if any(v < 0 for v in self.drop_after):
            raise ValueError(f"drop_after frame numbers must be >= 0, got {self.drop_after}")
        if not 0 <= self.jitter_s <= 0.01:
            raise ValueError(f"jitter_s must be in [0, 0.01] s, got {self.jitter_s}")
        if not 0 <= self.readout_ms <= 100:
            raise ValueError(f"readout_ms must be in [0, 100], got {self.readout_ms}")

    def to_dict(self) -> dict[str, object]:
        return {
            "fps": self.fps,
            "start_s": self.start_s,
            "drift_ppm": self.drift_ppm,
            "drop_after": list(self.drop_after),
            "jitter_s": self.jitter_s,
            "vfr": self.vfr,
            "readout_ms": self.readout_ms,
            "image_size": None if self.image_size is None else list(self.image_size),
        }


@dataclass(frozen=True)
class CameraClock:
    """The frames one camera wrote, and when.

    Attributes
    ----------
    true_s : ndarray, shape (T,)
        True capture time (left camera's clock) of each written frame (s):
        the instant of its middle row.
    stamp_s : ndarray, shape (T,)
        The timestamp the container holds for it (s).
    dropped_after : list of int
        Frame numbers (of the written video) after which frames were lost.
    fps : float
    """

    true_s: FloatArray
    stamp_s: FloatArray
    dropped_after: list[int]
    fps: float


def camera_clock(
    timing: CameraTiming, *, fps: float, duration_s: float, rng: np.random.Generator
) -> CameraClock:
    """The written frames of a camera running ``timing`` for ``duration_s`` seconds.

    ``round(duration_s · fps)`` frames are captured, less the lost ones. The
    jitter is drawn from ``rng`` (one value per captured frame), so the same
    seed gives the same clock.
    """
    rate = float(timing.fps if timing.fps is not None else fps)
    n_captured = round(duration_s * rate)
    scale = 1.0 + timing.drift_ppm * 1e-6
    n_written = n_captured - len(timing.drop_after)
    if n_written < 2 or (timing.drop_after and timing.drop_after[-1] >= n_written - 1):
        raise ValueError(
            f"frames lost after frame {', '.join(map(str, timing.drop_after))} do not fit a"
            f" video of {n_written} frames written (a lost frame must follow frame 0 to"
            f" {n_written - 2})"
        )
    jitter = rng.normal(0.0, timing.jitter_s, n_captured) if timing.jitter_s > 0 else 0.0
    # Written frame i is captured frame i + (frames lost before it).
    written = np.arange(n_written)
    captured = written + np.searchsorted(np.array(timing.drop_after, dtype=np.int64), written)
    own = (np.arange(n_captured) / rate + jitter / scale)[captured]  # the camera's own clock
    true_s = timing.start_s + scale * own
    stamp = own - own[0] if timing.vfr else written / rate
    return CameraClock(true_s, np.asarray(stamp), list(timing.drop_after), rate)


def rolling_shutter_times(
    cam: Camera,
    positions_at: object,
    t_frame_s: float,
    readout_s: float,
    n_points: int,
    *,
    iterations: int = 4,
) -> FloatArray:
    """The instant at which each of ``n_points`` moving points is read out by a rolling shutter.

    Row ``y`` is read at ``t_frame_s + readout_s · (y / (H − 1) − 0.5)``; a
    point is imaged on the row that is being read while it is there, found by
    fixed-point iteration (it converges in a few steps: a fingertip moves a
    few pixels during a readout that sweeps hundreds of rows).

    Parameters
    ----------
    cam : Camera
    positions_at : callable
        ``positions_at(t_s (N,)) -> (N, n_points, 3)`` world positions (mm).
    t_frame_s : float
        The frame's time (its middle row), s.
    readout_s : float
        Top row to bottom row (s).
    n_points : int

    Returns
    -------
    ndarray, shape (n_points,)
        Read-out instant of each point (s); ``t_frame_s`` where a point is
        not in front of the camera.
    """
    t = np.full(n_points, float(t_frame_s))
    if readout_s <= 0:
        return t
    height = cam.image_size.height
    idx = np.arange(n_points)
    for _ in range(iterations):
        pos = positions_at(t)[idx, idx]  # type: ignore[operator]
        y = cam.project(pos)[:, 1]
        y = np.where(np.isfinite(y), np.clip(y, 0.0, height - 1.0), 0.5 * (height - 1))
        t = t_frame_s + readout_s * (y / (height - 1) - 0.5)
    return t

"""When two board recordings were taken: the time offset of free-running calibration videos.

Two webcams or phones filming a calibration board start at different moments
and run on their own clocks, so frame ``i`` of one video and frame ``i`` of the
other show the board at different instants; while the board moves, they show
different poses and no rig fits them. This module finds the map between the
two clocks from the board detections that calibration has anyway (no frame is
decoded or searched again), and pairs each left view with the right camera's
board at the same instant. The clock map is ``core.clock``'s
(``docs/sync.md``):

    t_left = offset_s + (1 + drift_ppm · 1e-6) · t_right

with each camera's frame times from :mod:`core.timing` (0 at its first frame).

1. **Motion** (:func:`board_motion`): in each camera, how fast the board moves
   between consecutive searched frames, in board sizes per second (median
   corner displacement over the board's size in the image, so the two cameras
   see about the same value). Still moments are near zero, moves are large.
2. **Coarse offset** (:func:`estimate_offset`): the offset at which the two
   cameras' log-speeds correlate best, over ``±max_offset_s``, to a fraction
   of the spacing of the searched frames (parabola through the peak).
3. **Pairing** (:func:`right_at_left_instants`): the right corners at each
   left instant, interpolated linearly in time between the two searched right
   frames around it. A pair is kept only where the predicted error of that
   interpolation is small: the board's speed times the offset's uncertainty,
   plus the curvature of its path (second differences). With the coarse
   offset only still (or very slow) views pass; once
   :func:`core.calibration.calibrate_stereo` has a rig from them, it refines
   the offset by epipolar consistency and pairs again with a tighter
   uncertainty.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from core.boards import BoardDetection, BoardSpec
from core.camera import ImageSize

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Board speeds (board sizes per second) below this count as still in the log-speed.
SPEED_FLOOR = 0.01
#: Fewest consecutive-sample speeds both cameras must share at an offset.
MIN_OVERLAP = 8
#: A coarse offset is trusted when the log-speeds correlate at least this well.
MIN_CORRELATION = 0.3
#: Offsets whose score is within this share of the best are rival candidates.
RIVAL_SHARE = 0.9
#: How far (in spacings of the searched frames) the coarse offset may be off: the
#: signals are sampled at those frames, and a peak between them is found to about
#: half a spacing (tests/core/test_board_sync.py).
COARSE_UNCERTAINTY = 0.75
#: Interpolated right corners whose predicted error exceeds this (px) are not paired.
PAIR_TOLERANCE_PX = 0.1

SYNCHRONOUS = "synchronous"
ESTIMATED = "estimated"
IMAGES = "images"


@dataclass(frozen=True)
class BoardTrack:
    """One camera's board detections at the searched frames of a recording.

    Attributes
    ----------
    frames : ndarray, shape (S,), int64
        Frame numbers searched, increasing.
    t_s : ndarray, shape (S,)
        Their capture times on this camera's clock (s, 0 at frame 0).
    detections : tuple of BoardDetection or None
        ``S`` entries; None where the board was not found.
    edge_width_px : ndarray, shape (S,)
        Blur of each detection (:func:`core.calibration.edge_width_px`), NaN
        where not detected.
    fps : float
        The video's nominal frame rate (Hz).
    image_size : ImageSize
    """

    frames: IntArray
    t_s: FloatArray
    detections: tuple[BoardDetection | None, ...]
    edge_width_px: FloatArray
    fps: float
    image_size: ImageSize

    def __post_init__(self) -> None:
        n = len(self.frames)
        if len(self.t_s) != n or len(self.detections) != n or len(self.edge_width_px) != n:
            raise ValueError(
                f"a board track needs as many times, detections and widths as frames ({n})"
            )

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def detected(self) -> int:
        return sum(d is not None for d in self.detections)

    @property
    def sample_interval_s(self) -> float:
        """Median time between consecutive searched frames (s)."""
        if len(self.t_s) < 2:
            return 1.0 / self.fps
        return float(np.median(np.diff(self.t_s)))


@dataclass(frozen=True)
class BoardSync:
    """The time map of a pair of board recordings, as found.

    Attributes
    ----------
    offset_s : float
        Left time of the right camera's time 0 (s): ``t_left = offset_s +
        (1 + drift_ppm·1e-6) · t_right``.
    drift_ppm : float
        Right clock's rate error (not estimated from board recordings: 0,
        the nominal frame rates are taken as exact; see docs/calibration.md).
    fps_left : float
        The left video's frame rate (Hz), for :attr:`offset_frames`.
    method : {"synchronous", "estimated", "images"}
        ``"synchronous"``: the board motion says the frames were taken together
        (a lab rig) and frames are paired by number; ``"estimated"``: the
        cameras ran free and views are paired by the time map; ``"images"``:
        two image folders, paired by file-name order.
    uncertainty_s : float
        How far the offset may be off (s); sets which views can be paired.
    correlation : float
        Correlation of the two cameras' board speeds at the offset (NaN if not
        measured): near 1 when the motion lines up.
    refined : bool
        Whether the offset was refined by epipolar consistency with a fitted rig.
    candidates_s : tuple of float
        Rival offsets whose board speeds correlated almost as well (a board
        moved at a regular pace), best first.
    coarse_offset_s : float
        The offset found from the board's motion alone (NaN if none was).
    """

    offset_s: float
    drift_ppm: float = 0.0
    fps_left: float = 1.0
    method: str = SYNCHRONOUS
    uncertainty_s: float = 0.0
    correlation: float = float("nan")
    refined: bool = False
    candidates_s: tuple[float, ...] = field(default=())
    coarse_offset_s: float = float("nan")

    @property
    def offset_frames(self) -> float:
        """The offset in left frames: right frame ``j`` ↔ left frame ``j + offset_frames``."""
        return self.offset_s * self.fps_left

    @property
    def rate(self) -> float:
        return 1.0 + self.drift_ppm * 1e-6

    def left_to_right(self, t_left_s: FloatArray) -> FloatArray:
        return (np.asarray(t_left_s, dtype=np.float64) - self.offset_s) / self.rate

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready figures for ``rig.quality["sync"]``."""

        def rnd(x: float, nd: int) -> float | None:
            return round(float(x), nd) if np.isfinite(x) else None

        return {
            "method": self.method,
            "offset_s": rnd(self.offset_s, 5),
            "offset_frames": rnd(self.offset_frames, 3),
            "uncertainty_s": rnd(self.uncertainty_s, 5),
            "correlation": rnd(self.correlation, 3),
            "refined": self.refined,
        }


# ------------------------------------------------------------------ motion


def align_numbering(
    reference: BoardDetection, other: BoardDetection, board: BoardSpec
) -> BoardDetection:
    """``other`` numbered like ``reference`` (a chessboard may be numbered a half turn off).

    The numbering (as found, or a half turn off) whose common corners are
    nearer to the reference's is kept; ChArUco ids are unique and kept as they are.
    """
    if board.kind != "chessboard":
        return other
    flipped = other.flipped(board)
    return flipped if _mean_move(reference, flipped) < _mean_move(reference, other) else other


def _common_points(a: BoardDetection, b: BoardDetection) -> tuple[IntArray, FloatArray, FloatArray]:
    ids = np.intersect1d(a.ids, b.ids)
    return ids, a.corners_px[np.isin(a.ids, ids)], b.corners_px[np.isin(b.ids, ids)]


def _mean_move(a: BoardDetection, b: BoardDetection) -> float:
    ids, pa, pb = _common_points(a, b)
    if len(ids) == 0:
        return float("inf")
    return float(np.mean(np.linalg.norm(pb - pa, axis=1)))


def _board_scale_px(det: BoardDetection) -> float:
    """The board's size in the image: square root of its corners' hull area (px)."""
    hull = cv2.convexHull(det.corners_px.astype(np.float32))
    return float(np.sqrt(max(float(cv2.contourArea(hull)), 1.0)))


@dataclass(frozen=True)
class BoardMotion:
    """How the board moves between consecutive searched frames of one camera.

    Attributes
    ----------
    t_s : ndarray, shape (S - 1,)
        Mid-times of consecutive searched frames (s, this camera's clock).
    speed : ndarray, shape (S - 1,)
        Median corner displacement over the board's size in the image, per
        second (board sizes / s).
    velocity : ndarray, shape (S - 1, 4)
        Signed rates that two cameras looking the same way see alike: the
        board centre's image velocity ``x``, ``y`` (board sizes / s), the rate
        of change of the log of its image size (1/s: nearer or farther) and of
        the image angle of its rows (rad/s: turning in the image plane).

    All NaN where the board is missing in either frame or fewer than 4
    corners are common.
    """

    t_s: FloatArray
    speed: FloatArray
    velocity: FloatArray


def board_motion(track: BoardTrack, board: BoardSpec) -> BoardMotion:
    """How the board moves between consecutive searched frames of one camera."""
    n = len(track)
    t_mid = 0.5 * (track.t_s[1:] + track.t_s[:-1]) if n > 1 else np.zeros(0)
    speed = np.full(max(n - 1, 0), np.nan)
    velocity = np.full((max(n - 1, 0), 4), np.nan)
    cols = board.corner_grid[0]
    for s in range(n - 1):
        a, b = track.detections[s], track.detections[s + 1]
        if a is None or b is None:
            continue
        b = align_numbering(a, b, board)
        ids, pa, pb = _common_points(a, b)
        if len(ids) < 4:
            continue
        dt = float(track.t_s[s + 1] - track.t_s[s])
        scale_a = _board_scale_px(a)
        move = float(np.median(np.linalg.norm(pb - pa, axis=1)))
        speed[s] = move / scale_a / dt
        shift = (pb.mean(axis=0) - pa.mean(axis=0)) / scale_a
        grow = np.log(_board_scale_px(b) / scale_a)
        turn = _row_angle(ids, pb, cols) - _row_angle(ids, pa, cols)
        turn = (turn + np.pi) % (2 * np.pi) - np.pi
        velocity[s] = np.array([shift[0], shift[1], grow, turn]) / dt
    return BoardMotion(t_mid, speed, velocity)


def _row_angle(ids: IntArray, pts: FloatArray, cols: int) -> float:
    """Mean image angle (rad) of the board's rows: of the steps between neighbouring
    corners of one row, summed as vectors."""
    index = {int(k): n for n, k in enumerate(ids)}
    steps = [
        pts[index[k + 1]] - pts[n]
        for n, k in enumerate(ids.tolist())
        if (k + 1) % cols and k + 1 in index
    ]
    if not steps:
        return 0.0
    v = np.sum(steps, axis=0)
    return float(np.arctan2(v[1], v[0]))


def _sample_linear(t: FloatArray, values: FloatArray, at: FloatArray, max_gap: float) -> FloatArray:
    """``values`` ``(S,)`` or ``(S, C)`` (NaN = missing) linearly interpolated at ``at``;
    NaN outside, across missing neighbours, or where the neighbours are more than
    ``max_gap`` apart."""
    out = np.full((len(at), *values.shape[1:]), np.nan)
    if len(t) < 2:
        return out
    j = np.searchsorted(t, at, side="right") - 1
    ok = (j >= 0) & (j < len(t) - 1)
    j0 = np.where(ok, j, 0)
    j1 = j0 + 1
    gap = t[j1] - t[j0]
    ok &= gap <= max_gap
    f = np.where(ok, (at - t[j0]) / np.where(gap > 0, gap, 1.0), 0.0)
    if values.ndim > 1:
        f = f[:, None]
        ok = ok[:, None]
    vals = (1 - f) * values[j0] + f * values[j1]
    return np.where(ok, vals, np.nan)


def _standardised(values: FloatArray) -> FloatArray:
    """Each column minus its mean, over its standard deviation (NaN ignored)."""
    mean = np.nanmean(values, axis=0) if np.any(np.isfinite(values)) else 0.0
    std = np.nanstd(values, axis=0) if np.any(np.isfinite(values)) else 1.0
    return (values - mean) / np.where(std > 0, std, 1.0)


def estimate_offset(
    left: BoardTrack,
    right: BoardTrack,
    board: BoardSpec,
    *,
    max_offset_s: float | None = None,
) -> BoardSync:
    """The clock offset of two board recordings from the board's motion in each.

    The log board speeds (:func:`board_motion`; still moments at the floor
    ``SPEED_FLOOR``) of the right camera are shifted by each candidate offset,
    on a grid of a quarter of the searched frames' spacing over
    ``±max_offset_s`` (default: half the shorter recording), and correlated
    with the left ones (over all left samples, so that a shorter overlap
    scores less); the best score, refined by a parabola, is the offset, and
    other local maxima scoring within ``RIVAL_SHARE`` of it are its rivals.
    Drift is not estimated here.

    Returns
    -------
    BoardSync
        ``method="estimated"``, ``uncertainty_s`` ``COARSE_UNCERTAINTY`` times
        the spacing of the searched frames; ``correlation`` NaN when the board never moved in
        both cameras (nothing to measure: the caller pairs frames by number,
        which is right whenever the board stands still).
    """
    spacing = max(left.sample_interval_s, right.sample_interval_s)
    motion_l, motion_r = board_motion(left, board), board_motion(right, board)
    tl, sl = motion_l.t_s, motion_l.speed
    tr, sr = motion_r.t_s, motion_r.speed
    duration = min(
        float(left.t_s[-1]) if len(left) else 0.0, float(right.t_s[-1]) if len(right) else 0.0
    )
    if max_offset_s is None:
        max_offset_s = 0.5 * duration
    step = 0.25 * spacing
    n_steps = int(np.floor(max_offset_s / step))
    offsets = np.arange(-n_steps, n_steps + 1) * step
    unmeasured = BoardSync(
        0.0,
        fps_left=left.fps,
        method=ESTIMATED,
        uncertainty_s=spacing,
        correlation=float("nan"),
    )
    moving_l = np.isfinite(sl) & (sl > 10 * SPEED_FLOOR)
    moving_r = np.isfinite(sr) & (sr > 10 * SPEED_FLOOR)
    if not np.any(moving_l) or not np.any(moving_r):
        return unmeasured
    # Scores: the products of the standardised signals (log-speed and the four signed
    # rates), summed over the overlap and divided by all left samples (a shorter
    # overlap scores less); the Pearson correlation over the overlap is the
    # confidence reported.
    feats_l = _standardised(np.column_stack([np.log(sl + SPEED_FLOOR), motion_l.velocity]))
    feats_r = _standardised(np.column_stack([np.log(sr + SPEED_FLOOR), motion_r.velocity]))
    valid_l = np.all(np.isfinite(feats_l), axis=1)
    n_valid = int(valid_l.sum())
    score = np.full(len(offsets), np.nan)
    pearson = np.full(len(offsets), np.nan)
    for n, off in enumerate(offsets):
        z = _sample_linear(tr, feats_r, tl[valid_l] - off, 1.5 * right.sample_interval_s)
        ok = np.all(np.isfinite(z), axis=1)
        if ok.sum() < max(MIN_OVERLAP, 0.25 * n_valid):
            continue
        a = feats_l[valid_l][ok].ravel()
        b = z[ok].ravel()
        score[n] = float(np.sum(a * b)) / (n_valid * feats_l.shape[1])
        sa, sb = float(np.std(a)), float(np.std(b))
        if sa > 0 and sb > 0:
            pearson[n] = float(np.mean((a - a.mean()) * (b - b.mean()))) / (sa * sb)
    if not np.any(np.isfinite(score)):
        return unmeasured
    best = int(np.nanargmax(score))
    peak = float(score[best])
    offset = float(offsets[best])
    if 0 < best < len(offsets) - 1 and np.all(np.isfinite(score[best - 1 : best + 2])):
        y0, y1, y2 = score[best - 1 : best + 2]
        denom = y0 - 2 * y1 + y2
        if denom < 0:
            offset += float(np.clip(0.5 * (y0 - y2) / denom, -0.5, 0.5)) * step
    # Rival peaks: local maxima away from the best that correlate almost as well.
    rivals = []
    c = np.where(np.isfinite(score), score, -np.inf)
    for n in range(1, len(c) - 1):
        if c[n] >= c[n - 1] and c[n] >= c[n + 1] and abs(offsets[n] - offsets[best]) > 2 * spacing:
            if c[n] >= RIVAL_SHARE * peak:
                rivals.append((float(c[n]), float(offsets[n])))
    return BoardSync(
        offset,
        fps_left=left.fps,
        method=ESTIMATED,
        uncertainty_s=COARSE_UNCERTAINTY * spacing,
        correlation=float(pearson[best]),
        candidates_s=tuple(o for _, o in sorted(rivals, reverse=True)),
        coarse_offset_s=offset,
    )


# ------------------------------------------------------------------ pairing


@dataclass(frozen=True)
class RightAtLeft:
    """The right camera's board at one left instant.

    Attributes
    ----------
    left_index : int
        Index into the left track.
    detection : BoardDetection
        The right corners at that instant (interpolated, or one searched frame's).
    error_px : float
        Predicted error of the interpolation (px): the largest over the corners.
    right_indices : tuple of int
        The right track's samples it was interpolated from.
    """

    left_index: int
    detection: BoardDetection
    error_px: float
    right_indices: tuple[int, ...]


def right_at_left_instants(
    left: BoardTrack,
    right: BoardTrack,
    board: BoardSpec,
    sync: BoardSync,
    *,
    tolerance_px: float = PAIR_TOLERANCE_PX,
    left_indices: Sequence[int] | None = None,
) -> list[RightAtLeft]:
    """The right board at the instants of the left detections, where it can be told well.

    For left sample ``k`` the right-clock instant is ``sync.left_to_right(t_k)``;
    the right corners there are interpolated linearly between the searched
    right frames before and after it (a frame within 1 % of a frame interval
    is used as it is). The predicted error of a corner is its speed times
    ``sync.uncertainty_s`` plus ``f (1 − f) / 2`` times the larger second
    difference of its path at the two frames, the smaller of the two (linear
    interpolation of a curved path); pairs whose largest predicted error exceeds ``tolerance_px``
    are left out, as are instants outside the right recording.

    Returns
    -------
    list of RightAtLeft
        In left order, only where a pair is kept.
    """
    if tolerance_px <= 0:
        raise ValueError(f"tolerance_px must be positive, got {tolerance_px}")
    indices = range(len(left)) if left_indices is None else left_indices
    t_right = right.t_s
    max_gap = 1.5 * right.sample_interval_s + 1e-9
    exact = 0.01 / right.fps
    out: list[RightAtLeft] = []
    for k in indices:
        if left.detections[k] is None:
            continue
        tau = float(sync.left_to_right(np.array([left.t_s[k]]))[0])
        j = int(np.searchsorted(t_right, tau, side="right")) - 1
        if j < 0 or j >= len(right):
            continue
        if abs(tau - t_right[j]) <= exact or (
            j + 1 < len(right) and abs(tau - t_right[j + 1]) <= exact
        ):
            jj = j if abs(tau - t_right[j]) <= exact else j + 1
            found = _at_frame(right, board, jj, sync.uncertainty_s)
            if found is not None and found[1] <= tolerance_px:
                out.append(RightAtLeft(k, found[0], found[1], (jj,)))
            continue
        if j + 1 >= len(right) or t_right[j + 1] - t_right[j] > max_gap:
            continue
        found = _between_frames(right, board, j, tau, sync.uncertainty_s)
        if found is not None and found[1] <= tolerance_px:
            out.append(RightAtLeft(k, found[0], found[1], (j, j + 1)))
    return out


def _aligned(
    track: BoardTrack, board: BoardSpec, ref: BoardDetection, j: int
) -> BoardDetection | None:
    d = track.detections[j] if 0 <= j < len(track) else None
    return None if d is None else align_numbering(ref, d, board)


def _points(det: BoardDetection | None, ids: IntArray) -> FloatArray | None:
    """The corners of ``ids`` in ``det`` (all present), else None."""
    if det is None or not np.all(np.isin(ids, det.ids)):
        return None
    return det.corners_px[np.isin(det.ids, ids)]


def _at_frame(
    track: BoardTrack, board: BoardSpec, j: int, uncertainty_s: float
) -> tuple[BoardDetection, float] | None:
    """Searched frame ``j`` as it is, with the error the offset's uncertainty may cause."""
    det = track.detections[j]
    if det is None:
        return None
    speeds = []
    for nb in (j - 1, j + 1):
        other = _aligned(track, board, det, nb)
        if other is None:
            continue
        ids, p0, p1 = _common_points(det, other)
        if len(ids) == len(det):
            dt = abs(float(track.t_s[nb] - track.t_s[j]))
            speeds.append(np.linalg.norm(p1 - p0, axis=1).max() / dt)
    if not speeds:
        # No neighbour tells the speed: usable only when the offset is exact.
        return (det, 0.0) if uncertainty_s == 0 else None
    return det, float(max(speeds)) * uncertainty_s


def _between_frames(
    track: BoardTrack, board: BoardSpec, j: int, tau: float, uncertainty_s: float
) -> tuple[BoardDetection, float] | None:
    """The corners at right-clock instant ``tau`` between searched frames ``j`` and ``j + 1``."""
    d0 = track.detections[j]
    if d0 is None:
        return None
    d1 = _aligned(track, board, d0, j + 1)
    if d1 is None:
        return None
    ids, p0, p1 = _common_points(d0, d1)
    if len(ids) < 4:
        return None
    t0, t1 = float(track.t_s[j]), float(track.t_s[j + 1])
    f = (tau - t0) / (t1 - t0)
    pts = (1 - f) * p0 + f * p1
    step = np.linalg.norm(p1 - p0, axis=1)
    # Curvature of the path: second differences at j and j + 1, where the neighbours exist.
    curv = []
    pm = _points(_aligned(track, board, d0, j - 1), ids)
    pp = _points(_aligned(track, board, d0, j + 2), ids)
    if pm is not None:
        curv.append(np.linalg.norm(p1 - 2 * p0 + pm, axis=1))
    if pp is not None:
        curv.append(np.linalg.norm(pp - 2 * p1 + p0, axis=1))
    if curv:
        # The smaller one: a move that ends at j (or starts at j + 1) bends the path
        # outside the interval, not inside it.
        bend = np.min(np.vstack(curv), axis=0)
    elif float(step.max()) <= 0.25 * PAIR_TOLERANCE_PX:
        bend = step  # still at both ends: no move in between is likely
    else:
        return None  # moving, and nothing tells how straight the path is
    error = step / (t1 - t0) * uncertainty_s + 0.5 * f * (1 - f) * bend
    det = BoardDetection(
        ids=ids,
        corners_px=pts,
        object_points_mm=board.object_points()[ids],
        image_size=d0.image_size,
    )
    return det, float(error.max())

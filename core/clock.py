"""The time model of a stereo recording: how the right camera's clock maps to the left one's.

Free-running cameras (two webcams, two phones) start at different moments, run
on their own clocks, lose frames under load and may read the sensor out row by
row. The model (``docs/sync.md``):

    t_left = offset_s + (1 + drift_ppm · 1e-6) · t_right

where ``t_left`` and ``t_right`` are capture times on each camera's clock
(:mod:`core.timing`: from a timestamps file, the container's timestamps or
``i / fps``), corrected for lost frames that constant timestamps do not show
(each such loss adds one frame interval to all later frames of that camera).

Estimation (epipolar consistency over the whole recording, as in
:mod:`core.sync`):

1. a whole-frame offset over ``±max_offset_s`` (nearest-frame pairing, no
   drift): :func:`core.sync.estimate_offset` for two constant-rate cameras at
   one rate, the same cost on capture times otherwise;
2. in windows of ``WINDOW_S`` seconds, the local offset to a small fraction of
   a frame: the right markers' 2D tracks are interpolated to the left
   instants (cubic in time, :func:`points_at_times`) at offsets around the
   whole-frame one, and the minimum of the epipolar cost is refined with a
   parabola;
3. local offsets that differ by whole frames mark lost frames (constant
   timestamps); each loss is placed at the frame where the cost says it is,
   and ``offset_s`` and ``drift_ppm`` are the weighted least-squares line
   through the local offsets with the losses taken out.

Then every left frame's instant is mapped to the right clock and the right
markers are interpolated there (sub-frame, along their 2D tracks), so the two
cameras are triangulated at common instants; no position is invented across
a gap of lost frames or beyond a track's ends.

Rolling shutter (``Camera.readout_ms``): a detection at image row ``y`` was
taken ``readout · (y / (H − 1) − 0.5)`` after its frame's time (the middle
row's). The left detections are interpolated along their own tracks to their
frame's instant, and the right tracks are interpolated in the detections' own
instants, so both cameras are measured at the left frame's instant.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from core.camera import Camera, StereoRig
from core.errors import DetectionError
from core.geometry_kernels import _geometry
from core.sync import (
    MAX_POINTS_PER_FRAME,
    SyncEstimate,
    _epipolar_costs,
    _flatten,
    _ranks,
    _select_frames,
    estimate_offset,
    given_offset,
    link_points,
)
from core.timing import FrameTimes, lost_after, uniform_times

FloatArray = NDArray[np.float64]

#: Length of the windows in which the local offset is measured (s).
WINDOW_S = 0.5
#: Offsets (frames of the right camera) searched around a window's whole-frame offset.
FINE_RANGE = 1.0
FINE_STEP = 0.1
#: The model is applied (instead of pairing whole frames) when it moves any
#: frame by at least this share of a frame interval.
MODEL_MIN_FRAMES = 0.05
#: Windows whose cost curvature is below this share of the median are not used.
MIN_WINDOW_WEIGHT = 0.25
#: Confidence below which the automatic estimate is not trusted.
MIN_CONFIDENCE = 0.2
#: The two videos show the same motion at no offset when fewer than this share
#: of the moving left detections lie on an epipolar line of the right ones.
MIN_CONSISTENT = 0.25
#: ... and when no offset stands out (confidence below MIN_CONFIDENCE) while fewer than this
#: share agree at the best one: two unrelated recordings of a hand at the same place (their
#: closures meet the epipolar lines now and then; 34 % in tests/app/test_cli_analyze.py).
MIN_CONSISTENT_UNSURE = 0.5
GATE_PX = 3.0
#: More lost frames than this, or a larger clock difference, gets a warning.
#: The epipolar residual after synchronisation (px) above which the offset is doubted: a
#: calibrated rig gives 0.03-0.1 px on the simulator; an offset a tap period off (a true
#: one beyond the ±``max_offset_s`` searched) gave 1.5 px, its markers still mostly
#: within the gate.
DOUBTFUL_EPIPOLAR_PX = 1.0
LARGE_DROPS = 5
LARGE_DRIFT_PPM = 1000.0


@dataclass(frozen=True)
class ClockModel:
    """The map from the right camera's clock to the left one's.

    Attributes
    ----------
    offset_s : float
        Left time of the right camera's time 0 (s).
    drift_ppm : float
        Right clock's rate error: ``t_left = offset_s + (1 + drift_ppm·1e-6) · t_right``.
    dropped_left, dropped_right : tuple of int
        Frame numbers (each camera's own) after which a frame was lost and the
        timestamps do not show it (one entry per lost frame).
    """

    offset_s: float
    drift_ppm: float = 0.0
    dropped_left: tuple[int, ...] = ()
    dropped_right: tuple[int, ...] = ()

    @property
    def rate(self) -> float:
        return 1.0 + self.drift_ppm * 1e-6

    def right_to_left(self, t_right_s: FloatArray) -> FloatArray:
        return self.offset_s + self.rate * np.asarray(t_right_s, dtype=np.float64)

    def left_to_right(self, t_left_s: FloatArray) -> FloatArray:
        return (np.asarray(t_left_s, dtype=np.float64) - self.offset_s) / self.rate


def corrected_times(times: FrameTimes, dropped_after: Sequence[int]) -> FloatArray:
    """Capture times with the hidden lost frames put back: each adds an interval after it."""
    t = np.array(times.t_s, dtype=np.float64)
    for i in dropped_after:
        t[i + 1 :] += times.interval_s
    return t


# ------------------------------------------------------------------- 2D tracks in time


@dataclass(frozen=True)
class TrackTable:
    """The detections of one camera, flat, linked into 2D tracks, with their instants.

    Attributes
    ----------
    points : ndarray, shape (N, 2)
        All detections (px), frame by frame.
    starts : ndarray, shape (T + 1,)
        Frame ``j`` holds ``points[starts[j]:starts[j + 1]]``.
    nxt, prv : ndarray, shape (N,)
        Flat index of each detection's successor / predecessor, or -1.
    frame_t : ndarray, shape (T,)
        Frame times (s, the camera's clock, lost frames put back).
    point_t : ndarray, shape (N,)
        Each detection's own instant (s): its frame's time plus the rolling-shutter delay of its row.
    gap_after : ndarray, shape (T,) of bool
        Frames after which frames were lost (no interpolation across).
    """

    points: FloatArray
    starts: NDArray[np.intp]
    nxt: NDArray[np.intp]
    prv: NDArray[np.intp]
    frame_t: FloatArray
    point_t: FloatArray
    gap_after: NDArray[np.bool_]


def row_delay_s(cam: Camera, points_px: FloatArray) -> FloatArray:
    """Rolling-shutter delay (s) of detections at ``points_px`` ``(N, 2)`` relative to the middle row."""
    if cam.readout_ms <= 0:
        return np.zeros(len(points_px))
    h = cam.image_size.height
    return cam.readout_ms * 1e-3 * (points_px[:, 1] / (h - 1) - 0.5)


@dataclass(frozen=True)
class _Tracks:
    """One camera's detections, flat, with their 2D tracks before any gap of lost frames cuts
    them: what a :class:`TrackTable` keeps whatever the frame times (made once per camera)."""

    points: FloatArray
    counts: NDArray[np.intp]
    starts: NDArray[np.intp]
    nxt: NDArray[np.intp]
    prv: NDArray[np.intp]
    frame: NDArray[np.intp]  # each detection's frame
    delay_s: FloatArray  # each detection's rolling-shutter delay (row_delay_s)


def _tracks(
    points_px: Sequence[FloatArray], *, camera: Camera, links: Sequence[NDArray[np.intp]]
) -> _Tracks:
    pts, counts = _flatten(points_px)
    n = len(counts)
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.intp)
    nxt = np.full(len(pts), -1, dtype=np.intp)
    if n > 1:
        local = np.concatenate([np.asarray(links[j], dtype=np.intp) for j in range(n - 1)])
        frame = np.repeat(np.arange(n - 1), counts[:-1])
        linked = local >= 0
        nxt[: starts[n - 1]][linked] = starts[frame[linked] + 1] + local[linked]
    prv = np.full(len(pts), -1, dtype=np.intp)
    has = nxt >= 0
    prv[nxt[has]] = np.flatnonzero(has)
    frame_of = np.repeat(np.arange(n, dtype=np.intp), counts)
    return _Tracks(pts, counts, starts, nxt, prv, frame_of, row_delay_s(camera, pts))


def _table_at(tracks: _Tracks, frame_t: FloatArray, gap: NDArray[np.bool_]) -> TrackTable:
    """The :class:`TrackTable` of ``tracks`` at frame times ``frame_t``: tracks cut after
    the frames where ``gap`` ``(T,)`` says frames were lost."""
    nxt, prv = tracks.nxt.copy(), tracks.prv.copy()
    has = nxt >= 0
    frame_t = np.asarray(frame_t, dtype=np.float64)
    # No track crosses a gap of lost frames.
    cross = has & gap[tracks.frame]
    prv[nxt[cross]] = -1
    nxt[cross] = -1
    point_t = np.repeat(frame_t, tracks.counts) + tracks.delay_s
    return TrackTable(tracks.points, tracks.starts, nxt, prv, frame_t, point_t, gap)


def track_table(
    points_px: Sequence[FloatArray],
    frame_t: FloatArray,
    *,
    camera: Camera,
    links: Sequence[NDArray[np.intp]],
    interval_s: float,
) -> TrackTable:
    """One camera's detections with their 2D tracks (``links``, :func:`core.sync.link_points`)
    and their instants; tracks are cut at gaps of lost frames (the grid of
    :func:`core.timing.lost_after`: a late frame followed by an early one is no gap)."""
    gap = lost_after(frame_t, 1.0 / interval_s) > 0
    return _table_at(_tracks(points_px, camera=camera, links=links), frame_t, gap)


def points_at_times(
    table: TrackTable, t_s: FloatArray, *, exact_tol_s: float = 1e-9
) -> tuple[FloatArray, NDArray[np.intp]]:
    """Detections of one camera interpolated along their 2D tracks to given instants.

    For an instant ``t`` between frames ``j`` and ``j + 1``, each detection of
    frame ``j`` linked to one in frame ``j + 1`` is interpolated with the
    Lagrange polynomial through its samples at their own instants (cubic
    through ``j − 1 .. j + 2`` when the track has them, else quadratic through
    three; a track of two samples gives nothing: a straight line would be off
    by a millimetre at tapping accelerations). Nothing is given across a gap
    of lost frames, before the first frame or after the last. An instant that
    is a frame's time (global shutter) gives that frame's detections as they are.
    The loop over instants and points is compiled (:func:`core._geometry.points_at_times`,
    the numpy formulation's arithmetic: ``tests/core/geometry_reference.py`` keeps it and a
    test compares).

    Parameters
    ----------
    table : TrackTable
    t_s : ndarray, shape (S,)
        Instants (s, this camera's clock with lost frames put back).

    Returns
    -------
    points : ndarray, shape (M, 2)
        The points of all instants, in the order of ``t_s`` (px).
    counts : ndarray, shape (S,)
        Number of points of each instant.
    """
    ft = table.frame_t
    n = len(ft)
    t = np.ascontiguousarray(t_s, dtype=np.float64)
    if n == 0 or len(t) == 0:
        return np.zeros((0, 2)), np.zeros(len(t), dtype=np.intp)
    j = (np.searchsorted(ft, t, side="right") - 1).astype(np.intp)
    return _geometry.points_at_times(
        table.points,
        table.starts,
        table.nxt,
        table.prv,
        ft,
        table.point_t,
        table.gap_after.view(np.uint8),
        t,
        j,
        exact_tol_s,
    )


def _split(points: FloatArray, counts: NDArray[np.intp]) -> list[FloatArray]:
    return list(np.split(points, np.cumsum(counts)[:-1])) if len(counts) else []


# ------------------------------------------------------------------- costs


@dataclass(frozen=True)
class _Scene:
    """What the cost of a clock model needs, computed once."""

    rig: StereoRig
    left: tuple[FloatArray, NDArray[np.intp]]  # flat normalized left points, per-frame counts
    left_t: FloatArray  # left frame instants (s, lost frames put back)
    right_table: TrackTable
    f_left: float
    f_right: float


def _frame_costs(
    scene: _Scene, frames: NDArray[np.intp], query_t: FloatArray, *, missing_cost: float = 1.0
) -> tuple[FloatArray, NDArray[np.intp], FloatArray]:
    """Truncated epipolar cost of left frames against the right points interpolated at given instants.

    Parameters
    ----------
    frames : ndarray, shape (F,)
        Left frames (ascending).
    query_t : ndarray, shape (C, F)
        For each candidate ``c``, the right-clock instant of each frame.
    missing_cost : float
        Cost of a left detection without right points to compare with (the
        truncated cost is at most 1).

    Returns
    -------
    costs : ndarray, shape (C, F)
        Sum over the frame's left detections of ``min(d, gate)² / gate²``.
    n_points : ndarray, shape (F,)
        Left detections of each frame.
    d_min : ndarray, shape (C, L)
        Epipolar distance of each left detection to its nearest partner (px).
    """
    n_c, n_f = query_t.shape
    pts_px, counts = points_at_times(scene.right_table, query_t.ravel())
    if len(pts_px):
        pts_norm = scene.rig.right.undistort_points(pts_px)
    else:
        pts_norm = np.zeros((0, 2))
    keep = _ranks(counts) < MAX_POINTS_PER_FRAME
    right = (pts_norm[keep], np.minimum(counts, MAX_POINTS_PER_FRAME))
    l_pts, l_frame = _select_frames(scene.left, frames)
    pos = np.searchsorted(frames, l_frame)
    r_row = pos[None, :] + (n_f * np.arange(n_c))[:, None]
    cost, d_min = _cost_matrix(scene, l_pts, right, r_row)
    cost[np.isinf(d_min)] = missing_cost
    out = np.zeros((n_c, n_f))
    for c in range(n_c):
        out[c] = np.bincount(pos, weights=cost[c], minlength=n_f)
    return out, np.bincount(pos, minlength=n_f).astype(np.intp), d_min


def _cost_matrix(
    scene: _Scene,
    l_pts: FloatArray,
    right: tuple[FloatArray, NDArray[np.intp]],
    r_row: NDArray[np.intp],
) -> tuple[FloatArray, FloatArray]:
    """Per left detection and candidate: truncated cost and nearest epipolar distance (px)."""
    d_min = _nearest_epipolar_px(scene.rig, l_pts, right, r_row)
    cost = np.minimum(d_min, GATE_PX) ** 2 / GATE_PX**2
    return cost, d_min


def _nearest_epipolar_px(
    rig: StereoRig,
    l_pts: FloatArray,
    right: tuple[FloatArray, NDArray[np.intp]],
    rows: NDArray[np.intp],
) -> FloatArray:
    """Symmetric epipolar distance (px) of each left point to the nearest right point of its row.

    ``rows`` is ``(L,)`` (one right row per left point) or ``(C, L)`` (one set per
    candidate, all at once); the result has its shape. Each point's epipolar line is
    computed once, whatever the number of candidates and pairs it takes part in; the
    pairs are one compiled loop (:func:`core._geometry.nearest_epipolar`, numpy's
    arithmetic in numpy's order: the former numpy formulation's bits, a test compares).
    """
    r_pts, r_counts = right
    E = rig.essential_matrix
    n_l = len(l_pts)
    flat_rows = np.ascontiguousarray(rows, dtype=np.intp).ravel()
    if len(flat_rows) == 0 or n_l == 0:
        return np.full(np.shape(rows), np.inf)
    line_r = np.column_stack([l_pts, np.ones(n_l)]) @ E.T  # lines in the right image
    line_l = np.column_stack([r_pts, np.ones(len(r_pts))]) @ E  # lines in the left image
    norm_r = np.sqrt(line_r[:, 0] * line_r[:, 0] + line_r[:, 1] * line_r[:, 1])
    norm_l = np.sqrt(line_l[:, 0] * line_l[:, 0] + line_l[:, 1] * line_l[:, 1])
    counts = np.ascontiguousarray(r_counts, dtype=np.intp)
    starts = (np.cumsum(counts) - counts).astype(np.intp)
    out = _geometry.nearest_epipolar(
        np.ascontiguousarray(line_r),
        norm_r,
        np.ascontiguousarray(r_pts, dtype=np.float64).reshape(-1, 2),
        norm_l,
        starts,
        counts,
        flat_rows,
        _focal(rig.right),
        _focal(rig.left),
    )
    return out.reshape(np.shape(rows))


# ------------------------------------------------------------------- estimation


@dataclass(frozen=True)
class TimeModelResult:
    """The synchronisation of a stereo recording, ready for triangulation.

    Attributes
    ----------
    left_px, right_px : list of ndarray
        Per left frame, the detections of each camera at that frame's instant
        (px). When ``pairing_offset`` is not None they are the detections as
        found, per each camera's own frame.
    pairing_offset : int or None
        Whole-frame pairing (left ``i`` with right ``i - K``) when the time
        model is a whole-frame offset (a lab rig); None when ``right_px`` is
        already per left frame.
    left_time_s : ndarray, shape (T,)
        Capture time of each left frame (s, left clock, lost frames put back).
    sync : dict
        The ``sync`` object of result.json.
    warnings : list of str
    """

    left_px: list[FloatArray]
    right_px: list[FloatArray]
    pairing_offset: int | None
    left_time_s: FloatArray
    sync: dict[str, Any]
    warnings: list[str] = field(default_factory=list)
    model: ClockModel | None = None


def _focal(cam: Camera) -> float:
    return 0.5 * float(cam.K[0, 0] + cam.K[1, 1])


def _coarse_offset_s(
    scene_left: tuple[FloatArray, NDArray[np.intp]],
    left_t: FloatArray,
    right_norm: tuple[FloatArray, NDArray[np.intp]],
    right_t: FloatArray,
    rig: StereoRig,
    max_offset_s: float,
    step_s: float,
) -> tuple[float, float, FloatArray, FloatArray]:
    """Whole-frame offset on capture times: left frame i paired with the right frame nearest
    ``t_left[i] − offset``. Returns (offset_s, confidence, offsets, costs)."""
    t_left = len(scene_left[1])
    frames = np.unique(np.linspace(0, t_left - 1, min(t_left, 400)).round().astype(int))
    offsets = np.arange(-np.ceil(max_offset_s / step_s), np.ceil(max_offset_s / step_s) + 1)
    offsets = offsets * step_s
    l_pts, l_frame = _select_frames(scene_left, frames)
    q = left_t[l_frame][None, :] - offsets[:, None]
    j = np.clip(np.searchsorted(right_t, q), 1, len(right_t) - 1)
    nearer_prev = (q - right_t[j - 1]) < (right_t[j] - q)
    row = np.where(nearer_prev, j - 1, j)
    dt = np.abs(right_t[row] - q)
    row[(dt > 0.75 * step_s) & (dt > 0.75 * np.median(np.diff(right_t)))] = -1
    costs, n_points = _epipolar_costs(
        rig.essential_matrix, l_pts, right_norm, row, _focal(rig.left), _focal(rig.right), GATE_PX
    )
    costs = np.where(n_points >= max(10, len(frames) // 10), costs, np.nan)
    if not np.any(np.isfinite(costs)):
        return 0.0, 0.0, offsets, costs
    best = int(np.nanargmin(costs))
    far = np.abs(offsets - offsets[best]) >= 1.9 * step_s
    second = np.nanmin(costs[far]) if np.any(far & np.isfinite(costs)) else np.nan
    conf = float(np.clip(1 - costs[best] / second, 0, 1)) if second > 0 else 0.0
    return float(offsets[best]), conf, offsets, costs


def _windows(left_t: FloatArray) -> list[NDArray[np.intp]]:
    """Left frame indices split into consecutive windows of about ``WINDOW_S``."""
    n = len(left_t)
    if n == 0:
        return []
    edges = np.arange(left_t[0], left_t[-1] + WINDOW_S, WINDOW_S)
    k = np.searchsorted(edges, left_t, side="right") - 1
    return [np.flatnonzero(k == w) for w in range(len(edges)) if np.any(k == w)]


def _local_offsets(
    scene: _Scene,
    windows: list[NDArray[np.intp]],
    model: ClockModel,
    right_interval_s: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per window: the local offset (s) relative to ``model``, its weight and centre time.

    The local offset ``u`` is found among ``model.offset_s + u`` (right
    frames of ±``FINE_RANGE`` plus whole frames of ±2), first by whole right
    frames, then in steps of ``FINE_STEP`` frames around the best, refined by a
    parabola. Weight: the cost curvature times the moving detections (0 when
    the window has no minimum).
    """
    n_w = len(windows)
    u = np.full(n_w, np.nan)
    weight = np.zeros(n_w)
    centre = np.array([float(np.mean(scene.left_t[w])) for w in windows])
    whole = np.arange(-3, 4) * right_interval_s
    fine = np.arange(-FINE_RANGE, FINE_RANGE + 1e-9, FINE_STEP) * right_interval_s
    all_frames = np.concatenate(windows)
    base_q = model.left_to_right(scene.left_t[all_frames])
    bounds = np.cumsum([0] + [len(w) for w in windows])
    # Whole frames first, all windows at once. Only the frames compared under every
    # candidate count: a left frame whose right instant falls before the right video's
    # start (or past a right track's end) under some candidates would make those dearer
    # for a reason that is not the motion, and a window at rest, whose cost is otherwise
    # flat, would take that edge for a sharp minimum (a 2.5-frame offset measured as
    # -0.2 with three lost frames and -1100 ppm of drift).
    cw, n_pts, _ = _frame_costs(
        scene, all_frames, base_q[None, :] - whole[:, None] / model.rate, missing_cost=np.nan
    )
    shift = np.zeros(n_w)
    for k in range(n_w):
        s, npts = _compared_cost(cw[:, bounds[k] : bounds[k + 1]], n_pts[bounds[k] : bounds[k + 1]])
        if npts >= 4:
            shift[k] = whole[int(np.argmin(s))]
    q = base_q - np.repeat(shift, np.diff(bounds)) / model.rate
    cf, _, _ = _frame_costs(
        scene, all_frames, q[None, :] - fine[:, None] / model.rate, missing_cost=np.nan
    )
    step = fine[1] - fine[0]
    for k in range(n_w):
        s, npts = _compared_cost(cf[:, bounds[k] : bounds[k + 1]], n_pts[bounds[k] : bounds[k + 1]])
        if npts < 4:
            continue
        s = s / npts
        b = int(np.argmin(s))
        if not 0 < b < len(fine) - 1:
            continue
        c_m, c_0, c_p = s[b - 1], s[b], s[b + 1]
        denom = c_m - 2 * c_0 + c_p
        if denom <= 0:
            continue
        frac = float(np.clip(0.5 * (c_m - c_p) / denom, -0.5, 0.5))
        u[k] = shift[k] + fine[b] + frac * step
        # Curvature (per s²) times detections: a sharp minimum over many points counts most.
        weight[k] = denom / step**2 * npts
    # Windows with little motion (the rest before tapping, a pause) have a flat
    # cost: their minimum says little and may sit a frame off.
    informative = weight > 0
    if np.any(informative):
        weak = weight < MIN_WINDOW_WEIGHT * float(np.median(weight[informative]))
        u[weak], weight[weak] = np.nan, 0.0
    return u, weight, centre


def _compared_cost(costs: FloatArray, n_pts: NDArray[np.intp]) -> tuple[FloatArray, int]:
    """Per candidate (rows of ``costs``, NaN where a frame had nothing to compare with), the
    cost summed over the frames compared under every candidate, and their detections."""
    compared = np.all(np.isfinite(costs), axis=0)
    return costs[:, compared].sum(axis=1), int(n_pts[compared].sum())


def _fit_line(
    t: FloatArray, u: FloatArray, w: FloatArray
) -> tuple[float, float, NDArray[np.bool_]]:
    """Weighted line ``u = a + b t`` with outliers (beyond 4 robust sigmas) left out."""
    ok = np.isfinite(u) & (w > 0)
    a, b = 0.0, 0.0
    for _ in range(4):
        if np.count_nonzero(ok) < 2:
            if np.any(ok):
                a = float(np.average(u[ok], weights=w[ok]))
            return a, 0.0, ok
        A = np.column_stack([np.ones(int(ok.sum())), t[ok]])
        sw = np.sqrt(w[ok])
        coef, *_ = np.linalg.lstsq(A * sw[:, None], u[ok] * sw, rcond=None)
        a, b = float(coef[0]), float(coef[1])
        r = np.abs(u - (a + b * t))
        sigma = 1.4826 * float(np.median(r[ok])) + 1e-6
        new_ok = np.isfinite(u) & (w > 0) & (r <= 4 * sigma)
        if np.array_equal(new_ok, ok):
            break
        ok = new_ok
    return a, b, ok


class _Estimator:
    """Holds the recording's detections and times while the time model is estimated."""

    def __init__(
        self,
        rig: StereoRig,
        left_px: list[FloatArray],
        right_px: list[FloatArray],
        left_norm: list[FloatArray],
        right_norm: list[FloatArray],
        left_times: FrameTimes,
        right_times: FrameTimes,
        max_step_px: float,
    ) -> None:
        self.rig = rig
        self.left_px, self.right_px = left_px, right_px
        self.left_norm, self.right_norm = left_norm, right_norm
        self.left_times, self.right_times = left_times, right_times
        self.max_step_px = max_step_px
        self.found_left_flat = _flatten(left_norm, MAX_POINTS_PER_FRAME)
        # What the right camera is compared with: the left markers at their frame's instant.
        # With a rolling shutter each was taken at its row's instant; compared as found, the
        # estimated offset takes on the left markers' row delays (0.9 ms and 57 ppm of false
        # drift at 15 ms readout, markers on rows 476 and 616 of 1080: the test's rig).
        self.left_flat = (
            _flatten(
                _undistort(rig.left, _left_at_frame_times(self, left_times.t_s)),
                MAX_POINTS_PER_FRAME,
            )
            if rig.left.readout_ms > 0
            else self.found_left_flat
        )
        self.right_flat = _flatten(right_norm, MAX_POINTS_PER_FRAME)
        self.right_links = link_points(right_px, max_step_px=max_step_px)
        # The right tracks, whatever lost frames the scenes put back (only their times change).
        self.right_tracks = _tracks(right_px, camera=rig.right, links=self.right_links)

    def scene(self, dropped_left: Sequence[int], dropped_right: Sequence[int]) -> _Scene:
        left_t = corrected_times(self.left_times, dropped_left)
        right_t = corrected_times(self.right_times, dropped_right)
        # Tracks are cut where the timestamps (their grid) or the model lost frames.
        gap = self.right_times.gap_after.copy()
        gap[np.asarray(dropped_right, dtype=np.intp)] = True
        table = _table_at(self.right_tracks, right_t, gap)
        return _Scene(
            self.rig, self.left_flat, left_t, table, _focal(self.rig.left), _focal(self.rig.right)
        )


def estimate_time_model(est: _Estimator, coarse_offset_s: float) -> ClockModel:
    """Offset, drift and hidden lost frames (:class:`ClockModel`) from the local offsets."""
    h_r = est.right_times.interval_s
    h_l = est.left_times.interval_s
    dropped_l: list[int] = []
    dropped_r: list[int] = []
    scene = est.scene(dropped_l, dropped_r)
    windows = _windows(scene.left_t)
    u, w, centre = _local_offsets(scene, windows, ClockModel(coarse_offset_s), h_r)
    if not est.left_times.variable and not est.right_times.variable:
        # Steps of whole frames between windows: lost frames the timestamps do not show.
        levels = _levels(u, w, h_l, h_r)
        valid = np.flatnonzero(np.isfinite(u) & (w > 0))
        for k in np.flatnonzero(np.diff(levels) != 0):
            step = int(levels[k + 1] - levels[k])
            # The loss lies between the last window measured at the old level and the first
            # at the new one (windows without motion between them say nothing), possibly
            # inside either: a window that holds a loss has a blend of both levels.
            before_k = valid[valid <= k]
            k_old = int(before_k[-1]) if len(before_k) else k
            k_new = int(valid[valid > k][0]) if np.any(valid > k) else k + 1
            lo, hi = int(windows[k_old][0]), int(windows[k_new][-1]) + 1
            # The model of the windows before the step (the median of the last three measured
            # at the old level: one of them may hold the blend), in the times corrected so far.
            same = before_k[levels[before_k] == levels[k]][-3:]
            if not len(same):  # no window measured before the step: nothing to place from
                continue
            u_old = float(np.median(u[same]))
            before = ClockModel(
                coarse_offset_s + u_old - len(dropped_r) * h_r + len(dropped_l) * h_l
            )
            camera = "right" if step > 0 else "left"
            # All the step's losses at one frame first (a burst; placed one by one, the
            # first loss of a burst cannot be told apart: one frame off or two both cost
            # the gate), then each placed again with the others kept (separate losses).
            n = abs(step)
            where = [_place_drop(est, before, dropped_l, dropped_r, lo, hi, camera, count=n)] * n
            for _ in range(3 if n > 1 else 0):  # until no loss moves
                previous = list(where)
                for i in range(n):
                    others = where[:i] + where[i + 1 :]
                    dl = dropped_l + others if camera == "left" else dropped_l
                    dr = dropped_r + others if camera == "right" else dropped_r
                    where[i] = _place_drop(est, before, dl, dr, lo, hi, camera)
                if sorted(where) == sorted(previous):
                    break
            if camera == "right":
                dropped_r = dropped_r + where
            else:
                dropped_l = dropped_l + where
        if dropped_l or dropped_r:
            scene = est.scene(dropped_l, dropped_r)
            windows = _windows(scene.left_t)
            u, w, centre = _local_offsets(scene, windows, ClockModel(coarse_offset_s), h_r)
    a, b, _ = _fit_line(centre, u, w)
    # The local offset at left time t is u(t) = a + b t: t_left = coarse + u(t) + t_right,
    # so t_left (1 − b) = coarse + a + t_right, i.e. offset (coarse + a) / (1 − b), rate 1 / (1 − b).
    rate = 1.0 / (1.0 - b)
    offset = (coarse_offset_s + a) * rate
    return ClockModel(
        offset, (rate - 1.0) * 1e6, tuple(sorted(dropped_l)), tuple(sorted(dropped_r))
    )


def _model_cost(est: _Estimator, model: ClockModel) -> float:
    """Mean truncated epipolar cost of all left detections under ``model``."""
    scene = est.scene(model.dropped_left, model.dropped_right)
    frames = np.arange(len(scene.left_t))
    costs, n_pts, _ = _frame_costs(scene, frames, model.left_to_right(scene.left_t)[None, :])
    return float(costs.sum() / max(int(n_pts.sum()), 1))


def _model_confidence(est: _Estimator, model: ClockModel) -> float:
    """Confidence of a time model, as of a whole-frame offset: ``1 − cost / second``, where
    ``second`` is the least cost of the same model moved by two frames either way."""
    h = est.right_times.interval_s
    cost = _model_cost(est, model)
    second = min(
        _model_cost(est, replace(model, offset_s=model.offset_s + s * 2 * h)) for s in (-1, 1)
    )
    return float(np.clip(1 - cost / second, 0, 1)) if second > 0 else 0.0


def _better_of(est: _Estimator, model: ClockModel, fallback: ClockModel) -> ClockModel:
    """``model`` unless the whole-frame ``fallback`` explains the recording better (a
    recording with little motion can mislead the local offsets)."""
    if model == fallback:
        return model
    return model if _model_cost(est, model) <= _model_cost(est, fallback) else fallback


def _levels(u: FloatArray, w: FloatArray, h_l: float, h_r: float) -> NDArray[np.int_]:
    """Whole-frame level of each window's local offset (right frames up, left frames down)."""
    ok = np.isfinite(u) & (w > 0)
    levels = np.zeros(len(u), dtype=np.int_)
    if not np.any(ok):
        return levels
    ref = float(np.median(u[ok][: max(1, min(3, int(ok.sum())))]))
    d = u - ref
    with np.errstate(invalid="ignore"):
        lv = np.where(d >= 0, np.round(d / h_r), -np.round(-d / h_l))
    levels[ok] = lv[ok].astype(np.int_)
    last = levels[np.argmax(ok)]
    for k in range(len(u)):  # windows without an estimate keep the level before them
        if ok[k]:
            last = levels[k]
        else:
            levels[k] = last
    return levels


def _place_drop(
    est: _Estimator,
    model: ClockModel,
    dropped_l: list[int],
    dropped_r: list[int],
    lo: int,
    hi: int,
    camera: str,
    *,
    count: int = 1,
) -> int:
    """The frame (of ``camera``) after which ``count`` hidden frames were lost, between left
    frames ``lo .. hi − 1``: the position whose corrected times give the least epipolar cost."""
    left_t = corrected_times(est.left_times, dropped_l)
    frames = np.arange(lo, hi)
    if camera == "right":
        q = model.left_to_right(left_t[frames])
        right_t = corrected_times(est.right_times, dropped_r)
        j0 = max(0, int(np.searchsorted(right_t, q[0])) - 2)
        j1 = min(len(right_t) - 2, int(np.searchsorted(right_t, q[-1])) + 1)
        candidates = list(range(j0, j1 + 1))
    else:
        candidates = list(range(max(0, lo - 1), min(len(left_t) - 2, hi)))
    best, best_cost = candidates[0], np.inf
    for cand in candidates:
        dl = [*dropped_l, *[cand] * count] if camera == "left" else dropped_l
        dr = [*dropped_r, *[cand] * count] if camera == "right" else dropped_r
        scene = est.scene(dl, dr)
        q = model.left_to_right(scene.left_t[frames])
        costs, n_pts, _ = _frame_costs(scene, frames, q[None, :], missing_cost=np.nan)
        # Per detection compared: frames near a candidate's gap have no right points, and
        # must not make it cheaper (two separate gaps leave out more frames than one); a
        # wrong candidate shows as the wrong frames paired between it and the true loss,
        # and as interpolation across the true gap.
        compared = np.isfinite(costs[0])
        cost = float(costs[0][compared].sum() / max(int(n_pts[compared].sum()), 1))
        if cost < best_cost:
            best, best_cost = cand, cost
    return best


# ------------------------------------------------------------------- the whole thing


def _residual_px(d_min: FloatArray) -> float | None:
    """RMS of the truncated epipolar distances (px) of the left detections that have right
    points to be compared with."""
    d = np.minimum(d_min[np.isfinite(d_min)], GATE_PX)
    return float(np.sqrt(np.mean(d**2))) if d.size else None


def _consistent_share(d_min: FloatArray) -> float:
    """Share of the left detections with right points to compare with that lie within
    ``GATE_PX`` of a right epipolar line."""
    d = d_min[np.isfinite(d_min)]
    return float(np.mean(d <= GATE_PX)) if d.size else 0.0


def synchronise(
    rig: StereoRig,
    left_px: list[FloatArray],
    right_px: list[FloatArray],
    left_norm: list[FloatArray],
    right_norm: list[FloatArray],
    *,
    left_times: FrameTimes | None = None,
    right_times: FrameTimes | None = None,
    fps: float | None = None,
    offset_frames: float | None = None,
    max_offset_s: float = 0.5,
    max_step_px: float,
) -> TimeModelResult:
    """Estimate the time model of a stereo recording and bring both cameras to the left instants.

    Parameters
    ----------
    rig : StereoRig
        With ``readout_ms`` per camera for rolling shutters.
    left_px, right_px : list of ndarray, each (Ni, 2)
        Detections per frame of each video (px).
    left_norm, right_norm : list of ndarray, each (Ni, 2)
        The same, undistorted normalized.
    left_times, right_times : FrameTimes, optional
        Capture times of each video's frames (:mod:`core.timing`); default
        ``i / fps``.
    fps : float, optional
        Frame rate of both videos when no times are given.
    offset_frames : float, optional
        A given offset (right frame ``j`` with left frame ``j + K``): used as
        it is, without drift or lost frames.
    max_offset_s : float
        Largest offset searched (s).
    max_step_px : float
        2D linking gate of the marker tracks (px).

    Returns
    -------
    TimeModelResult
    """
    n_left, n_right = len(left_px), len(right_px)
    if left_times is None or right_times is None:
        if fps is None:
            raise ValueError("give left_times and right_times, or fps")
        left_times = left_times or uniform_times(n_left, fps)
        right_times = right_times or uniform_times(n_right, fps)
    if len(left_times) != n_left or len(right_times) != n_right:
        raise ValueError(
            f"{len(left_times)}/{len(right_times)} frame times for {n_left}/{n_right} frames"
        )
    warnings: list[str] = []
    fps_l, fps_r = left_times.fps, right_times.fps
    lab = (
        not left_times.variable
        and not right_times.variable
        and abs(fps_l - fps_r) <= 1e-6 * fps_l
        and rig.left.readout_ms == 0
        and rig.right.readout_ms == 0
    )
    est = _Estimator(
        rig, left_px, right_px, left_norm, right_norm, left_times, right_times, max_step_px
    )
    confidence = 1.0
    method = "given"
    sync_est: SyncEstimate | None = None
    if offset_frames is not None:
        sync_est = given_offset(float(offset_frames))
        model = ClockModel(float(offset_frames) / fps_r)
    else:
        method = "auto"
        if lab:
            max_off = max(1, min(round(max_offset_s * fps_l), max(n_left, n_right) // 2))
            sync_est = estimate_offset(rig, left_norm, right_norm, max_offset_frames=max_off)
            coarse, confidence = sync_est.offset_frames / fps_l, sync_est.confidence
        else:
            step = min(left_times.interval_s, right_times.interval_s)
            coarse, confidence, _, _ = _coarse_offset_s(
                est.left_flat,
                left_times.t_s,
                est.right_flat,
                right_times.t_s,
                rig,
                max_offset_s,
                step,
            )
        model = ClockModel(coarse)
        if confidence < MIN_CONFIDENCE:
            # One whole-frame offset may fit badly because frames were lost part-way (the
            # offset steps by a frame at each loss): the piecewise model is tried, and kept
            # when it is itself unambiguous.
            pieces = estimate_time_model(est, coarse)
            if pieces.dropped_left or pieces.dropped_right:
                piece_confidence = _model_confidence(est, pieces)
                if piece_confidence >= MIN_CONFIDENCE:
                    model = _better_of(est, pieces, model)
                    if model is pieces:
                        confidence = piece_confidence

        else:
            model = _better_of(est, estimate_time_model(est, coarse), model)
        if confidence < MIN_CONFIDENCE:
            warnings.append(
                f"the time offset between the cameras could not be estimated reliably (confidence"
                f" {confidence:.2f}, best guess {coarse:.3f} s = {coarse * fps_r:.1f} frames); give"
                " it with --offset-frames if the cameras are not synchronised"
            )
    scene = est.scene(model.dropped_left, model.dropped_right)
    left_t = scene.left_t
    duration = float(left_t[-1] - left_t[0]) if n_left else 0.0
    k0 = model.offset_s * fps_r / model.rate  # right frames at left frame 0
    whole = round(k0)
    trivial = (
        lab
        and not model.dropped_left
        and not model.dropped_right
        and abs(model.drift_ppm) * 1e-6 * duration * fps_r < MODEL_MIN_FRAMES
        and abs(k0 - whole) < (MODEL_MIN_FRAMES if method == "auto" else 0.2)
    )
    frames = np.arange(n_left)
    # The epipolar residual of pairing whole frames at the whole-frame offset (a lab rig's view).
    d_before = _whole_frame_residuals(est, whole)
    if trivial:
        out_left, out_right, pairing = left_px, right_px, whole
        d_after_row = d_before
        used_frames = float(whole)
    else:
        out_left = _left_at_frame_times(est, left_t)
        q = model.left_to_right(left_t)
        pts, counts = points_at_times(scene.right_table, q)
        out_right = _split(pts, counts)
        pairing = None
        left_scene = _Scene(
            rig,
            _flatten(_undistort(rig.left, out_left), MAX_POINTS_PER_FRAME),
            left_t,
            scene.right_table,
            scene.f_left,
            scene.f_right,
        )
        _, _, d_after = _frame_costs(left_scene, frames, q[None, :])
        d_after_row = d_after[0]
        used_frames = k0
    if method == "auto":
        share = _consistent_share(d_after_row)
        if share < MIN_CONSISTENT:
            raise DetectionError(
                f"the markers of the two videos agree with the rig's geometry at no time offset"
                f" (at best {100 * share:.0f} % of the left detections); check that the two videos"
                " are recordings of the same test, not swapped, and that the rig belongs to"
                " these cameras."
            )
        if confidence < MIN_CONFIDENCE and share < MIN_CONSISTENT_UNSURE:
            raise DetectionError(
                f"the two videos do not show the same motion: no time offset between them stands"
                f" out (confidence {confidence:.2f}) and at the best one only {100 * share:.0f} %"
                " of the left markers agree with the rig's geometry; check that the two videos"
                " are recordings of the same test, taken together, and that the rig belongs to"
                " these cameras."
            )
    dropped_l = sorted([*left_times.dropped_after, *model.dropped_left])
    dropped_r = sorted([*right_times.dropped_after, *model.dropped_right])
    doc: dict[str, Any] = {
        "offset_frames": round(float(used_frames), 3),
        "method": method,
        "confidence": round(float(confidence), 4),
        "offset_s": round(model.offset_s, 6),
        "drift_ppm": round(model.drift_ppm, 2),
        "dropped_frames_left": dropped_l,
        "dropped_frames_right": dropped_r,
        "epipolar_px_before": _round(_residual_px(d_before)),
        "epipolar_px_after": _round(_residual_px(d_after_row)),
        "time_source": [left_times.source, right_times.source],
        "fps_right": round(fps_r, 4),
    }
    if method == "auto":
        doc["offset_subframe"] = round(float(k0), 3)
    if rig.left.readout_ms > 0 or rig.right.readout_ms > 0:
        doc["readout_ms"] = [rig.left.readout_ms, rig.right.readout_ms]
    residual_after = doc["epipolar_px_after"]
    if method == "auto" and residual_after is not None and residual_after > DOUBTFUL_EPIPOLAR_PX:
        warnings.append(
            f"after synchronisation the two views still disagree by {residual_after:.1f} px"
            f" (RMS epipolar distance; a calibrated rig gives under {DOUBTFUL_EPIPOLAR_PX:g}"
            f" px): the time offset found ({model.offset_s:.3f} s) may be a whole movement"
            f" off, as when the cameras started more than {max_offset_s:g} s apart (not"
            " searched), or the rig may not belong to these cameras; start both cameras"
            " together or give the offset with --offset-frames, and check the rig"
        )
    n_dropped = len(dropped_l) + len(dropped_r)
    if n_dropped > LARGE_DROPS:
        warnings.append(
            f"{n_dropped} frames were lost during the recording (left after frames"
            f" {dropped_l or 'none'}, right after frames {dropped_r or 'none'}); the positions"
            " around them are interpolated or missing; record with less load on the computer"
        )
    if abs(model.drift_ppm) > LARGE_DRIFT_PPM:
        warnings.append(
            f"the cameras' clocks differ by {model.drift_ppm:.0f} ppm; check that both record at"
            " the frame rate they state"
        )
    return TimeModelResult(
        [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in out_left],
        [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in out_right],
        pairing,
        left_t,
        doc,
        warnings,
        model,
    )


def _round(v: float | None, nd: int = 4) -> float | None:
    return None if v is None else round(v, nd)


def _undistort(cam: Camera, frames: list[FloatArray]) -> list[FloatArray]:
    counts = [len(f) for f in frames]
    if sum(counts) == 0:
        return [np.zeros((0, 2)) for _ in frames]
    flat = cam.undistort_points(np.concatenate(frames, axis=0))
    return list(np.split(flat, np.cumsum(counts)[:-1]))


def _whole_frame_residuals(est: _Estimator, offset: int) -> FloatArray:
    """Epipolar distance (px) of each left detection to the nearest right one of right frame
    ``i − offset`` (the detections as found)."""
    n_left, n_right = len(est.found_left_flat[1]), len(est.right_flat[1])
    frames = np.arange(n_left)
    l_pts, l_frame = _select_frames(est.found_left_flat, frames)
    rows = l_frame - offset
    valid = (rows >= 0) & (rows < n_right)
    right = (est.right_flat[0], np.append(est.right_flat[1], 0).astype(np.intp))
    rows = np.where(valid, rows, n_right).astype(np.intp)  # the empty extra frame
    return _nearest_epipolar_px(est.rig, l_pts, right, rows)


def _left_at_frame_times(est: _Estimator, left_t: FloatArray) -> list[FloatArray]:
    """The left detections at their frame's instant: as found for a global shutter; moved
    along their 2D tracks to the middle row's instant for a rolling shutter."""
    if est.rig.left.readout_ms <= 0:
        return est.left_px
    links = link_points(est.left_px, max_step_px=est.max_step_px)
    table = track_table(
        est.left_px, left_t, camera=est.rig.left, links=links, interval_s=est.left_times.interval_s
    )
    pts, counts = points_at_times(table, left_t)
    return _split(pts, counts)

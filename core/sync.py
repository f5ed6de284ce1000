"""Frame offset between the two cameras, estimated from the marker motion itself.

Convention (INTERFACES.md): an offset ``K`` means right frame ``j`` was taken
at the same time as left frame ``j + K``; left frame ``i`` pairs with right
frame ``i - K``.

Method (epipolar consistency): for every candidate offset, each left marker
detection is paired with the nearest epipolar line of the right detections of
the paired frame; the cost is the mean truncated squared epipolar distance
(px). Static points (reflections, a resting hand) satisfy the constraint at
every offset and only add a constant; the tapping fingers move several
millimetres per frame across the epipolar lines, so they satisfy it only at the
true offset. This uses the calibrated rig rather than a 2D motion signal, so it
does not depend on the two cameras seeing the motion alike.

Sub-frame offsets (cameras not triggered together): :func:`refine_offset`
evaluates the same cost at fractional offsets around the whole-frame minimum,
with the right detections interpolated in time along their 2D tracks
(:func:`link_points`, :func:`points_at`); an offset at least
``SUBFRAME_MIN`` from a whole frame is then used to pair frames
(:func:`right_points_for_left_frames`).

Confidence is ``1 - best / second_best``, where ``second_best`` is the lowest
cost at least two frames away from the best: 0 when the recording has no
motion to synchronise on, close to 1 for a sharp, unique minimum.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core.camera import StereoRig
from core.geometry_kernels import _geometry

FloatArray = NDArray[np.float64]

#: At most this many detections per frame enter the estimate (the rest are clutter).
MAX_POINTS_PER_FRAME = 12
#: At most this many left frames are used (evenly spaced) to bound the cost.
MAX_FRAMES_USED = 400
#: Offsets this far from a whole frame are applied as sub-frame offsets (frames).
SUBFRAME_MIN = 0.2


@dataclass(frozen=True)
class SyncEstimate:
    """The estimated frame offset.

    Attributes
    ----------
    offset_frames : int
        Whole-frame offset (right ``j`` <-> left ``j + K``).
    offset_subframe : float
        Sub-frame refinement of the offset (frames); equals ``offset_frames``
        when no refinement was possible. When it is at least ``SUBFRAME_MIN``
        away from ``offset_frames``, frames are paired at this fractional
        offset (the right detections are interpolated in time, see
        :func:`points_at`).
    confidence : float
        0 (no usable motion) .. 1 (sharp unique minimum).
    method : str
        ``"auto"`` or ``"given"``.
    offsets : ndarray, shape (C,)
        Candidate offsets tried (empty for ``"given"``).
    costs : ndarray, shape (C,)
        Mean truncated epipolar cost per candidate (dimensionless, 0..1).
    """

    offset_frames: int
    offset_subframe: float
    confidence: float
    method: str
    offsets: NDArray[np.int_] = field(default_factory=lambda: np.zeros(0, dtype=int))
    costs: FloatArray = field(default_factory=lambda: np.zeros(0))

    @property
    def fractional(self) -> bool:
        """Whether frames are paired at a sub-frame offset (cameras not triggered together)."""
        return abs(self.offset_subframe - self.offset_frames) >= SUBFRAME_MIN

    @property
    def used_offset(self) -> float:
        """The offset frames are paired with: ``offset_subframe`` if fractional, else whole."""
        return float(self.offset_subframe) if self.fractional else float(self.offset_frames)

    def to_result(self) -> dict[str, object]:
        """The ``sync`` object of result.json (``offset_frames`` is the offset used)."""
        out: dict[str, object] = {
            "offset_frames": round(self.used_offset, 3),
            "method": self.method,
            "confidence": round(float(self.confidence), 4),
        }
        if self.method == "auto":
            out["offset_subframe"] = round(float(self.offset_subframe), 3)
        return out


def _flatten(
    points: Sequence[ArrayLike], limit: int | None = None
) -> tuple[FloatArray, NDArray[np.intp]]:
    """Per-frame ``(Ni, 2)`` points as one ``(N, 2)`` array and the per-frame counts.

    With ``limit``, only the first ``limit`` points of each frame are kept.
    """
    flat = _concatenated(points)
    if flat is not None:
        counts = np.fromiter((np.shape(p)[0] for p in points), dtype=np.intp, count=len(points))
    else:
        arrays = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in points]
        counts = np.array([a.shape[0] for a in arrays], dtype=np.intp)
        flat = np.concatenate(arrays) if arrays else np.zeros((0, 2))
    if limit is not None and counts.size and int(counts.max()) > limit:
        keep = _ranks(counts) < limit
        flat, counts = flat[keep], np.minimum(counts, limit)
    return flat, counts


def _concatenated(points: Sequence[ArrayLike]) -> FloatArray | None:
    """The points of all frames as one ``(N, 2)`` float64 array when every frame is a ``(Ni, 2)``
    array (numbers that convert to float64 as ``np.asarray`` does), else None: the common
    case without a conversion per frame."""
    try:
        flat = np.concatenate(points) if len(points) else None
    except (ValueError, TypeError):
        return None
    if flat is None or flat.dtype != np.float64 or flat.ndim != 2 or flat.shape[1] != 2:
        return None
    return flat


def _ranks(counts: NDArray[np.intp]) -> NDArray[np.intp]:
    """Position of each element within its segment, for consecutive segments of ``counts``."""
    total = int(counts.sum())
    starts = np.cumsum(counts) - counts
    return np.arange(total, dtype=np.intp) - np.repeat(starts, counts)


def _segment_indices(
    starts: NDArray[np.intp], counts: NDArray[np.intp]
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Indices ``starts[s] .. starts[s] + counts[s] - 1`` of all segments ``s``, concatenated,
    and the segment of each index."""
    seg = np.repeat(np.arange(len(counts), dtype=np.intp), counts)
    return np.repeat(starts, counts) + _ranks(counts), seg


def _select_frames(
    points: tuple[FloatArray, NDArray[np.intp]], frames: NDArray[np.int_]
) -> tuple[FloatArray, NDArray[np.intp]]:
    """The finite points of frames ``frames`` (ascending) of flat per-frame points, and their
    frame."""
    pts, counts = points
    starts = np.cumsum(counts) - counts
    idx, seg = _segment_indices(starts[frames], counts[frames])
    frame = np.asarray(frames, dtype=np.intp)[seg]
    finite = np.isfinite(pts[idx, 0])
    return pts[idx[finite]], frame[finite]


def _homogeneous(points: FloatArray) -> FloatArray:
    """``(N, 2)`` points to ``(N, 3)`` homogeneous ones."""
    return np.column_stack([points, np.ones(len(points))])


def _epipolar_costs(
    E: FloatArray,
    left_pts: FloatArray,
    right: tuple[FloatArray, NDArray[np.intp]],
    right_row: NDArray[np.intp],
    f_left: float,
    f_right: float,
    gate_px: float,
) -> tuple[FloatArray, NDArray[np.intp]]:
    """Mean truncated epipolar cost of several candidate pairings, in one pass.

    Parameters
    ----------
    E : ndarray, shape (3, 3)
        Essential matrix of the rig.
    left_pts : ndarray, shape (L, 2)
        The left detections that enter the cost (undistorted normalized).
    right : (ndarray (N, 2), ndarray (R,) of int)
        Undistorted normalized right detections of ``R`` right frames, flat,
        with the number of detections per frame (see :func:`_flatten`).
    right_row : ndarray, shape (C, L) of int
        For candidate ``c``, the right frame paired with the frame of left
        detection ``l``, or -1 when that detection has no partner frame (it is
        then left out of candidate ``c``).
    f_left, f_right : float
        Focal lengths (px) that turn normalized distances into pixels.
    gate_px : float
        Truncation of the epipolar distance (px).

    Returns
    -------
    costs : ndarray, shape (C,)
        Per candidate, the mean over its left detections of
        ``min(d, gate)**2 / gate**2``, ``d`` the symmetric epipolar distance
        (px) to the nearest right detection of the paired frame (``inf``
        when that frame has none); NaN when the candidate has no detection.
    n_points : ndarray, shape (C,)
        Number of left detections in each cost.
    """
    r_pts, r_counts = right
    n_rows = len(r_counts)
    lines_l = _homogeneous(r_pts) @ E  # (N, 3) epipolar lines in the left image
    norm_l = np.linalg.norm(lines_l[:, :2], axis=1)
    valid = right_row >= 0
    lines_r = _homogeneous(left_pts) @ E.T  # (L, 3) epipolar lines in the right image
    la, lb, lc = lines_r.T.copy()
    norm_r = np.linalg.norm(lines_r[:, :2], axis=1)
    # d: sqrt(0.5 * s), s = d_l**2 + d_r**2 least over the right detections of the paired
    # frame (sqrt is non-decreasing, so that is the nearest one; NaN points count as
    # infinitely far), inf without any; the cost min(d, gate)**2 / gate**2. One compiled
    # loop over candidates and left detections, which measures only the right detections
    # that may lie within the gate (numpy's arithmetic in numpy's order: the former
    # formulation's bits, tests/core/test_sync.py compares).
    counts = np.append(r_counts, 0).astype(np.intp)  # row R: no partner frame
    starts = (np.cumsum(counts) - counts).astype(np.intp)
    cost = _geometry.truncated_epipolar_costs(
        la,
        lb,
        lc,
        norm_r,
        np.ascontiguousarray(r_pts, dtype=np.float64).reshape(-1, 2),
        norm_l,
        starts,
        counts,
        np.ascontiguousarray(np.where(valid, right_row, n_rows), dtype=np.intp).ravel(),
        float(f_right),
        float(f_left),
        float(gate_px),
        float(gate_px**2),
    ).reshape(np.shape(right_row))  # (C, L)
    n_points = valid.sum(axis=1)
    costs = np.full(len(right_row), np.nan)
    for c in np.flatnonzero(n_points):
        costs[c] = cost[c][valid[c]].mean()
    return costs, n_points


def estimate_offset(
    rig: StereoRig,
    left_points_norm: Sequence[ArrayLike],
    right_points_norm: Sequence[ArrayLike],
    *,
    max_offset_frames: int = 30,
    gate_px: float = 3.0,
) -> SyncEstimate:
    """Estimate the frame offset from per-frame marker detections of both cameras.

    Parameters
    ----------
    rig : StereoRig
    left_points_norm, right_points_norm : sequence of array_like, each (Ni, 2)
        Undistorted normalized detections per frame of each video
        (``Camera.undistort_points`` of the detected pixels).
    max_offset_frames : int
        Offsets ``-max .. +max`` are tried.
    gate_px : float
        Epipolar distances are truncated at this value (px), so unmatched
        clutter costs at most 1.

    Returns
    -------
    SyncEstimate
        ``method="auto"``; ``confidence`` 0 when there is nothing to
        synchronise on (then the offset is 0).
    """
    if max_offset_frames < 0:
        raise ValueError(f"max_offset_frames must be >= 0, got {max_offset_frames}")
    if gate_px <= 0:
        raise ValueError(f"gate_px must be positive, got {gate_px}")
    left = _flatten(left_points_norm, MAX_POINTS_PER_FRAME)
    right = _flatten(right_points_norm, MAX_POINTS_PER_FRAME)
    t_left, t_right = len(left[1]), len(right[1])
    offsets = np.arange(-max_offset_frames, max_offset_frames + 1)
    if t_left == 0 or t_right == 0:
        return SyncEstimate(0, 0.0, 0.0, "auto", offsets, np.full(len(offsets), np.nan))
    frames = np.unique(np.linspace(0, t_left - 1, min(t_left, MAX_FRAMES_USED)).round().astype(int))
    E = rig.essential_matrix
    f_left = 0.5 * (rig.left.K[0, 0] + rig.left.K[1, 1])
    f_right = 0.5 * (rig.right.K[0, 0] + rig.right.K[1, 1])
    # Each left detection of the frames used, and its right frame per offset.
    l_pts, l_frame = _select_frames(left, frames)
    r_row = l_frame[None, :] - offsets[:, None]
    r_row[(r_row < 0) | (r_row >= t_right)] = -1
    all_costs, n_points = _epipolar_costs(E, l_pts, right, r_row, f_left, f_right, gate_px)
    min_points = max(10, len(frames) // 10)
    costs = np.where(n_points >= min_points, all_costs, np.nan)
    if not np.any(np.isfinite(costs)):
        return SyncEstimate(0, 0.0, 0.0, "auto", offsets, costs)
    best = int(np.nanargmin(costs))
    far = np.abs(offsets - offsets[best]) >= 2
    second = np.nanmin(costs[far]) if np.any(far & np.isfinite(costs)) else np.nan
    if np.isfinite(second) and second > 0:
        confidence = float(np.clip(1.0 - costs[best] / second, 0.0, 1.0))
    else:
        confidence = 0.0
    sub = float(offsets[best])  # whole frames; refine_offset goes below a frame
    return SyncEstimate(int(offsets[best]), sub, confidence, "auto", offsets, costs)


def given_offset(offset_frames: float) -> SyncEstimate:
    """A user-given offset (``--offset-frames``); fractional values pair frames sub-frame."""
    if not np.isfinite(offset_frames):
        raise ValueError(f"offset_frames must be finite, got {offset_frames}")
    whole = round(offset_frames)
    sub = float(offset_frames) if abs(offset_frames - whole) >= SUBFRAME_MIN else float(whole)
    return SyncEstimate(whole, sub, 1.0, "given")


# -- sub-frame pairing --------------------------------------------------------------


def link_points(points_px: Sequence[ArrayLike], *, max_step_px: float) -> list[NDArray[np.intp]]:
    """Link the detections of consecutive frames of one camera (2D tracks).

    Parameters
    ----------
    points_px : sequence of array_like, each (Ni, 2)
        Detections per frame (px).
    max_step_px : float
        Largest distance between a detection's predicted position (constant
        velocity when it has a predecessor) and its successor (px).

    Returns
    -------
    list of ndarray, each (Ni,)
        For each detection of frame ``j``, the index of its successor in frame
        ``j + 1``, or -1 (global assignment per frame pair, Hungarian method).
    """
    pts, counts = _flatten(points_px)
    n, n_pts = len(counts), len(pts)
    if n == 0:
        return []
    starts = np.cumsum(counts) - counts
    nxt = np.full(n_pts, -1, dtype=np.intp)
    if n > 1:
        # Frame pair by frame pair (each pair's prediction needs the links before it), one
        # compiled loop that calls the Hungarian method where detections compete.
        _geometry.link_frames(
            np.ascontiguousarray(pts), counts.astype(np.intp), nxt, float(max_step_px)
        )
    local = np.where(nxt >= 0, nxt - np.repeat(np.r_[starts[1:], 0], counts), -1)
    return list(np.split(local.astype(np.intp), np.cumsum(counts)[:-1]))


def points_at(
    points_px: Sequence[FloatArray], links: Sequence[NDArray[np.intp]], t_frames: float
) -> FloatArray:
    """Detections of one camera interpolated to a fractional frame time.

    Each detection of frame ``floor(t)`` linked to one in the next frame is
    interpolated with the cubic through its samples at ``j - 1 .. j + 2``
    (4-point Lagrange), or linearly when its track is shorter. Unlinked
    detections are left out. This is the per-detection formulation, for one
    time; :func:`right_points_for_left_frames` and :func:`refine_offset`
    compute the same for many times at once.

    Parameters
    ----------
    points_px : sequence of ndarray, each (Ni, 2)
        Detections per frame (px).
    links : sequence of ndarray, each (Ni,)
        Successor indices per frame (:func:`link_points`).
    t_frames : float
        Frame time (frames).

    Returns
    -------
    ndarray, shape (M, 2)
        Interpolated detections (px); all detections of frame ``t`` when it is
        a whole frame, none outside the video.
    """
    n = len(points_px)
    j = int(np.floor(t_frames))
    f = float(t_frames - j)
    if j < 0 or j >= n:
        return np.zeros((0, 2))
    if f < 1e-9:
        return np.asarray(points_px[j], dtype=np.float64).reshape(-1, 2)
    if j + 1 >= n:
        return np.zeros((0, 2))
    cur = np.asarray(points_px[j], dtype=np.float64).reshape(-1, 2)
    out = []
    prev_of = {}
    if j >= 1:
        for a, b in enumerate(links[j - 1]):
            if b >= 0:
                prev_of[int(b)] = a
    w = (-f * (f - 1) * (f - 2) / 6, (f + 1) * (f - 1) * (f - 2) / 2,
         -(f + 1) * f * (f - 2) / 2, (f + 1) * f * (f - 1) / 6)  # fmt: skip
    for a in range(len(cur)):
        b = int(links[j][a])
        if b < 0:
            continue
        p0, p1 = cur[a], points_px[j + 1][b]
        pm = points_px[j - 1][prev_of[a]] if a in prev_of else None
        c = int(links[j + 1][b]) if j + 2 < n else -1
        p2 = points_px[j + 2][c] if c >= 0 else None
        if pm is not None and p2 is not None:
            out.append(w[0] * pm + w[1] * p0 + w[2] * p1 + w[3] * p2)
        else:
            out.append((1 - f) * p0 + f * p1)
    return np.array(out).reshape(-1, 2)


def _track_table(
    points_px: Sequence[ArrayLike], links: Sequence[NDArray[np.intp]]
) -> tuple[FloatArray, NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """The detections of all frames of one camera, flat, with their 2D-track neighbours.

    Returns
    -------
    points : ndarray, shape (N, 2)
        All detections (px), frame by frame.
    starts : ndarray, shape (T + 1,)
        Frame ``j`` holds ``points[starts[j]:starts[j + 1]]``.
    nxt, prv : ndarray, shape (N,)
        Flat index of each detection's successor in the next frame and of its
        predecessor in the previous frame (``links``), or -1.
    """
    points, counts = _flatten(points_px)
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.intp)
    n = len(counts)
    nxt = np.full(len(points), -1, dtype=np.intp)
    if n > 1:
        local = np.concatenate([np.asarray(links[j], dtype=np.intp) for j in range(n - 1)])
        frame = np.repeat(np.arange(n - 1), counts[:-1])
        linked = local >= 0
        nxt[: starts[n - 1]][linked] = starts[frame[linked] + 1] + local[linked]
    prv = np.full(len(points), -1, dtype=np.intp)
    has = nxt >= 0
    prv[nxt[has]] = np.flatnonzero(has)
    return points, starts, nxt, prv


def _points_at_times(
    table: tuple[FloatArray, NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]],
    t_frames: ArrayLike,
) -> tuple[FloatArray, NDArray[np.intp]]:
    """:func:`points_at` for many fractional frame times at once.

    Parameters
    ----------
    table : tuple
        :func:`_track_table` of the detections and their links.
    t_frames : array_like, shape (S,)
        Frame times (frames).

    Returns
    -------
    points : ndarray, shape (M, 2)
        ``points_at`` of every time, concatenated in the order of ``t_frames`` (px).
    counts : ndarray, shape (S,)
        Number of points of each time.
    """
    pts, starts, nxt, prv = table
    n = len(starts) - 1
    t = np.asarray(t_frames, dtype=np.float64)
    j = np.floor(t).astype(np.intp)
    f = t - j
    exact = f < 1e-9
    usable = (j >= 0) & (j < n) & (exact | (j + 1 < n))
    jc = np.clip(j, 0, max(n - 1, 0))
    counts = np.where(usable, starts[jc + 1] - starts[jc], 0)
    idx, time = _segment_indices(starts[jc], counts)
    keep = exact[time] | (nxt[idx] >= 0)
    idx, time = idx[keep], time[keep]
    out = pts[idx].copy()
    moving = ~exact[time]
    a, fm = idx[moving], f[time[moving]][:, None]
    b = nxt[a]
    pm, c = prv[a], nxt[b]
    p0, p1 = pts[a], pts[b]
    cubic = (pm >= 0) & (c >= 0)
    res = (1 - fm) * p0 + fm * p1
    if np.any(cubic):
        fc = fm[cubic]
        w0 = -fc * (fc - 1) * (fc - 2) / 6
        w1 = (fc + 1) * (fc - 1) * (fc - 2) / 2
        w2 = -(fc + 1) * fc * (fc - 2) / 2
        w3 = (fc + 1) * fc * (fc - 1) / 6
        res[cubic] = w0 * pts[pm[cubic]] + w1 * p0[cubic] + w2 * p1[cubic] + w3 * pts[c[cubic]]
    out[moving] = res
    return out, np.bincount(time, minlength=len(t)).astype(np.intp)


def right_points_for_left_frames(
    right_px: Sequence[FloatArray], n_left: int, offset_frames: float, *, max_step_px: float
) -> list[FloatArray]:
    """Right detections at the instant of each left frame ``i`` (right time ``i - K``).

    Parameters
    ----------
    right_px : sequence of ndarray, each (Ni, 2)
        Right detections per frame (px).
    n_left : int
        Number of left frames.
    offset_frames : float
        The (fractional) offset ``K`` (frames).
    max_step_px : float
        2D linking gate (px), see :func:`link_points`.

    Returns
    -------
    list of ndarray, each (Mi, 2)
        :func:`points_at` of the right detections at ``i - K`` for each left frame (px).
    """
    table = _track_table(right_px, link_points(right_px, max_step_px=max_step_px))
    pts, counts = _points_at_times(table, np.arange(n_left) - offset_frames)
    return list(np.split(pts, np.cumsum(counts)[:-1])) if n_left else []


def refine_offset(
    rig: StereoRig,
    left_points_norm: Sequence[ArrayLike],
    right_px: Sequence[FloatArray],
    estimate: SyncEstimate,
    *,
    max_step_px: float,
    gate_px: float = 3.0,
    steps: int = 10,
) -> SyncEstimate:
    """Sub-frame refinement: the epipolar cost at fractional offsets around the whole one.

    The right detections are interpolated in time (:func:`points_at`, all
    fractions and frames at once) at ``K + f`` for ``f`` in ``[-0.5, 0.5]``
    (``steps`` intervals); the minimum is refined with a parabola through its
    neighbours.

    Parameters
    ----------
    rig : StereoRig
    left_points_norm : sequence of array_like, each (Ni, 2)
        Undistorted normalized left detections per frame.
    right_px : sequence of ndarray, each (Mj, 2)
        Right detections per frame (px, as detected; undistorted after interpolation).
    estimate : SyncEstimate
        The whole-frame estimate (:func:`estimate_offset`).
    max_step_px : float
        2D linking gate (px), see :func:`link_points`.
    gate_px : float
        Epipolar distances are truncated at this value (px).
    steps : int
        Number of intervals over the fraction range ``[-0.5, 0.5]`` (frames).

    Returns
    -------
    SyncEstimate
        ``estimate`` with ``offset_subframe`` refined (frames); ``estimate``
        itself when no fraction could be scored.
    """
    if not np.any(np.isfinite(estimate.costs)):
        return estimate
    left = _flatten(left_points_norm, MAX_POINTS_PER_FRAME)
    t_left = len(left[1])
    frames = np.unique(np.linspace(0, t_left - 1, min(t_left, 200)).round().astype(int))
    table = _track_table(right_px, link_points(right_px, max_step_px=max_step_px))
    E = rig.essential_matrix
    f_left = 0.5 * (rig.left.K[0, 0] + rig.left.K[1, 1])
    f_right = 0.5 * (rig.right.K[0, 0] + rig.right.K[1, 1])
    fracs = np.linspace(-0.5, 0.5, steps + 1)
    # The interpolated right points of every offset and frame (offset-major),
    # undistorted in one vectorised call.
    times = (frames[None, :] - (estimate.offset_frames + fracs)[:, None]).ravel()
    pts_px, counts = _points_at_times(table, times)
    if len(pts_px) == 0:
        return estimate
    pts_norm = rig.right.undistort_points(pts_px)
    keep = _ranks(counts) < MAX_POINTS_PER_FRAME
    right = (pts_norm[keep], np.minimum(counts, MAX_POINTS_PER_FRAME))
    l_pts, l_frame = _select_frames(left, frames)
    r_row = (
        np.searchsorted(frames, l_frame)[None, :] + (len(frames) * np.arange(len(fracs)))[:, None]
    )
    costs, n_points = _epipolar_costs(E, l_pts, right, r_row, f_left, f_right, gate_px)
    costs = np.where(n_points >= max(10, len(frames) // 10), costs, np.nan)
    if not np.any(np.isfinite(costs)):
        return estimate
    best = int(np.nanargmin(costs))
    sub = float(estimate.offset_frames + fracs[best])
    if 0 < best < len(fracs) - 1 and np.all(np.isfinite(costs[best - 1 : best + 2])):
        c_m, c_0, c_p = costs[best - 1], costs[best], costs[best + 1]
        denom = c_m - 2 * c_0 + c_p
        if denom > 0:
            step = fracs[1] - fracs[0]
            sub += float(np.clip(0.5 * (c_m - c_p) / denom, -0.5, 0.5)) * step
    return SyncEstimate(
        estimate.offset_frames,
        sub,
        estimate.confidence,
        estimate.method,
        estimate.offsets,
        estimate.costs,
    )

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


def _pad(points: Sequence[ArrayLike]) -> FloatArray:
    """Per-frame ``(Ni, 2)`` points to a homogeneous ``(T, P, 3)`` array, NaN padded."""
    t = len(points)
    arrays = [np.asarray(p, dtype=np.float64).reshape(-1, 2)[:MAX_POINTS_PER_FRAME] for p in points]
    p_max = max([a.shape[0] for a in arrays] + [1])
    out = np.full((t, p_max, 3), np.nan)
    for i, a in enumerate(arrays):
        out[i, : a.shape[0], :2] = a
        out[i, : a.shape[0], 2] = 1.0
    return out


def _offset_cost(
    E: FloatArray,
    left: FloatArray,
    right: FloatArray,
    offset: int,
    frames: NDArray[np.int_],
    f_left: float,
    f_right: float,
    gate_px: float,
) -> tuple[float, int]:
    """Mean truncated epipolar cost of left frames ``frames`` paired at ``offset``."""
    r_idx = frames - offset
    ok = (r_idx >= 0) & (r_idx < right.shape[0])
    if not np.any(ok):
        return np.nan, 0
    hl = left[frames[ok]]  # (n, P, 3)
    hr = right[r_idx[ok]]  # (n, Q, 3)
    lines_r = hl @ E.T  # (n, P, 3)
    lines_l = hr @ E  # (n, Q, 3)
    alg = np.abs(np.einsum("npk,nqk->npq", lines_r, hr))
    with np.errstate(divide="ignore", invalid="ignore"):
        d_r = alg / np.linalg.norm(lines_r[..., :2], axis=2)[:, :, None] * f_right
        d_l = alg / np.linalg.norm(lines_l[..., :2], axis=2)[:, None, :] * f_left
    d = np.sqrt(0.5 * (d_l**2 + d_r**2))
    d = np.where(np.isfinite(d), d, np.inf)
    d_min = d.min(axis=2)  # (n, P)
    present = np.isfinite(hl[..., 0])
    n_points = int(present.sum())
    if n_points == 0:
        return np.nan, 0
    cost = np.minimum(d_min[present], gate_px) ** 2 / gate_px**2
    return float(cost.mean()), n_points


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
    left = _pad(left_points_norm)
    right = _pad(right_points_norm)
    t_left = left.shape[0]
    offsets = np.arange(-max_offset_frames, max_offset_frames + 1)
    if t_left == 0 or right.shape[0] == 0:
        return SyncEstimate(0, 0.0, 0.0, "auto", offsets, np.full(len(offsets), np.nan))
    frames = np.unique(np.linspace(0, t_left - 1, min(t_left, MAX_FRAMES_USED)).round().astype(int))
    E = rig.essential_matrix
    f_left = 0.5 * (rig.left.K[0, 0] + rig.left.K[1, 1])
    f_right = 0.5 * (rig.right.K[0, 0] + rig.right.K[1, 1])
    costs = np.full(len(offsets), np.nan)
    min_points = max(10, len(frames) // 10)
    for k, off in enumerate(offsets):
        c, n = _offset_cost(E, left, right, int(off), frames, f_left, f_right, gate_px)
        if n >= min_points:
            costs[k] = c
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
    from scipy.optimize import linear_sum_assignment

    frames = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in points_px]
    nxt = [np.full(len(f), -1, dtype=np.intp) for f in frames]
    prev_of: NDArray[np.intp] = np.full(len(frames[0]) if frames else 0, -1, dtype=np.intp)
    for j in range(len(frames) - 1):
        a, b = frames[j], frames[j + 1]
        new_prev = np.full(len(b), -1, dtype=np.intp)
        if len(a) and len(b):
            pred = a.copy()
            has = prev_of >= 0
            if np.any(has):
                pred[has] = 2 * a[has] - frames[j - 1][prev_of[has]]
            d = np.linalg.norm(pred[:, None, :] - b[None, :, :], axis=2)
            cost = np.where(d <= max_step_px, d, 1e9)
            rows, cols = linear_sum_assignment(cost)
            ok = cost[rows, cols] < 1e9
            nxt[j][rows[ok]] = cols[ok]
            new_prev[cols[ok]] = rows[ok]
        prev_of = new_prev
    return nxt


def points_at(
    points_px: Sequence[FloatArray], links: Sequence[NDArray[np.intp]], t_frames: float
) -> FloatArray:
    """Detections of one camera interpolated to a fractional frame time.

    Each detection of frame ``floor(t)`` linked to one in the next frame is
    interpolated with the cubic through its samples at ``j - 1 .. j + 2``
    (4-point Lagrange), or linearly when its track is shorter. Unlinked
    detections are left out.

    Returns
    -------
    ndarray, shape (M, 2)
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


def right_points_for_left_frames(
    right_px: Sequence[FloatArray], n_left: int, offset_frames: float, *, max_step_px: float
) -> list[FloatArray]:
    """Right detections at the instant of each left frame ``i`` (right time ``i - K``)."""
    links = link_points(right_px, max_step_px=max_step_px)
    return [points_at(right_px, links, i - offset_frames) for i in range(n_left)]


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

    The right detections are interpolated in time (:func:`points_at`) at
    ``K + f`` for ``f`` in ``[-0.5, 0.5]`` (``steps`` intervals); the minimum
    is refined with a parabola through its neighbours.
    """
    if not np.any(np.isfinite(estimate.costs)):
        return estimate
    left = _pad(left_points_norm)
    t_left = left.shape[0]
    frames = np.unique(np.linspace(0, t_left - 1, min(t_left, 200)).round().astype(int))
    links = link_points(right_px, max_step_px=max_step_px)
    E = rig.essential_matrix
    f_left = 0.5 * (rig.left.K[0, 0] + rig.left.K[1, 1])
    f_right = 0.5 * (rig.right.K[0, 0] + rig.right.K[1, 1])
    fracs = np.linspace(-0.5, 0.5, steps + 1)
    # The interpolated right points of every offset and frame, undistorted in
    # one vectorised call (one call per frame and offset cost ~0.5 s for 10 s).
    pts_px = [
        points_at(right_px, links, i - (estimate.offset_frames + frac))
        for frac in fracs
        for i in frames
    ]
    counts = [len(p) for p in pts_px]
    if sum(counts) == 0:
        return estimate
    flat = rig.right.undistort_points(np.concatenate([p.reshape(-1, 2) for p in pts_px]))
    pts_norm = np.split(flat, np.cumsum(counts)[:-1])
    costs = np.full(len(fracs), np.nan)
    for k in range(len(fracs)):
        right = _pad(pts_norm[k * len(frames) : (k + 1) * len(frames)])
        c, n = _offset_cost(
            E, left[frames], right, 0, np.arange(len(frames)), f_left, f_right, gate_px
        )
        if n >= max(10, len(frames) // 10):
            costs[k] = c
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

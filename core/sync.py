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
does not depend on the two cameras seeing the motion alike. The integer
minimum is refined to a sub-frame value with a parabola through the costs at
``K - 1, K, K + 1`` (reported only; the pipeline pairs whole frames).

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
MAX_FRAMES_USED = 3000


@dataclass(frozen=True)
class SyncEstimate:
    """The estimated frame offset.

    Attributes
    ----------
    offset_frames : int
        Integer offset used to pair frames (right ``j`` <-> left ``j + K``).
    offset_subframe : float
        Sub-frame refinement of the offset (frames); equals ``offset_frames``
        when no refinement was possible.
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

    def to_result(self) -> dict[str, object]:
        """The ``sync`` object of result.json."""
        out: dict[str, object] = {
            "offset_frames": float(self.offset_frames),
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
    sub = float(offsets[best])
    if 0 < best < len(offsets) - 1 and np.all(np.isfinite(costs[best - 1 : best + 2])):
        c_m, c_0, c_p = costs[best - 1], costs[best], costs[best + 1]
        denom = c_m - 2 * c_0 + c_p
        if denom > 0:
            sub += float(np.clip(0.5 * (c_m - c_p) / denom, -0.5, 0.5))
    return SyncEstimate(int(offsets[best]), sub, confidence, "auto", offsets, costs)


def given_offset(offset_frames: float) -> SyncEstimate:
    """A user-given offset (``--offset-frames``), rounded to whole frames for pairing."""
    if not np.isfinite(offset_frames):
        raise ValueError(f"offset_frames must be finite, got {offset_frames}")
    return SyncEstimate(round(offset_frames), float(offset_frames), 1.0, "given")

"""Stereo matching of marker detections with the epipolar constraint.

Points are undistorted first (:meth:`core.camera.Camera.undistort_points`), so
the constraint is exact for any lens model: ``x_right^T E x_left = 0`` with the
rig's essential matrix. The distance of a pair to the constraint is measured in
pixels, symmetrically: the RMS of the distance of each point to the epipolar
line of the other, converted from normalized units with the camera's focal
length.

:func:`candidate_pairs` keeps every pair within the gate (the tracker chooses
among them with its motion prediction); :func:`match_stereo` also makes a
one-to-one choice by a global assignment (Hungarian method) that minimises the
summed epipolar distance, which is what a frame without history can do when
there are more than two candidates per camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from core.camera import StereoRig

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class StereoMatches:
    """Pairs of detections, one row per pair.

    Attributes
    ----------
    left_index, right_index : ndarray, shape (K,)
        Row indices into the left and right point arrays.
    epipolar_px : ndarray, shape (K,)
        Symmetric epipolar distance of each pair (px).
    """

    left_index: IntArray
    right_index: IntArray
    epipolar_px: FloatArray

    def __len__(self) -> int:
        return int(self.left_index.shape[0])


def _homogeneous(xy: FloatArray) -> FloatArray:
    return np.concatenate([xy, np.ones((*xy.shape[:-1], 1))], axis=-1)


def epipolar_distances_px(
    rig: StereoRig, left_norm: ArrayLike, right_norm: ArrayLike
) -> FloatArray:
    """Symmetric epipolar distance of every left/right pair.

    Parameters
    ----------
    rig : StereoRig
    left_norm : array_like, shape (N, 2)
        Undistorted normalized left points.
    right_norm : array_like, shape (M, 2)
        Undistorted normalized right points.

    Returns
    -------
    ndarray, shape (N, M)
        ``sqrt((d_left^2 + d_right^2) / 2)`` in pixels, where ``d_right`` is the
        distance of the right point to the epipolar line of the left point (and
        vice versa), scaled by each camera's mean focal length. NaN where a
        point is NaN.
    """
    left = np.asarray(left_norm, dtype=np.float64).reshape(-1, 2)
    right = np.asarray(right_norm, dtype=np.float64).reshape(-1, 2)
    E = rig.essential_matrix
    hl = _homogeneous(left)  # (N, 3)
    hr = _homogeneous(right)  # (M, 3)
    lines_in_right = hl @ E.T  # (N, 3): E x_left
    lines_in_left = hr @ E  # (M, 3): E^T x_right
    algebraic = hl @ E.T @ hr.T  # (N, M): x_right^T E x_left
    with np.errstate(divide="ignore", invalid="ignore"):
        d_right = np.abs(algebraic) / np.linalg.norm(lines_in_right[:, :2], axis=1)[:, None]
        d_left = np.abs(algebraic) / np.linalg.norm(lines_in_left[:, :2], axis=1)[None, :]
    f_left = 0.5 * (rig.left.K[0, 0] + rig.left.K[1, 1])
    f_right = 0.5 * (rig.right.K[0, 0] + rig.right.K[1, 1])
    result: NDArray[np.float64] = np.sqrt(0.5 * ((d_left * f_left) ** 2 + (d_right * f_right) ** 2))
    return result


@dataclass(frozen=True)
class FramePairs:
    """Every left/right detection pair of every left frame, flat, one row per pair.

    Rows are in frame order, then left index, then right index (the order of
    ``np.nonzero`` on each frame's ``(N, M)`` distance matrix).

    Attributes
    ----------
    frame : ndarray, shape (K,)
        Left frame of the pair (the right frame is ``frame - offset``).
    left_index, right_index : ndarray, shape (K,)
        Row of the detection within its frame.
    left_row, right_row : ndarray, shape (K,)
        Row of the detection in all the frames' detections concatenated.
    epipolar_px : ndarray, shape (K,)
        Symmetric epipolar distance of the pair (px), as :func:`epipolar_distances_px`.
    """

    frame: IntArray
    left_index: IntArray
    right_index: IntArray
    left_row: IntArray
    right_row: IntArray
    epipolar_px: FloatArray

    def __len__(self) -> int:
        return int(self.frame.shape[0])


def _points_2d(frame: ArrayLike) -> FloatArray:
    a = np.asarray(frame, dtype=np.float64)
    if a.size == 0:
        return a.reshape(0, 2)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"each frame's points must have shape (n, 2), got {a.shape}")
    return a


def concatenate_frames(frames: Sequence[ArrayLike]) -> tuple[FloatArray, IntArray]:
    """The points ``(n_i, 2)`` of all frames in one ``(sum n_i, 2)`` array, and each ``n_i``."""
    if not len(frames):
        return np.zeros((0, 2)), np.zeros(0, np.intp)
    try:  # the usual case, frames already (n_i, 2): one call, no per-frame conversion
        flat = np.concatenate(frames, axis=0)
    except ValueError:  # frames of different dimensions (an empty frame as shape (0,)): below
        flat = np.zeros((0, 0))
    if flat.ndim == 2 and flat.shape[1] == 2:
        counts = np.array([len(f) for f in frames], dtype=np.intp)  # type: ignore[arg-type]
        if int(counts.sum()) == len(flat):
            return flat.astype(np.float64, copy=False), counts
    parts = [_points_2d(f) for f in frames]  # raises for a frame that is not (n, 2)
    counts = np.array([len(f) for f in parts], dtype=np.intp)
    return np.concatenate(parts, axis=0), counts


def frame_pairs_epipolar_px(
    rig: StereoRig,
    left_norm: Sequence[ArrayLike],
    right_norm: Sequence[ArrayLike],
    offset: int = 0,
) -> FramePairs:
    """Symmetric epipolar distance of every pair of every frame, in one vectorised pass.

    Left frame ``i`` is paired with right frame ``i - offset`` (when it exists);
    every detection of the one is paired with every detection of the other.
    The distances are those of :func:`epipolar_distances_px` on each frame
    (to rounding: the algebraic error is summed per pair instead of by a
    matrix product).

    Parameters
    ----------
    rig : StereoRig
    left_norm, right_norm : sequence of array_like, each shape (n_i, 2)
        Undistorted normalized points of each frame of each camera.
    offset : int
        Frame offset of the right video.

    Returns
    -------
    FramePairs
    """
    left_flat, left_counts = concatenate_frames(left_norm)
    right_flat, right_counts = concatenate_frames(right_norm)
    n_left, n_right = len(left_counts), len(right_counts)
    left_start = np.concatenate([[0], np.cumsum(left_counts)]).astype(np.intp)
    right_start = np.concatenate([[0], np.cumsum(right_counts)]).astype(np.intp)
    # Right frame paired with each left frame, and its detection count (0 when none).
    j = np.arange(n_left, dtype=np.intp) - offset
    has_right = (j >= 0) & (j < n_right)
    j_safe = np.where(has_right, j, 0)
    nr = np.where(has_right, right_counts[j_safe] if n_right else 0, 0).astype(np.intp)
    per_frame = left_counts * nr
    total = int(per_frame.sum())
    frame = np.repeat(np.arange(n_left, dtype=np.intp), per_frame)
    first = np.concatenate([[0], np.cumsum(per_frame)[:-1]]).astype(np.intp)
    within = np.arange(total, dtype=np.intp) - first[frame]
    nr_pair = nr[frame]
    li = within // nr_pair if total else within
    ri = within - li * nr_pair
    left_row = left_start[frame] + li
    right_row = right_start[j_safe[frame]] + ri
    if total == 0:
        return FramePairs(frame, li, ri, left_row, right_row, np.zeros(0))
    E = rig.essential_matrix
    hl = _homogeneous(left_flat)  # all left detections (NL, 3)
    hr = _homogeneous(right_flat)  # all right detections (NR, 3)
    lines_in_right = hl @ E.T  # (NL, 3): E x_left
    lines_in_left = hr @ E  # (NR, 3): E^T x_right
    norm_right = np.linalg.norm(lines_in_right[:, :2], axis=1)
    norm_left = np.linalg.norm(lines_in_left[:, :2], axis=1)
    lr = lines_in_right[left_row]
    pr = hr[right_row]
    algebraic = lr[:, 0] * pr[:, 0] + lr[:, 1] * pr[:, 1] + lr[:, 2] * pr[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        d_right = np.abs(algebraic) / norm_right[left_row]
        d_left = np.abs(algebraic) / norm_left[right_row]
    f_left = 0.5 * (rig.left.K[0, 0] + rig.left.K[1, 1])
    f_right = 0.5 * (rig.right.K[0, 0] + rig.right.K[1, 1])
    d = np.sqrt(0.5 * ((d_left * f_left) ** 2 + (d_right * f_right) ** 2))
    return FramePairs(frame, li, ri, left_row, right_row, d)


def candidate_pairs(
    rig: StereoRig,
    left_norm: ArrayLike,
    right_norm: ArrayLike,
    *,
    max_epipolar_px: float = 2.0,
) -> StereoMatches:
    """Every left/right pair within ``max_epipolar_px`` of the epipolar constraint.

    A detection may appear in several pairs; sorted by increasing distance.
    """
    if max_epipolar_px <= 0:
        raise ValueError(f"max_epipolar_px must be positive, got {max_epipolar_px}")
    d = epipolar_distances_px(rig, left_norm, right_norm)
    with np.errstate(invalid="ignore"):
        li, ri = np.nonzero(d <= max_epipolar_px)
    order = np.argsort(d[li, ri], kind="stable")
    return StereoMatches(li[order].astype(np.intp), ri[order].astype(np.intp), d[li, ri][order])


def match_stereo(
    rig: StereoRig,
    left_px: ArrayLike,
    right_px: ArrayLike,
    *,
    max_epipolar_px: float = 2.0,
) -> StereoMatches:
    """One-to-one epipolar matching of detections in the two images.

    Parameters
    ----------
    rig : StereoRig
    left_px : array_like, shape (N, 2)
        Distorted pixel points of the left image.
    right_px : array_like, shape (M, 2)
        Distorted pixel points of the right image.
    max_epipolar_px : float
        Gate: pairs farther from the epipolar constraint are never matched (px).

    Returns
    -------
    StereoMatches
        At most ``min(N, M)`` pairs minimising the summed epipolar distance,
        each detection used once, all within the gate.
    """
    if max_epipolar_px <= 0:
        raise ValueError(f"max_epipolar_px must be positive, got {max_epipolar_px}")
    left = np.asarray(left_px, dtype=np.float64).reshape(-1, 2)
    right = np.asarray(right_px, dtype=np.float64).reshape(-1, 2)
    empty = StereoMatches(np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0))
    if len(left) == 0 or len(right) == 0:
        return empty
    d = epipolar_distances_px(
        rig, rig.left.undistort_points(left), rig.right.undistort_points(right)
    )
    return assign_pairs(d, max_cost=max_epipolar_px)


def assign_pairs(cost: ArrayLike, *, max_cost: float) -> StereoMatches:
    """Global one-to-one assignment on a ``(N, M)`` cost matrix, pairs above ``max_cost`` dropped."""
    c = np.asarray(cost, dtype=np.float64)
    if c.ndim != 2:
        raise ValueError(f"cost must be a 2D matrix, got shape {c.shape}")
    if c.size == 0:
        return StereoMatches(np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0))
    gated = np.where(np.isfinite(c) & (c <= max_cost), c, max_cost * 1e3 + 1e6)
    rows, cols = linear_sum_assignment(gated)
    keep = np.isfinite(c[rows, cols]) & (c[rows, cols] <= max_cost)
    rows, cols = rows[keep], cols[keep]
    return StereoMatches(rows.astype(np.intp), cols.astype(np.intp), c[rows, cols])

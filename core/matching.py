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
    return np.sqrt(0.5 * ((d_left * f_left) ** 2 + (d_right * f_right) ** 2))


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

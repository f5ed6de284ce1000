"""Triangulation of matched image points into 3D (mm), in the rig's world frame.

Two steps, both vectorised over points:

1. a linear start: the DLT solution on *undistorted* normalized coordinates
   (:meth:`core.camera.Camera.undistort_points`), which is exact for noise-free
   points and a good start otherwise;
2. a refinement that minimises the reprojection error on the *distorted* pixel
   projection of both cameras (Gauss–Newton with Levenberg damping, 3
   unknowns per point), i.e. the maximum-likelihood point for isotropic pixel
   noise.

The reprojection error of a point is the root mean square over the two cameras
of the pixel residual length: ``sqrt((|r_left|^2 + |r_right|^2) / 2)`` px.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core.camera import Camera, StereoRig

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Triangulation:
    """Triangulated points.

    Attributes
    ----------
    points_mm : ndarray, shape (N, 3)
        World (left-camera) coordinates in mm; NaN where the pair could not be
        triangulated (NaN input, or a point behind a camera).
    reprojection_px : ndarray, shape (N,)
        RMS over both cameras of the pixel residual length (px).
    residuals_px : ndarray, shape (N, 2, 2)
        Projected minus observed pixels, ``[:, 0]`` left, ``[:, 1]`` right.
    """

    points_mm: FloatArray
    reprojection_px: FloatArray
    residuals_px: FloatArray

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Points that are finite (triangulated in front of both cameras)."""
        return np.all(np.isfinite(self.points_mm), axis=1)


def _check_pairs(left_px: ArrayLike, right_px: ArrayLike) -> tuple[FloatArray, FloatArray]:
    left = np.asarray(left_px, dtype=np.float64)
    right = np.asarray(right_px, dtype=np.float64)
    if left.ndim == 1 and left.shape == (2,):
        left = left[None]
    if right.ndim == 1 and right.shape == (2,):
        right = right[None]
    if left.ndim != 2 or left.shape[1] != 2:
        raise ValueError(f"left_px must have shape (N, 2), got {left.shape}")
    if right.shape != left.shape:
        raise ValueError(f"right_px must have the shape of left_px {left.shape}, got {right.shape}")
    return left, right


def triangulate_linear(rig: StereoRig, left_norm: ArrayLike, right_norm: ArrayLike) -> FloatArray:
    """DLT triangulation of undistorted normalized coordinates.

    Parameters
    ----------
    rig : StereoRig
    left_norm, right_norm : array_like, shape (N, 2)
        Undistorted normalized coordinates (``Camera.undistort_points``).

    Returns
    -------
    ndarray, shape (N, 3)
        World points in mm; NaN for NaN input.
    """
    left, right = _check_pairs(left_norm, right_norm)
    n = left.shape[0]
    out = np.full((n, 3), np.nan)
    ok = np.all(np.isfinite(left), axis=1) & np.all(np.isfinite(right), axis=1)
    if not np.any(ok):
        return out
    P_left = rig.left.projection_matrix_normalized
    P_right = rig.right.projection_matrix_normalized
    a = np.empty((int(ok.sum()), 4, 4))
    for row, (P, xy) in enumerate(((P_left, left[ok]), (P_right, right[ok]))):
        a[:, 2 * row] = xy[:, 0:1] * P[2] - P[0]
        a[:, 2 * row + 1] = xy[:, 1:2] * P[2] - P[1]
    # Row scaling keeps the SVD well conditioned for points far from the rig.
    a /= np.linalg.norm(a, axis=2, keepdims=True)
    _, _, vt = np.linalg.svd(a)
    h = vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        out[ok] = h[:, :3] / h[:, 3:4]
    return out


def _project_both(rig: StereoRig, points_mm: FloatArray) -> tuple[FloatArray, FloatArray]:
    return rig.left.project(points_mm), rig.right.project(points_mm)


def _depths_positive(cam: Camera, points_mm: FloatArray) -> NDArray[np.bool_]:
    with np.errstate(invalid="ignore"):
        return cam.to_camera(points_mm)[:, 2] > 0


def triangulate(
    rig: StereoRig,
    left_px: ArrayLike,
    right_px: ArrayLike,
    *,
    refine: bool = True,
    max_iter: int = 10,
    tol_mm: float = 1e-7,
) -> Triangulation:
    """Triangulate matched distorted pixel points of the two cameras.

    Parameters
    ----------
    rig : StereoRig
    left_px, right_px : array_like, shape (N, 2)
        Matched pixel coordinates (OpenCV's ``(x, y)``, distorted, as detected).
    refine : bool
        Minimise the reprojection error after the linear start (default).
    max_iter : int
        Gauss–Newton iterations at most.
    tol_mm : float
        Stop when every point moved less than this (mm).

    Returns
    -------
    Triangulation
        Points (N, 3) mm, reprojection error (N,) px and residuals (N, 2, 2) px.
    """
    left, right = _check_pairs(left_px, right_px)
    if max_iter < 0:
        raise ValueError(f"max_iter must be >= 0, got {max_iter}")
    points = triangulate_linear(
        rig, rig.left.undistort_points(left), rig.right.undistort_points(right)
    )
    front = _depths_positive(rig.left, points) & _depths_positive(rig.right, points)
    points[~front] = np.nan
    observed = np.concatenate([left, right], axis=1)  # (N, 4)
    ok = np.all(np.isfinite(points), axis=1)
    if refine and np.any(ok):
        x = points[ok]
        obs = observed[ok]
        lam = np.full(len(x), 1e-6)
        step_mm = 1e-4 * np.maximum(
            1.0, np.linalg.norm(x, axis=1)
        )  # relative finite-difference step
        for _ in range(max_iter):
            n = len(x)
            stacked = np.concatenate(
                [
                    x,
                    x + step_mm[:, None] * np.array([1.0, 0, 0]),
                    x + step_mm[:, None] * np.array([0, 1.0, 0]),
                    x + step_mm[:, None] * np.array([0, 0, 1.0]),
                ]
            )
            pl, pr = _project_both(rig, stacked)
            proj = np.concatenate([pl, pr], axis=1).reshape(4, n, 4)
            r = proj[0] - obs  # (n, 4)
            J = np.stack([(proj[k + 1] - proj[0]) / step_mm[:, None] for k in range(3)], axis=2)
            JtJ = np.einsum("nij,nik->njk", J, J)
            Jtr = np.einsum("nij,ni->nj", J, r)
            JtJ_damped = (
                JtJ
                + lam[:, None, None] * np.eye(3) * np.trace(JtJ, axis1=1, axis2=2)[:, None, None]
            )
            delta = -np.linalg.solve(JtJ_damped, Jtr[:, :, None])[:, :, 0]
            if not np.all(np.isfinite(delta)):
                delta = np.where(np.isfinite(delta), delta, 0.0)
            x_new = x + delta
            pl_new, pr_new = _project_both(rig, x_new)
            r_new = np.concatenate([pl_new, pr_new], axis=1) - obs
            better = np.sum(r_new**2, axis=1) <= np.sum(r**2, axis=1)
            better &= np.all(np.isfinite(r_new), axis=1)
            x = np.where(better[:, None], x_new, x)
            lam = np.where(better, lam * 0.1, lam * 10.0)
            if np.all(np.abs(delta[better]) < tol_mm) if np.any(better) else True:
                break
        points[ok] = x
    pl, pr = _project_both(rig, points)
    residuals = np.stack([pl - left, pr - right], axis=1)
    reproj = np.sqrt(np.sum(residuals**2, axis=(1, 2)) / 2.0)
    return Triangulation(points_mm=points, reprojection_px=reproj, residuals_px=residuals)

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
from core.geometry_kernels import _geometry

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
        result: NDArray[np.bool_] = np.all(np.isfinite(self.points_mm), axis=1)
        return result


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


class _Projector:
    """``Camera.project`` with the same floating-point operations, as two coordinate arrays.

    The refinement projects about 50 times as many points as it triangulates, so
    this skips the work that cannot change a bit of the result: the terms of
    the lens model whose coefficient is zero (``0 * v`` added to a finite sum,
    a rational denominator of exactly 1) and the column stacking. Every other
    operation is the one :meth:`core.camera.Camera.project` and
    :func:`core.camera.distort_normalized` do, in the same order, so the
    pixels are bit for bit those of ``Camera.project`` (pinned by a test).
    Sensor tilt, or a point so far off axis that a skipped term would not be
    finite, goes through ``Camera.project`` itself.
    """

    # Beyond this squared normalized radius a skipped term ``0 * r2**3`` could overflow.
    _MAX_R2 = 1e30

    def __init__(self, cam: Camera) -> None:
        self.cam = cam
        d = np.zeros(14)
        d[: cam.dist.shape[0]] = cam.dist
        self.k1, self.k2, self.p1, self.p2, self.k3 = (float(v) for v in d[:5])
        self.rational = bool(np.any(d[5:8] != 0.0))
        self.thin_prism = bool(np.any(d[8:12] != 0.0))
        self.general = bool(np.any(d[12:14] != 0.0)) or self.rational or self.thin_prism
        self.identity = bool(
            np.all(cam.R_cam_from_world == np.eye(3)) and np.all(cam.t_cam_from_world_mm == 0.0)
        )
        self.fx, self.fy = float(cam.K[0, 0]), float(cam.K[1, 1])
        self.cx, self.cy = float(cam.K[0, 2]), float(cam.K[1, 2])

    def _to_camera(self, points_mm: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``Camera.to_camera`` as three columns: the same product, ``t`` added per column.

        For the identity pose (the left camera) of finite points the product is
        exact, so it is skipped.
        """
        if self.identity and np.all(np.isfinite(points_mm)):
            return points_mm[:, 0], points_mm[:, 1], points_mm[:, 2]
        rotated = points_mm @ self.cam.R_cam_from_world.T
        t = self.cam.t_cam_from_world_mm
        return rotated[:, 0] + t[0], rotated[:, 1] + t[1], rotated[:, 2] + t[2]

    def __call__(self, points_mm: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Distorted pixels ``(u, v)``, each ``(N,)``, of world points ``(N, 3)`` mm."""
        if self.general:
            px = self.cam.project(points_mm)
            return px[:, 0], px[:, 1]
        x, y, z = self._to_camera(points_mm)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = x / z
            y = y / z
        behind = z <= 0
        if np.any(behind):
            x[behind] = np.nan
            y[behind] = np.nan
        r2 = x * x + y * y
        if np.any(r2 > self._MAX_R2):
            px = self.cam.project(points_mm)
            return px[:, 0], px[:, 1]
        # distort_normalized: radial = (1 + k1 r2 + k2 r4 + k3 r6) / 1, then the tangential terms.
        r4 = r2 * r2
        radial = 1 + self.k1 * r2 + self.k2 * r4
        if self.k3 != 0.0:
            radial = radial + self.k3 * (r4 * r2)
        xd = x * radial
        yd = y * radial
        if self.p1 != 0.0 or self.p2 != 0.0:
            a1 = 2 * x * y
            xd = xd + self.p1 * a1 + self.p2 * (r2 + 2 * x * x)
            yd = yd + self.p1 * (r2 + 2 * y * y) + self.p2 * a1
        return xd * self.fx + self.cx, yd * self.fy + self.cy


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
    project = (_Projector(rig.left), _Projector(rig.right))
    with np.errstate(invalid="ignore"):
        front = (project[0]._to_camera(points)[2] > 0) & (project[1]._to_camera(points)[2] > 0)
    points[~front] = np.nan
    ok = np.all(np.isfinite(points), axis=1)
    if refine and np.any(ok):
        points[ok] = _refine(project, points[ok], left[ok], right[ok], max_iter, tol_mm)
    residuals = np.empty((len(points), 2, 2))
    for k, observed in enumerate((left, right)):
        u, v = project[k](points)
        residuals[:, k, 0] = u - observed[:, 0]
        residuals[:, k, 1] = v - observed[:, 1]
    reproj = np.sqrt(np.sum(residuals**2, axis=(1, 2)) / 2.0)
    return Triangulation(points_mm=points, reprojection_px=reproj, residuals_px=residuals)


def _refine(
    project: tuple[_Projector, _Projector],
    x: FloatArray,
    left: FloatArray,
    right: FloatArray,
    max_iter: int,
    tol_mm: float,
) -> FloatArray:
    """Gauss–Newton with Levenberg damping on the distorted reprojection error, per point.

    :func:`_refine_numpy`'s iterations with the projections, the Jacobian, the normal
    equations and the step's acceptance compiled (:func:`core._geometry.refine_system`,
    :func:`core._geometry.refine_accept`: ``_Projector``'s arithmetic in its order), and
    the pose products and the 3x3 solves still numpy's (BLAS and LAPACK, whose bits a
    loop of our own need not match): the points are bit for bit those of
    :func:`_refine_numpy` (a test compares), which remains for the lens models
    ``_Projector`` hands to ``Camera.project`` and, from the start, when a point goes far
    off axis.
    """
    if any(p.general for p in project):
        return _refine_numpy(project, x, left, right, max_iter, tol_mm)
    n = len(x)
    start, x = x, np.array(x, dtype=np.float64)
    lens_l, lens_r = ((p.k1, p.k2, p.p1, p.p2, p.k3, p.fx, p.fy, p.cx, p.cy) for p in project)
    obs = np.ascontiguousarray(np.column_stack([left, right]))
    lam = np.full(n, 1e-6)
    step_mm = 1e-4 * np.maximum(1.0, np.linalg.norm(x, axis=1))  # relative difference step
    offsets = step_mm[:, None] * np.eye(3)[:, None, :]  # (3, n, 3): step along each axis
    stacked = np.empty((4, n, 3))
    damped = np.empty((n, 3, 3))
    Jtr = np.empty((n, 3))
    cost = np.empty(n)

    def camera_frame(points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Camera-frame coordinates ``(3, N)`` of ``points`` in each camera (``_to_camera``)."""
        left_cam, right_cam = (np.stack(p._to_camera(points)) for p in project)
        return left_cam, right_cam

    for _ in range(max_iter):
        stacked[0] = x
        np.add(x, offsets, out=stacked[1:])
        cams = camera_frame(stacked.reshape(4 * n, 3))
        if not _geometry.refine_system(*cams, lens_l, lens_r, obs, step_mm, lam, damped, Jtr, cost):
            return _refine_numpy(project, start, left, right, max_iter, tol_mm)
        delta: FloatArray = np.negative(np.linalg.solve(damped, Jtr[:, :, None])[:, :, 0])
        if not np.all(np.isfinite(delta)):
            delta = np.where(np.isfinite(delta), delta, 0.0)
        x_new: FloatArray = np.add(x, delta)
        done = _geometry.refine_accept(
            *camera_frame(x_new), lens_l, lens_r, obs, cost, x_new, delta, x, lam, tol_mm
        )
        if done is None:
            return _refine_numpy(project, start, left, right, max_iter, tol_mm)
        if done:
            break
    return x


def _refine_numpy(
    project: tuple[_Projector, _Projector],
    x: FloatArray,
    left: FloatArray,
    right: FloatArray,
    max_iter: int,
    tol_mm: float,
) -> FloatArray:
    """Gauss–Newton with Levenberg damping on the distorted reprojection error, per point.

    The Jacobian is a forward difference with a step relative to the distance
    from the origin; all points iterate until every accepted step is below
    ``tol_mm``. The sums (``J^T J``, ``J^T r``, the trace, the cost) are
    written out on ``(n,)`` columns in the order ``einsum``, ``np.trace`` and
    ``np.sum`` take them, so the points are bit for bit those of the first
    formulation with those calls (a test keeps it so).
    """
    n = len(x)
    obs = (left[:, 0], left[:, 1], right[:, 0], right[:, 1])
    lam = np.full(n, 1e-6)
    step_mm = 1e-4 * np.maximum(1.0, np.linalg.norm(x, axis=1))  # relative difference step
    offsets = step_mm[:, None] * np.eye(3)[:, None, :]  # (3, n, 3): step along each axis
    stacked = np.empty((4, n, 3))
    damped = np.empty((n, 3, 3))
    Jtr = np.empty((n, 3))
    for _ in range(max_iter):
        stacked[0] = x
        np.add(x, offsets, out=stacked[1:])
        flat = stacked.reshape(4 * n, 3)
        # proj[c]: (4, n) pixel coordinate c (left u, left v, right u, right v) of x and x + steps
        proj = [p.reshape(4, n) for cam in project for p in cam(flat)]
        J = [[(pc[k + 1] - pc[0]) / step_mm for k in range(3)] for pc in proj]  # J[c][k]: (n,)
        r = [pc[0] - o for pc, o in zip(proj, obs, strict=True)]
        # J^T J, its trace and J^T r, summed in the order einsum and np.trace take.
        JtJ = {}
        for j in range(3):
            for k in range(j, 3):
                JtJ[j, k] = (
                    J[0][j] * J[0][k] + J[1][j] * J[1][k] + J[2][j] * J[2][k] + J[3][j] * J[3][k]
                )
            Jtr[:, j] = J[0][j] * r[0] + J[1][j] * r[1] + J[2][j] * r[2] + J[3][j] * r[3]
        trace = JtJ[0, 0] + JtJ[1, 1] + JtJ[2, 2]
        # Levenberg: J^T J + lam * I * trace, element by element (off the diagonal 0 * trace).
        on_diagonal = lam * trace
        off_diagonal = lam * 0.0 * trace
        for (j, k), value in JtJ.items():
            damped[:, j, k] = value + (on_diagonal if j == k else off_diagonal)
            damped[:, k, j] = damped[:, j, k]
        delta = -np.linalg.solve(damped, Jtr[:, :, None])[:, :, 0]
        if not np.all(np.isfinite(delta)):
            delta = np.where(np.isfinite(delta), delta, 0.0)
        x_new = x + delta
        r_new = [p - o for p, o in zip((*project[0](x_new), *project[1](x_new)), obs, strict=True)]
        # The squared residual lengths, summed in np.sum's order.
        cost = r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3]
        cost_new = r_new[0] * r_new[0] + r_new[1] * r_new[1] + r_new[2] * r_new[2]
        cost_new += r_new[3] * r_new[3]
        better = cost_new <= cost
        for rc in r_new:
            better &= np.isfinite(rc)
        x = np.where(better[:, None], x_new, x)
        lam = np.where(better, lam * 0.1, lam * 10.0)
        if np.all(np.abs(delta[better]) < tol_mm) if np.any(better) else True:
            break
    return x

"""Triangulation: linear start + reprojection refinement, against known cameras."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from rigs import verging_rig

from core.camera import Camera, StereoRig
from core.triangulation import _Projector, _refine, _refine_numpy, triangulate, triangulate_linear


def make_rig(*, distorted: bool = True) -> StereoRig:
    return verging_rig(distorted=distorted, right_focal_scale=1.01)


def random_points(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack(
        [rng.uniform(-80, 80, n), rng.uniform(-60, 60, n), rng.uniform(420, 600, n)]
    )


def test_exact_points_are_recovered() -> None:
    rig = make_rig()
    pts = random_points(np.random.default_rng(0), 200)
    tri = triangulate(rig, rig.left.project(pts), rig.right.project(pts))
    assert tri.points_mm.shape == (200, 3)
    assert tri.reprojection_px.shape == (200,)
    assert tri.residuals_px.shape == (200, 2, 2)
    np.testing.assert_allclose(tri.points_mm, pts, atol=1e-6)  # mm
    assert np.max(tri.reprojection_px) < 1e-6  # px


def test_linear_matches_opencv_on_undistorted_points() -> None:
    rig = make_rig(distorted=False)
    pts = random_points(np.random.default_rng(1), 50)
    ln, rn = (
        rig.left.undistort_points(rig.left.project(pts)),
        rig.right.undistort_points(rig.right.project(pts)),
    )
    ours = triangulate_linear(rig, ln, rn)
    h = cv2.triangulatePoints(
        rig.left.projection_matrix_normalized, rig.right.projection_matrix_normalized, ln.T, rn.T
    )
    np.testing.assert_allclose(ours, (h[:3] / h[3]).T, atol=1e-6)  # mm
    np.testing.assert_allclose(ours, pts, atol=1e-6)  # mm


def test_noisy_points_refinement_beats_linear() -> None:
    rig = make_rig()
    rng = np.random.default_rng(2)
    pts = random_points(rng, 2000)
    sigma_px = 0.1
    lp = rig.left.project(pts) + rng.normal(0, sigma_px, (2000, 2))
    rp = rig.right.project(pts) + rng.normal(0, sigma_px, (2000, 2))
    lin = triangulate(rig, lp, rp, refine=False)
    ref = triangulate(rig, lp, rp)
    err_lin = np.linalg.norm(lin.points_mm - pts, axis=1)
    err_ref = np.linalg.norm(ref.points_mm - pts, axis=1)
    # 0.1 px noise at ~500 mm with f = 1800 px: lateral 0.03 mm, depth ~0.1 mm.
    assert np.sqrt(np.mean(err_ref**2)) < 0.15  # mm
    assert np.mean(ref.reprojection_px) <= np.mean(lin.reprojection_px) + 1e-12  # px
    assert np.sqrt(np.mean(err_ref**2)) <= np.sqrt(np.mean(err_lin**2)) * 1.01
    # The residual of the ML point is the noise minus its 3 fitted dimensions: about sigma/sqrt(4/1).
    assert 0.3 * sigma_px < np.median(ref.reprojection_px) < 1.5 * sigma_px  # px


def test_wrong_pair_has_large_reprojection_error_and_nan_propagates() -> None:
    rig = make_rig()
    pts = random_points(np.random.default_rng(3), 2)
    lp, rp = rig.left.project(pts), rig.right.project(pts)
    rp_wrong = rp[::-1] + np.array([0.0, 40.0])
    tri = triangulate(rig, lp, rp_wrong)
    assert np.all(tri.reprojection_px > 5)  # px
    lp_nan = lp.copy()
    lp_nan[0] = np.nan
    tri = triangulate(rig, lp_nan, rp)
    assert np.all(np.isnan(tri.points_mm[0])) and np.isnan(tri.reprojection_px[0])
    assert np.all(np.isfinite(tri.points_mm[1]))
    assert tri.valid.tolist() == [False, True]


def test_convention_swapping_cameras_breaks_the_geometry() -> None:
    """Feeding right pixels as left must not give the true points (convention check)."""
    rig = make_rig()
    pts = random_points(np.random.default_rng(4), 20)
    tri = triangulate(rig, rig.right.project(pts), rig.left.project(pts))
    bad = ~tri.valid | (np.linalg.norm(np.nan_to_num(tri.points_mm) - pts, axis=1) > 1.0)
    assert np.all(bad)
    # The swapped rig, on the other hand, gives the same points in its own frame.
    sw = rig.swapped()
    tri_sw = triangulate(sw, rig.right.project(pts), rig.left.project(pts))
    np.testing.assert_allclose(tri_sw.points_mm, rig.right.to_camera(pts), atol=1e-6)  # mm


@pytest.mark.parametrize("shape", [(3,), (4, 3), (2, 2, 2)])
def test_shape_errors(shape: tuple[int, ...]) -> None:
    rig = make_rig()
    with pytest.raises(ValueError):
        triangulate(rig, np.zeros(shape), np.zeros(shape))
    with pytest.raises(ValueError):
        triangulate(rig, np.zeros((3, 2)), np.zeros((2, 2)))


def _rig_with(dist_left: list[float], dist_right: list[float]) -> StereoRig:
    base = make_rig()
    return StereoRig(
        Camera("left", base.left.image_size, base.left.K, np.array(dist_left)),
        Camera(
            "right",
            base.right.image_size,
            base.right.K,
            np.array(dist_right),
            base.right.R_cam_from_world,
            base.right.t_cam_from_world_mm,
        ),
    )


LENS_MODELS = {
    "radial k1 k2 (as the simulator's)": ([-0.1, 0.06, 0, 0, 0], [-0.1, 0.06, 0, 0, 0]),
    "k1..k3 and tangential": (
        [-0.12, 0.08, 0.0005, -0.0003, -0.02],
        [-0.10, 0.05, -0.0004, 0.0002, 0.0],
    ),
    "4 coefficients, p2 only": ([-0.1, 0.02, 0.0, 0.001], [0.05, 0.0, 0.0, 0.0]),
    "rational": ([-0.1, 0.02, 0, 0, 0.01, 0.05, 0.01, 0.002], [-0.1, 0.06, 0, 0, 0]),
    "thin prism and tilt": (
        [-0.1, 0.02, 0.001, 0, 0.01, 0, 0, 0, 0.001, 0, -0.002, 0.0005],
        [-0.1, 0.02, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0.01, -0.02],
    ),
    "no distortion": ([0, 0, 0, 0, 0], [0, 0, 0, 0]),
}


@pytest.mark.parametrize("model", LENS_MODELS)
def test_projector_is_camera_project_bit_for_bit(model: str) -> None:
    rig = _rig_with(*LENS_MODELS[model])
    pts = random_points(np.random.default_rng(5), 300)
    pts[0] = np.nan  # not triangulated
    pts[1] = [10.0, 5.0, -300.0]  # behind both cameras
    pts[2] = [0.0, 0.0, 0.0]  # the left centre: z = 0
    pts[3] = [1e20, 0.0, 1.0]  # far off axis: no fast path
    pts[4] = [np.inf, 0.0, 500.0]
    pts[5] = [-0.0, 0.0, 500.0]
    for cam in rig.cameras:
        with np.errstate(invalid="ignore"):  # inf * 0 in the pose product
            want = cam.project(pts)
        for rows in (slice(None), slice(6, None)):  # with and without the special points
            with np.errstate(invalid="ignore"):
                u, v = _Projector(cam)(pts[rows])
            assert np.array_equal(u, want[rows, 0], equal_nan=True)
            assert np.array_equal(v, want[rows, 1], equal_nan=True)
        assert np.all(np.isfinite(want[6:]))


def _reference_triangulate(
    rig: StereoRig, left: np.ndarray, right: np.ndarray, max_iter: int = 10, tol_mm: float = 1e-7
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The refinement as first written (Camera.project, einsum): the fast one must equal it."""
    points = triangulate_linear(
        rig, rig.left.undistort_points(left), rig.right.undistort_points(right)
    )
    with np.errstate(invalid="ignore"):
        front = (rig.left.to_camera(points)[:, 2] > 0) & (rig.right.to_camera(points)[:, 2] > 0)
    points[~front] = np.nan
    observed = np.concatenate([left, right], axis=1)
    ok = np.all(np.isfinite(points), axis=1)
    if np.any(ok):
        x, obs = points[ok], observed[ok]
        lam = np.full(len(x), 1e-6)
        step_mm = 1e-4 * np.maximum(1.0, np.linalg.norm(x, axis=1))
        for _ in range(max_iter):
            n = len(x)
            stacked = np.concatenate(
                [x] + [x + step_mm[:, None] * np.eye(3)[k] for k in range(3)]  # type: ignore[operator]
            )
            proj = np.concatenate(
                [rig.left.project(stacked), rig.right.project(stacked)], axis=1
            ).reshape(4, n, 4)
            r = proj[0] - obs
            J = np.stack([(proj[k + 1] - proj[0]) / step_mm[:, None] for k in range(3)], axis=2)
            JtJ = np.einsum("nij,nik->njk", J, J)
            Jtr = np.einsum("nij,ni->nj", J, r)
            damped = (
                JtJ
                + lam[:, None, None] * np.eye(3) * np.trace(JtJ, axis1=1, axis2=2)[:, None, None]
            )
            delta = -np.linalg.solve(damped, Jtr[:, :, None])[:, :, 0]
            delta = np.where(np.isfinite(delta), delta, 0.0)
            x_new = x + delta
            r_new = (
                np.concatenate([rig.left.project(x_new), rig.right.project(x_new)], axis=1) - obs
            )
            better = np.sum(r_new**2, axis=1) <= np.sum(r**2, axis=1)
            better &= np.all(np.isfinite(r_new), axis=1)
            x = np.where(better[:, None], x_new, x)
            lam = np.where(better, lam * 0.1, lam * 10.0)
            if np.all(np.abs(delta[better]) < tol_mm) if np.any(better) else True:
                break
        points[ok] = x
    residuals = np.stack(
        [rig.left.project(points) - left, rig.right.project(points) - right], axis=1
    )
    return points, np.sqrt(np.sum(residuals**2, axis=(1, 2)) / 2.0), residuals


@pytest.mark.parametrize("model", LENS_MODELS)
@pytest.mark.parametrize("max_iter", [0, 2, 10])
def test_refinement_equals_the_reference_bit_for_bit(model: str, max_iter: int) -> None:
    """Same points and residuals as the first formulation, to the last bit.

    The refinement stops at a damped step the rounding of the cost happens to
    accept, so its points depend on every bit of the arithmetic (at ~1e-8 mm).
    """
    rig = _rig_with(*LENS_MODELS[model])
    rng = np.random.default_rng(6)
    pts = random_points(rng, 400)
    lp = rig.left.project(pts) + rng.normal(0, 0.3, (400, 2))
    rp = rig.right.project(pts) + rng.normal(0, 0.3, (400, 2))
    rp[:60] = rp[rng.permutation(60)] + rng.normal(0, 2.0, (60, 2))  # wrong pairs
    lp[60] = np.nan
    rp[61] = [5000.0, 5000.0]  # cannot be undistorted
    tri = triangulate(rig, lp, rp, max_iter=max_iter)
    points, reproj, residuals = _reference_triangulate(rig, lp, rp, max_iter=max_iter)
    assert np.array_equal(tri.points_mm, points, equal_nan=True)
    assert np.array_equal(tri.reprojection_px, reproj, equal_nan=True)
    assert np.array_equal(tri.residuals_px, residuals, equal_nan=True)
    assert np.count_nonzero(tri.valid) > 300


@pytest.mark.parametrize("model", LENS_MODELS)
def test_compiled_refinement_equals_the_numpy_one_bit_for_bit(model: str) -> None:
    """The compiled iterations (``_geometry.refine_system``/``refine_accept``) give the points
    of the numpy ones, also when a point's step takes it far off axis mid-way (then the numpy
    iterations take over from the start)."""
    rig = _rig_with(*LENS_MODELS[model])
    rng = np.random.default_rng(8)
    pts = random_points(rng, 300)
    lp = rig.left.project(pts) + rng.normal(0, 0.3, (300, 2))
    rp = rig.right.project(pts) + rng.normal(0, 0.3, (300, 2))
    rp[:40] = rp[rng.permutation(40)] + rng.normal(0, 2.0, (40, 2))  # wrong pairs
    project = (_Projector(rig.left), _Projector(rig.right))
    start = pts + rng.normal(0, 0.5, pts.shape)
    far = start.copy()
    far[7] = [1e20, 0.0, 1.0]  # r2 = 1e40: Camera.project's own arithmetic
    for x0 in (start, far):
        for max_iter in (1, 10):
            with np.errstate(all="ignore"):
                got = _refine(project, x0, lp, rp, max_iter, 1e-7)
                want = _refine_numpy(project, x0, lp, rp, max_iter, 1e-7)
            assert np.array_equal(got, want, equal_nan=True)
            assert not np.array_equal(got, x0)  # it moved the points

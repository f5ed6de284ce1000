"""Triangulation: linear start + reprojection refinement, against known cameras."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from core.camera import Camera, ImageSize, StereoRig
from core.triangulation import triangulate, triangulate_linear


def make_rig(*, distorted: bool = True) -> StereoRig:
    """A verging 1280x1024 rig, 160 mm baseline, converging at 500 mm (like the simulator's)."""
    size = ImageSize(1280, 1024)
    K = np.array([[1800.0, 0, 645.0], [0, 1795.0, 508.0], [0, 0, 1]])
    dist_l = np.array([-0.12, 0.08, 0.0005, -0.0003, -0.02]) if distorted else np.zeros(5)
    dist_r = np.array([-0.10, 0.05, -0.0004, 0.0002, 0.0]) if distorted else np.zeros(5)
    angle = np.arctan2(160.0, 500.0)
    R = np.asarray(cv2.Rodrigues(np.array([0.01, -angle, 0.005]))[0], dtype=np.float64)
    c_right = np.array([160.0, 2.0, 0.0])  # right camera centre in the left frame (mm)
    t = -R @ c_right
    return StereoRig(
        Camera("left", size, K, dist_l),
        Camera("right", size, K * [[1.01], [1.01], [1]], dist_r, R, t),
    )


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

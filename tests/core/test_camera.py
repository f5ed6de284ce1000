"""Camera model: projection against OpenCV, back-projection round trips, rig file."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from core.camera import (
    Camera,
    ImageSize,
    StereoRig,
    distort_normalized,
    read_rig,
    rig_from_dict,
    rig_to_dict,
    write_rig,
)
from core.errors import RigFileError

SIZE = ImageSize(1280, 1024)
K = np.array([[1500.0, 0.0, 652.3], [0.0, 1498.0, 505.9], [0.0, 0.0, 1.0]])

# Distortion sets of every length OpenCV accepts; the 5-coefficient one is a
# strong barrel lens (corners move by tens of pixels).
DISTS = {
    4: np.array([-0.21, 0.09, 0.0012, -0.0007]),
    5: np.array([-0.42, 0.26, 0.0011, -0.0006, -0.09]),
    8: np.array([-0.3, 0.1, 0.001, -0.0005, -0.02, 0.05, 0.01, 0.002]),
    12: np.array([-0.3, 0.1, 0.001, -0.0005, -0.02, 0.05, 0.01, 0.002, 0.001, -0.002, 5e-4, 1e-3]),
    14: np.array(
        [
            -0.3,
            0.1,
            0.001,
            -0.0005,
            -0.02,
            0.05,
            0.01,
            0.002,
            0.001,
            -0.002,
            5e-4,
            1e-3,
            0.01,
            -0.02,
        ]
    ),
}


def _camera(dist: np.ndarray, rvec=(0.1, -0.2, 0.05), t=(10.0, -20.0, 5.0)) -> Camera:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))
    return Camera("left", SIZE, K, dist, R, np.asarray(t))


def _points_in_view(cam: Camera, n: int, seed: int = 0) -> np.ndarray:
    """World points that project inside the image (depth 300-900 mm)."""
    rng = np.random.default_rng(seed)
    px = rng.uniform([0, 0], [SIZE.width - 1, SIZE.height - 1], (n, 2))
    depth = rng.uniform(300, 900, n)
    return cam.backproject_depth(px, depth)


@pytest.mark.parametrize("n_coeffs", sorted(DISTS))
def test_project_matches_opencv(n_coeffs):
    dist = DISTS[n_coeffs]
    cam = _camera(dist)
    pts = np.random.default_rng(1).uniform([-200, -200, 400], [200, 200, 900], (2000, 3))
    ref, _ = cv2.projectPoints(pts, cam.rvec, cam.t_cam_from_world_mm, K, dist)
    np.testing.assert_allclose(cam.project(pts), ref.reshape(-1, 2), rtol=0, atol=1e-9)  # px


@pytest.mark.parametrize("n_coeffs", sorted(DISTS))
def test_backprojection_inverts_projection_over_whole_image(n_coeffs):
    cam = _camera(DISTS[n_coeffs])
    u, v = np.meshgrid(
        np.linspace(-0.5, SIZE.width - 0.5, 97), np.linspace(-0.5, SIZE.height - 0.5, 77)
    )
    px = np.column_stack([u.ravel(), v.ravel()])
    xy = cam.undistort_points(px)
    assert not np.isnan(xy).any()
    back = cam.normalized_to_pixels(distort_normalized(xy, cam.dist))
    np.testing.assert_allclose(back, px, rtol=0, atol=1e-6)  # px
    # Through 3D as well: a point on each ray projects back onto its pixel.
    origins, dirs = cam.backproject(px)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(cam.project(origins + 500.0 * dirs), px, rtol=0, atol=1e-6)  # px


@pytest.mark.parametrize("n_coeffs", sorted(DISTS))
def test_compiled_undistortion_gives_the_numpy_formulation_bit_for_bit(n_coeffs):
    # core/_geometry.pyx's Newton loop (no sensor tilt; 14 coefficients stay in numpy) must
    # give the former numpy formulation's bits, NaN included: whole batches (every point
    # steps until all have converged), one point, none, points beyond the invertible region
    # of the lens, NaN input and a capped number of steps.
    from geometry_reference import undistort_normalized_reference

    from core.camera import undistort_normalized

    dist = DISTS[n_coeffs]
    rng = np.random.default_rng(n_coeffs)
    inside = rng.uniform(-0.55, 0.55, (3000, 2))
    inside[::97] = np.nan
    beyond = rng.uniform(-6.0, 6.0, (300, 2))
    with np.errstate(all="ignore"):  # the numpy formulation overflows beyond the lens
        for batch in (inside, beyond, np.vstack([beyond, inside]), inside[5:6], inside[:0]):
            for max_iter in (50, 4, 1, 0):
                want = undistort_normalized_reference(batch, dist, max_iter=max_iter)
                got = undistort_normalized(batch, dist, max_iter=max_iter)
                assert got.shape == want.shape
                assert np.array_equal(got, want, equal_nan=True)
        # the branch that gives up is exercised: points the Newton steps cannot invert (the
        # 4-coefficient lens, k2 > 0 without k3, inverts everywhere)
        assert np.any(np.isnan(undistort_normalized_reference(beyond, dist))) == (n_coeffs != 4)


def test_strong_barrel_distortion_is_strong():
    """Guard: the 'strong' lens really moves the corners by tens of pixels."""
    cam = _camera(DISTS[5])
    corner = np.array([[0.0, 0.0]])
    assert np.linalg.norm(cam.undistort_pixels(corner) - corner) > 50.0  # px


def test_undistort_agrees_with_opencv_under_mild_distortion():
    cam = _camera(DISTS[4])
    px = np.random.default_rng(3).uniform([0, 0], [1279, 1023], (500, 2))
    ref = cv2.undistortPoints(
        px.reshape(-1, 1, 2), K, cam.dist, criteria=(cv2.TERM_CRITERIA_COUNT, 100, 0)
    ).reshape(-1, 2)
    np.testing.assert_allclose(cam.undistort_points(px), ref, atol=1e-9)


def test_points_behind_camera_project_to_nan():
    cam = _camera(DISTS[5], rvec=(0, 0, 0), t=(0, 0, 0))
    out = cam.project(np.array([[0.0, 0.0, -100.0], [0.0, 0.0, 500.0]]))
    assert np.isnan(out[0]).all() and np.isfinite(out[1]).all()


def test_pixel_convention_principal_point():
    """A point on the optical axis lands on (cx, cy) = (column, row), not (row, column)."""
    cam = Camera("left", SIZE, K, np.zeros(5))
    np.testing.assert_allclose(cam.project([[0.0, 0.0, 700.0]]), [[652.3, 505.9]], atol=1e-12)
    # +x in the camera frame is to the right (growing column), +y is down (growing row).
    right_down = cam.project([[10.0, 20.0, 700.0]])[0]
    assert right_down[0] > 652.3 and right_down[1] > 505.9


def test_image_size_of_image_is_width_height():
    assert ImageSize.of_image(np.zeros((1024, 1280), np.uint8)) == (1280, 1024)
    assert ImageSize.of_image(np.zeros((1024, 1280, 3), np.uint8)).width == 1280


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"K": np.eye(2)}, "shape"),
        ({"K": np.array([[1.0, 0.1, 0], [0, 1, 0], [0, 0, 1]])}, "K must be"),
        ({"dist": np.zeros(6)}, "4, 5, 8, 12 or 14"),
        ({"R_cam_from_world": np.diag([1.0, 1.0, -1.0])}, "rotation"),
        ({"t_cam_from_world_mm": np.zeros(2)}, "shape"),
        ({"image_size": (0, 10)}, "positive"),
    ],
)
def test_camera_validation(kwargs, match):
    args = {"name": "left", "image_size": SIZE, "K": K}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Camera(**args)


def test_project_shape_errors():
    cam = Camera("left", SIZE, K)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        cam.project(np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        cam.undistort_points(np.zeros((4, 3)))


def _rig() -> StereoRig:
    left = Camera("left", SIZE, K, DISTS[5])
    R, _ = cv2.Rodrigues(np.array([0.02, -0.45, 0.01]))
    right = Camera(
        "right", SIZE, K * [[1.01], [1.01], [1]], DISTS[8], R, np.array([-250.0, 2.0, 60.0])
    )
    return StereoRig(left, right, {"rms_px": 0.21})


def test_epipolar_constraint_and_baseline():
    rig = _rig()
    X = _points_in_view(rig.left, 400)
    X = X[rig.right.in_image(rig.right.project(X))]  # seen by both cameras
    assert len(X) > 50
    xl = rig.left.undistort_points(rig.left.project(X))
    xr = rig.right.undistort_points(rig.right.project(X))
    h = lambda a: np.column_stack([a, np.ones(len(a))])  # noqa: E731
    residual = np.einsum("ij,jk,ik->i", h(xr), rig.essential_matrix, h(xl))
    assert np.abs(residual).max() < 1e-9
    assert rig.baseline_mm == pytest.approx(np.linalg.norm(rig.right.center_world_mm), abs=1e-12)
    assert rig.baseline_mm == pytest.approx(
        np.linalg.norm(rig.right.R_cam_from_world.T @ [-250.0, 2.0, 60.0])
    )


def test_swapped_rig_sees_the_same_points():
    rig = _rig()
    X = _points_in_view(rig.left, 200)
    X = X[rig.right.in_image(rig.right.project(X))]
    swapped = rig.swapped()
    X_in_new_world = rig.right.to_camera(X)
    np.testing.assert_allclose(
        swapped.left.project(X_in_new_world), rig.right.project(X), atol=1e-9
    )
    np.testing.assert_allclose(
        swapped.right.project(X_in_new_world), rig.left.project(X), atol=1e-9
    )


def test_rig_requires_left_camera_at_world_origin():
    R, _ = cv2.Rodrigues(np.array([0.0, 0.1, 0.0]))
    with pytest.raises(ValueError, match="left camera"):
        StereoRig(Camera("left", SIZE, K, R_cam_from_world=R), Camera("right", SIZE, K))


def test_rig_file_round_trip(tmp_path):
    rig = _rig()
    path = tmp_path / "rig.json"
    write_rig(rig, path)
    doc = json.loads(path.read_text())
    assert doc["format"] == "bradyscope.rig/1" and doc["units"] == "mm"
    assert doc["cameras"][0]["image_size"] == [1280, 1024]  # [width, height]
    back = read_rig(path)
    for a, b in zip(rig.cameras, back.cameras, strict=True):
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.dist, b.dist)
        np.testing.assert_array_equal(a.R_cam_from_world, b.R_cam_from_world)
        np.testing.assert_array_equal(a.t_cam_from_world_mm, b.t_cam_from_world_mm)
        assert a.image_size == b.image_size
    assert back.quality == {"rms_px": 0.21}


def test_rig_file_ignores_unknown_keys_and_needs_no_quality():
    doc = rig_to_dict(_rig())
    doc["vendor_note"] = "x"
    doc["cameras"][1]["serial"] = "abc"
    del doc["quality"]
    assert rig_from_dict(doc).quality == {}


def _broken(mutate):
    doc = rig_to_dict(_rig())
    mutate(doc)
    return doc


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ([], "not a JSON object"),
        (_broken(lambda d: d.update(format="bradyscope.rig/2")), "bradyscope.rig/2"),
        (_broken(lambda d: d.pop("format")), "format None"),
        (_broken(lambda d: d.update(units="m")), "'m'"),
        (_broken(lambda d: d["cameras"].pop()), "exactly two cameras"),
        (_broken(lambda d: d["cameras"][0].pop("K")), "lacks K"),
        (_broken(lambda d: d["cameras"][1].update(name="left")), "expected 'right'"),
        (_broken(lambda d: d["cameras"][0].update(dist=[1, 2, 3])), "4, 5, 8, 12 or 14"),
        (_broken(lambda d: d["cameras"][0].update(t=[5, 0, 0])), "left camera"),
        (_broken(lambda d: d["cameras"][1].update(K="nonsense")), "invalid"),
    ],
)
def test_rig_file_errors(doc, match):
    with pytest.raises(RigFileError, match=match):
        rig_from_dict(doc)


def test_read_rig_file_errors(tmp_path):
    with pytest.raises(RigFileError, match="cannot read"):
        read_rig(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{ not json")
    with pytest.raises(RigFileError, match="not valid JSON"):
        read_rig(bad)
    binary = tmp_path / "video.json"
    binary.write_bytes(b"\xff\xd8\xff\xe0" * 10)
    with pytest.raises(RigFileError, match="not a text file"):
        read_rig(binary)

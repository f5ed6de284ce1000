"""Merged marker images measured along their rays from the other camera (core.merged).

Ground truth from the simulator's compositor (``core.simulation.hand``: opaque
limb-darkened markers, the nearer over the farther, on lit skin or the dark
room) at known 3D positions; the lines come from the other camera of the
default rig, as the pipeline gets them.
"""

from __future__ import annotations

import numpy as np
import pytest

from core.markers import ImagePatch
from core.merged import (
    MIN_VISIBLE,
    _lines_in_patch,
    _start_positions,
    fit_two_discs,
    measure_merged,
    measure_patch,
)
from core.simulation.hand import Capsules, SkinLook, composite_spheres, draw_skin
from core.simulation.render import DISC, SphereLayer
from core.simulation.rig import default_rig

RIG = default_rig()  # 1280 x 1024, f = 1250 px, 250 mm baseline
CAM, OTHER = RIG.left, RIG.right
NEAR_MM = np.array([10.0, -5.0, 490.0])


def _scene(
    far_mm: np.ndarray, *, skin: bool, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """uint8 left frame with two 5-mm markers (the nearer at NEAR_MM); (image, true px
    (2, 2), visible fractions (2,))."""
    canvas = np.full((1024, 1280), 14.0, np.float32)
    sk = None
    if skin:
        finger = Capsules([[-60.0, -2.0, 500.0]], [[60.0, -2.0, 500.0]], [7.0], [7.0])
        sk = draw_skin(canvas, CAM, finger, SkinLook(level=57.0))
    centres = np.array([[NEAR_MM, far_mm]])
    layer = SphereLayer(centres, np.array([2.5, 2.5]), np.array([230.0, 221.0]), DISC)
    vis = composite_spheres(canvas, CAM, layer, sk, psf_sigma_px=0.5)
    canvas += np.random.default_rng(seed).normal(0.0, 2.0, canvas.shape).astype(np.float32)
    img = np.clip(np.rint(canvas), 0, 255).astype(np.uint8)
    return img, CAM.project(centres[0]), vis


def _patch(img: np.ndarray, true_px: np.ndarray, diameter_px: float = 12.5) -> ImagePatch:
    mid = true_px.mean(axis=0)
    half = int(np.ceil(0.5 * np.ptp(true_px, axis=0).max() + diameter_px + 4))
    x0, y0 = round(float(mid[0])) - half, round(float(mid[1])) - half
    pixels = img[y0 : y0 + 2 * half + 1, x0 : x0 + 2 * half + 1].copy()
    return ImagePatch(x0, y0, pixels, mid[None], np.zeros(0, np.intp), diameter_px)


def _fit(img: np.ndarray, true_px: np.ndarray, other_px: np.ndarray):  # type: ignore[no-untyped-def]
    patch = _patch(img, true_px)
    q, u, _, depth, slope = _lines_in_patch(OTHER, CAM, other_px, true_px.mean(axis=0))
    start = _start_positions(q, u, patch.points_px)
    return fit_two_discs(
        patch.pixels,
        patch.x0,
        patch.y0,
        q,
        u,
        radius_px=6.0,
        radius_ratio=depth.mean() / depth,
        start_t_px=start,
        depth_mm=depth,
        depth_per_px=slope,
    )


@pytest.mark.parametrize("skin", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_overlapping_markers_are_measured_on_their_lines(skin: bool, seed: int) -> None:
    # the far marker 3 mm behind, its image ~6 px from the near one's: a third of it hidden
    far = NEAR_MM + np.array([0.0, 2.4, 3.0])
    img, true_px, vis = _scene(far, skin=skin, seed=seed)
    assert 0.55 < vis[1] < 0.8 and vis[0] > 0.99
    fit = _fit(img, true_px, OTHER.project(np.array([NEAR_MM, far])))
    assert fit.front == 0
    err = np.linalg.norm(fit.centres_px - true_px, axis=1)
    assert err[0] <= 0.05  # px: the whole marker in front
    assert err[1] <= 0.1  # px: the crescent behind it
    assert abs(fit.visible[1] - vis[1]) <= 0.05  # share of the disc (geometry of the fit)
    assert fit.residual <= 0.08


def test_lines_in_swapped_order_give_swapped_centres() -> None:
    far = NEAR_MM + np.array([0.0, 2.4, 3.0])
    img, true_px, _ = _scene(far, skin=False)
    other = OTHER.project(np.array([NEAR_MM, far]))
    a = _fit(img, true_px, other)
    b = _fit(img, true_px[::-1], other[::-1])
    np.testing.assert_allclose(b.centres_px, a.centres_px[::-1], atol=1e-3)  # px
    assert b.front == 1


def test_a_marker_almost_hidden_behind_the_other_is_not_measured() -> None:
    # 4 mm behind along the near marker's own ray, 0.4 mm aside: ~90 % hidden
    far = NEAR_MM * (494.0 / 490.0) + np.array([0.0, 0.4, 0.0])
    img, true_px, vis = _scene(far, skin=True)
    assert vis[1] < MIN_VISIBLE
    other = OTHER.project(np.array([NEAR_MM, far]))
    got = measure_patch(OTHER, CAM, _patch(img, true_px), other)
    assert [i for i, _ in got] == [0]  # the near one only (the far one's depth is not observed)
    assert np.linalg.norm(got[0][1] - true_px[0]) <= 0.05  # px


def test_measure_merged_replaces_the_patch_detections_and_flags_them() -> None:
    far = NEAR_MM + np.array([0.0, 2.4, 3.0])
    img, true_px, _ = _scene(far, skin=True)
    other = OTHER.project(np.array([NEAR_MM, far]))
    blob = true_px.mean(axis=0)
    patch = _patch(img, true_px)
    patch = ImagePatch(patch.x0, patch.y0, patch.pixels, blob[None], np.array([1]), 12.5)
    glint = np.array([100.0, 100.0])
    left = [np.array([glint, blob])]  # the merged blob was detected as one (row 1)
    right = [other]
    out = measure_merged(RIG, left, right, {0: [patch]}, {}, 0)
    assert (out.frames_left, out.frames_right) == (1, 0)
    assert out.left_px[0].shape == (3, 2)
    np.testing.assert_array_equal(out.left_measured[0], [False, True, True])
    np.testing.assert_array_equal(out.left_px[0][0], glint)
    np.testing.assert_allclose(out.left_px[0][1:], true_px, atol=0.1)  # px
    np.testing.assert_array_equal(out.right_px[0], other)
    # the other camera merged too in the same frames: nothing can be placed
    both = measure_merged(RIG, left, right, {0: [patch]}, {0: [patch]}, 0)
    assert both.frames_left == both.frames_right == 0


def test_fit_two_discs_rejects_bad_shapes() -> None:
    img = np.zeros((20, 20), np.uint8)
    with pytest.raises(ValueError, match="lines_q_px"):
        fit_two_discs(img, 0, 0, np.zeros((3, 2)), np.ones((2, 2)), radius_px=5.0)
    with pytest.raises(ValueError, match="patch"):
        fit_two_discs(img[:3], 0, 0, np.zeros((2, 2)), np.ones((2, 2)), radius_px=5.0)
    with pytest.raises(ValueError, match="radius_px"):
        fit_two_discs(img, 0, 0, np.zeros((2, 2)), np.ones((2, 2)), radius_px=0.0)

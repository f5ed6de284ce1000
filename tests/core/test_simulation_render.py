"""Marker rendering: the image of a sphere is centred on the projection of its centre."""

from __future__ import annotations

import numpy as np
import pytest

from core.camera import ImageSize
from core.simulation.render import (
    GLINT,
    SensorNoise,
    SphereLayer,
    add_patches,
    draw_spheres,
    intensity_centroid,
    make_background,
    sphere_patches,
    to_uint8,
)
from core.simulation.rig import default_rig

RIG = default_rig()  # 1280 x 1024, mild barrel distortion, converging cameras


def _render_one(camera, centre_mm, *, radius_mm=2.5, size=RIG.left.image_size):
    canvas = np.zeros((size.height, size.width), np.float32)
    draw_spheres(canvas, camera, SphereLayer(np.asarray(centre_mm)[None, None], radius_mm, 230.0))
    return canvas


def _centroid_near(image, px, half=20):
    """Intensity centroid of the window of +-half px around ``px`` (the marker is isolated)."""
    x0, y0 = max(int(px[0]) - half, 0), max(int(px[1]) - half, 0)
    window = image[y0 : int(px[1]) + half + 1, x0 : int(px[0]) + half + 1]
    return intensity_centroid(window, x0=x0, y0=y0)


@pytest.mark.parametrize("cam_name", ["left", "right"])
def test_centroid_is_projection_of_centre(cam_name):
    """Noise-free, isolated markers all over the image, including the distorted corners."""
    cam = getattr(RIG, cam_name)
    rng = np.random.default_rng(5)
    pixels = np.column_stack([rng.uniform(15, 1265, 40), rng.uniform(15, 1009, 40)])
    pixels[:4] = [[15, 15], [1265, 15], [15, 1009], [1265, 1009]]  # corners: strongest distortion
    depths = rng.uniform(350, 700, 40)  # mm
    errors_float, errors_u8 = [], []
    for px, z in zip(pixels, depths, strict=True):
        centre = cam.backproject_depth(px[None], z)[0]
        truth = cam.project(centre[None])[0]
        np.testing.assert_allclose(truth, px, atol=1e-6)  # px, sanity of the set-up
        canvas = _render_one(cam, centre)
        # The whole marker lies in the window: nothing else is drawn.
        assert _centroid_near(canvas, truth, 20) == pytest.approx(_centroid_near(canvas, truth, 30))
        errors_float.append(np.linalg.norm(_centroid_near(canvas, truth) - truth))
        errors_u8.append(np.linalg.norm(_centroid_near(to_uint8(canvas), truth) - truth))
    assert max(errors_float) < 0.05  # px (measured ~0.002)
    assert max(errors_u8) < 0.05  # px, after rounding to 8 bits


def test_marker_size_follows_perspective():
    cam = RIG.left
    widths = []
    for z in (400.0, 500.0, 600.0):
        canvas = _render_one(cam, [0.0, 0.0, z])
        row = canvas[int(np.rint(cam.K[1, 2]))]
        half = row.max() / 2
        widths.append(np.count_nonzero(row > half))
    # 5 mm at 500 mm with f = 1250 px is 12.5 px across (FWHM within a pixel).
    assert abs(widths[1] - 12.5) <= 1.0
    assert widths[0] > widths[1] > widths[2]
    assert 8 <= widths[2] and widths[0] <= 20


def test_sub_pixel_shift_moves_centroid():
    cam = RIG.left
    a = intensity_centroid(_render_one(cam, [0.0, 0.0, 500.0]))
    b = intensity_centroid(_render_one(cam, [0.1, 0.0, 500.0]))  # 0.1 mm = 0.25 px
    assert b[0] - a[0] == pytest.approx(0.25, abs=0.01)  # px
    assert b[1] - a[1] == pytest.approx(0.0, abs=0.01)  # px


def test_motion_blur_streaks_along_the_motion():
    cam = RIG.left
    S = 9
    start = np.array([0.0, 0.0, 500.0])
    path = start + np.linspace(0.0, 4.0, S)[:, None] * np.array([1.0, 0.0, 0.0])  # 4 mm = 10 px
    canvas = np.zeros((1024, 1280), np.float32)
    draw_spheres(canvas, cam, SphereLayer(path[:, None, :], 2.5, 230.0))
    truth = cam.project(path).mean(axis=0)
    assert np.linalg.norm(intensity_centroid(canvas) - truth) < 0.05  # px
    ys, xs = np.nonzero(canvas > 0.05 * canvas.max())
    assert np.ptp(xs) > np.ptp(ys) + 7  # px: elongated along x by the 10 px travel
    # The total light is that of one still marker (the exposure is shared out).
    still = _render_one(cam, start)
    assert canvas.sum() == pytest.approx(still.sum(), rel=0.02)


def test_glint_and_hidden_objects():
    cam = RIG.left
    canvas = np.zeros((1024, 1280), np.float32)
    centres = np.array([[[0.0, 0.0, 500.0], [50.0, 0.0, 500.0], [0.0, 0.0, -100.0]]])
    draw_spheres(canvas, cam, SphereLayer(centres, 1.0, [200.0, 0.0, 200.0], GLINT))
    # Only the first is drawn: the second has zero brightness, the third is behind the camera.
    truth = cam.project(centres[0, :1])[0]
    assert np.linalg.norm(intensity_centroid(canvas) - truth) < 0.05  # px
    assert canvas.max() == pytest.approx(200.0, rel=0.1)


def test_marker_at_image_border_is_clipped_not_crashing():
    cam = RIG.left
    centre = cam.backproject_depth(np.array([[1279.0, 500.0]]), 500.0)[0]
    canvas = _render_one(cam, centre)
    assert canvas[:, -1].max() > 100
    assert np.isfinite(canvas).all()


def test_background_and_noise():
    size = ImageSize(320, 256)
    rng = np.random.default_rng(0)
    bg = make_background(size, rng=rng)
    assert bg.shape == (256, 320) and bg.dtype == np.float32
    assert 5 < bg.mean() < 25 and bg.min() >= 0  # dark, gray levels
    noise = SensorNoise(size, sigma=2.0, rng=rng)
    a = np.zeros((256, 320), np.float32)
    b = np.zeros((256, 320), np.float32)
    noise.add_to(a)
    noise.add_to(b)
    assert a.std() == pytest.approx(2.0, rel=0.05)  # gray levels
    assert not np.array_equal(a, b)  # a new pattern every frame
    assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < 0.05


def test_layer_validation():
    with pytest.raises(ValueError, match="shape"):
        SphereLayer(np.zeros((2, 2)), 1.0, 100.0)
    with pytest.raises(ValueError, match="radius"):
        SphereLayer(np.zeros((1, 1, 3)), 0.0, 100.0)
    with pytest.raises(ValueError, match="profile"):
        SphereLayer(np.zeros((1, 1, 3)), 1.0, 100.0, "square")
    with pytest.raises(ValueError, match="float32"):
        draw_spheres(np.zeros((4, 4)), RIG.left, SphereLayer(np.zeros((1, 1, 3)), 1.0, 1.0))


def test_default_rig_geometry():
    assert RIG.baseline_mm == pytest.approx(250.0)
    # Both optical axes cross at (0, 0, 500) mm: it projects near both principal points.
    for cam in RIG.cameras:
        px = cam.project([[0.0, 0.0, 500.0]])[0]
        assert np.linalg.norm(px - cam.K[:2, 2]) < 15  # px (small mounting errors)
    # The right camera is to the right of the left one (x > 0 in the left frame).
    assert RIG.right.center_world_mm[0] > 200
    small = default_rig(image_size=ImageSize(640, 512))
    assert small.left.K[0, 0] == pytest.approx(625.0)  # same field of view


def test_to_uint8_rounds_and_saturates():
    frame = np.array([[-3.0, 0.4, 1.6, 254.6, 300.0]], np.float32)
    out = to_uint8(frame)
    assert out.dtype == np.uint8
    assert out.tolist() == [[0, 0, 2, 255, 255]]
    assert frame[0, 0] == -3.0  # the input is left unchanged


def test_noisy_copy_leaves_the_background_alone():
    size = ImageSize(64, 48)
    bg = np.full((48, 64), 10.0, np.float32)
    noise = SensorNoise(size, sigma=2.0, rng=np.random.default_rng(1))
    frame = noise.noisy(bg)
    assert np.all(bg == 10.0)
    assert frame.std() == pytest.approx(2.0, rel=0.15)  # gray levels, 3072 samples
    assert np.array_equal(SensorNoise(size, sigma=0.0, rng=np.random.default_rng(1)).noisy(bg), bg)


@pytest.mark.parametrize("hand", ["right", "left"])
def test_default_scenario_is_in_view_of_both_cameras(hand):
    from core.simulation.kinematics import TappingScenario, simulate_tapping

    truth = simulate_tapping(
        TappingScenario(hand=hand, hand_marker=True, amplitude_mm=80.0, drift_mm=10.0), seed=2
    )
    pts = truth.positions_mm.reshape(-1, 3)
    for cam in RIG.cameras:
        assert cam.in_image(cam.project(pts), margin_px=30).all()
        # The index marker is above the thumb marker in the image (y is down).
        px = cam.project(truth.positions_mm[:, :2].reshape(-1, 3)).reshape(-1, 2, 2)
        assert np.all(px[:, 1, 1] < px[:, 0, 1])


@pytest.mark.parametrize("sigma", [3.0, 0.0])
def test_a_frame_made_in_one_pass_is_the_float_canvas_s_bytes(sigma):
    """``SensorNoise.frame_u8`` (the whole frame converted in one pass, only the objects'
    boxes through the float canvas) gives exactly the bytes of the float path: noisy
    background, patches added in order, then ``to_uint8``. The objects overlap one another
    and the image border, sit on the background's extremes (clipped at 0 and 255) and on
    exact halves."""
    size = ImageSize(320, 256)
    bg = make_background(size, rng=np.random.default_rng(1))
    bg[:40, :40] = -30.0  # below black
    bg[-40:, -40:] = 300.0  # above white
    bg[100:110, 100:200] = np.float32(37.5)  # a half: rounds to even
    cam = default_rig(image_size=size).left
    centres = [[0.0, 0.0, 500.0], [2.0, 1.0, 500.0], [-60.0, -50.0, 480.0], [70.0, 55.0, 520.0]]
    rng = np.random.default_rng(7)
    layer = SphereLayer(np.array(centres)[None], 5.0, np.array([230.0, 180.0, 90.0, 250.0]))
    patches = sphere_patches(size, cam, layer, shot_noise=(rng, 0.025))
    patches += sphere_patches(size, cam, SphereLayer(np.array(centres[:2])[None], 3.0, 60.0, GLINT))
    assert len(patches) == 6
    old = SensorNoise(size, sigma=sigma, rng=np.random.default_rng(3))
    new = SensorNoise(size, sigma=sigma, rng=np.random.default_rng(3))
    for _ in range(3):  # consecutive frames take the same noise windows
        canvas = old.noisy(bg)
        add_patches(canvas, patches)
        assert np.array_equal(new.frame_u8(bg, patches), to_uint8(canvas))
    assert np.array_equal(new.frame_u8(bg, []), to_uint8(old.noisy(bg)))

"""The IR-lit hand of the simulator: skin image, depth order, marker visibility, postures."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from core.camera import ImageSize
from core.simulation.hand import (
    MARKER_BASE_MM,
    NAIL_FINGER_RADIUS_MM,
    Capsules,
    SkinLook,
    closed_marker_separation_mm,
    composite_spheres,
    draw_skin,
    nail_glints,
    overlap_orientation_deg,
    tapping_hand,
)
from core.simulation.kinematics import TappingScenario, simulate_tapping
from core.simulation.render import DISC, SphereLayer, intensity_centroid
from core.simulation.rig import default_rig
from core.simulation.session import ImagingScenario, simulate_session

RIG = default_rig()  # 1280 x 1024
CAM = RIG.left
F_PX = CAM.K[0, 0]


def _canvas(level: float = 0.0) -> np.ndarray:
    return np.full((1024, 1280), level, np.float32)


def _px(point_mm) -> tuple[int, int]:
    p = CAM.project(np.asarray(point_mm, dtype=float)[None])[0]
    return int(np.rint(p[0])), int(np.rint(p[1]))


def _bar(z_mm: float, radius_mm: float = 8.0, y_mm: float = 0.0) -> Capsules:
    """A horizontal capsule facing the left camera, 100 mm long."""
    return Capsules([[-50.0, y_mm, z_mm]], [[50.0, y_mm, z_mm]], [radius_mm], [radius_mm])


def test_capsules_check_their_shapes():
    with pytest.raises(ValueError, match="differ in shape"):
        Capsules(np.zeros((2, 3)), np.zeros((1, 3)), 1.0, 1.0)
    with pytest.raises(ValueError, match="positive"):
        Capsules(np.zeros((1, 3)), np.ones((1, 3)), 0.0, 1.0)
    with pytest.raises(ValueError, match="skin level"):
        SkinLook(level=300.0)


def test_skin_shading_width_and_edges():
    look = SkinLook(level=60.0, wrap=0.25, blur_px=0.0)
    canvas = _canvas(10.0)
    skin = draw_skin(canvas, CAM, _bar(500.0), look)
    assert skin is not None
    x, y = _px([0.0, 0.0, 500.0])
    # facing the camera at the front surface (492 mm): inverse square from 500 mm
    assert canvas[y, x] == pytest.approx(60.0 * (500.0 / 492.0) ** 2, rel=0.01)
    # perspective width: 8 mm at 500 mm is 20 px of radius
    half_px = F_PX * 8.0 / 500.0
    assert canvas[y + int(half_px) - 2, x] > 20.0  # inside, darker towards the edge
    assert canvas[y + int(half_px) - 2, x] < canvas[y, x]
    assert canvas[y + int(half_px) + 2, x] == pytest.approx(10.0)  # the background is left alone
    # the edge keeps wrap / (1 + wrap) of the brightness (scattered light), not black
    rim = canvas[y + int(half_px) - 1, x]
    assert 0.15 * 60 < rim < 0.6 * 60
    assert skin.depth_mm[y - skin.y0, x - skin.x0] == pytest.approx(492.0, abs=0.2)


def test_nearer_skin_wins_whatever_the_drawing_order():
    look = SkinLook(level=60.0, blur_px=0.0)
    near = Capsules([[0.0, -50.0, 450.0]], [[0.0, 50.0, 450.0]], [6.0], [6.0])  # vertical
    far = _bar(550.0)
    both = [
        Capsules(
            np.vstack([a.starts_mm, b.starts_mm]),
            np.vstack([a.ends_mm, b.ends_mm]),
            np.concatenate([a.start_radius_mm, b.start_radius_mm]),
            np.concatenate([a.end_radius_mm, b.end_radius_mm]),
        )
        for a, b in ((near, far), (far, near))
    ]
    images = []
    for caps in both:
        canvas = _canvas()
        draw_skin(canvas, CAM, caps, look)
        images.append(canvas)
    np.testing.assert_allclose(images[0], images[1], atol=1e-3)
    x, y = _px([0.0, 0.0, 450.0])
    assert images[0][y, x] == pytest.approx(60.0 * (500.0 / 444.0) ** 2, rel=0.01)


def _marker(centre_mm, peak: float = 230.0) -> SphereLayer:
    return SphereLayer(np.asarray(centre_mm, dtype=float)[None, None], 2.5, peak, DISC)


def test_marker_replaces_the_skin_behind_it_and_keeps_its_centre():
    look = SkinLook(level=60.0, blur_px=0.7)
    canvas = _canvas()
    skin = draw_skin(canvas, CAM, _bar(520.0, radius_mm=15.0), look)
    before = canvas.copy()
    centre = [1.3, 0.7, 500.0]
    vis = composite_spheres(canvas, CAM, _marker(centre), skin, psf_sigma_px=0.5)
    assert vis[0] == pytest.approx(1.0)
    x, y = _px(centre)
    assert canvas[y, x] == pytest.approx(230.0, abs=1.0)  # opaque: not 230 + skin
    diff = canvas - before
    patch = diff[y - 12 : y + 13, x - 12 : x + 13]
    c = intensity_centroid(patch, x0=x - 12, y0=y - 12)
    np.testing.assert_allclose(c, CAM.project(np.array([centre]))[0], atol=0.01)  # px


def test_skin_in_front_hides_a_marker_and_visibility_is_the_hidden_share():
    look = SkinLook(level=60.0, blur_px=0.0)
    centre = np.array([0.0, 0.0, 500.0])
    # a wide finger in front of the lower half of the marker (its upper edge at y = 0)
    finger = _bar(460.0, radius_mm=10.0, y_mm=10.0)
    canvas = _canvas()
    skin = draw_skin(canvas, CAM, finger, look)
    vis = composite_spheres(canvas, CAM, _marker(centre), skin)
    assert vis[0] == pytest.approx(0.5, abs=0.04)
    x, y = _px(centre)
    assert canvas[y - 3, x] > 200  # the upper half is seen
    assert canvas[y + 3, x] < 100  # the lower half is skin
    # fully behind it
    canvas = _canvas()
    skin = draw_skin(canvas, CAM, _bar(460.0, radius_mm=10.0), look)
    vis = composite_spheres(canvas, CAM, _marker(centre), skin)
    assert vis[0] == pytest.approx(0.0, abs=1e-3)
    assert canvas[y, x] < 100


def test_nearer_marker_hides_the_farther_one():
    r_px = F_PX * 2.5 / 500.0  # both ~6.25 px in radius
    near = np.array([0.0, 0.0, 500.0])
    far = np.array([4.0 * 520.0 / 500.0, 0.0, 520.0])  # projects 4 mm (10 px) to the side
    layer = SphereLayer(np.stack([far, near])[None], 2.5, 230.0, DISC)
    vis = composite_spheres(_canvas(), CAM, layer, None)
    assert vis[1] == pytest.approx(1.0)
    # lens area of two discs: radii ~6.25 (near) and ~6.0 (far), 10 px apart
    r1, r2 = r_px, F_PX * 2.5 / 520.0
    d = 10.0
    a = (
        r1**2 * np.arccos((d * d + r1 * r1 - r2 * r2) / (2 * d * r1))
        + r2**2 * np.arccos((d * d + r2 * r2 - r1 * r1) / (2 * d * r2))
        - 0.5 * np.sqrt((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2))
    )
    assert vis[0] == pytest.approx(1.0 - a / (np.pi * r2 * r2), abs=0.03)


def test_tapping_hand_puts_the_markers_on_the_nails():
    tap = TappingScenario(duration_s=2.0)
    truth = simulate_tapping(tap, seed=4)
    for t in (0.2, 0.7, 1.1):
        caps = tapping_hand(truth.model, t, marker_radius_mm=2.5)
        markers = truth.model.positions_mm(np.array([t]))[0]
        lift = NAIL_FINGER_RADIUS_MM + MARKER_BASE_MM + 2.5
        for k, m in ((0, markers[1]), (1, markers[0])):  # capsule 0: index, 1: thumb
            a, b = caps.starts_mm[k], caps.ends_mm[k]
            u = (b - a) / np.linalg.norm(b - a)
            dist = np.linalg.norm((m - a) - ((m - a) @ u) * u)
            assert dist == pytest.approx(lift, abs=0.8)  # mm: the marker sits on the nail


def test_turns_are_rigid_and_come_back():
    base = TappingScenario(duration_s=3.0)
    turned = dataclasses.replace(base, turns=((0.5, 1.5, 60.0),))
    a = simulate_tapping(base, seed=2)
    b = simulate_tapping(turned, seed=2)
    np.testing.assert_allclose(b.aperture_mm, a.aperture_mm, atol=1e-9)  # rigid
    assert b.model.roll_deg(np.array([1.0]))[0] == pytest.approx(60.0)
    np.testing.assert_allclose(b.positions_mm[:50], a.positions_mm[:50], atol=1e-9)  # before
    np.testing.assert_allclose(b.positions_mm[200:], a.positions_mm[200:], atol=1e-9)  # after
    assert np.max(np.linalg.norm(b.positions_mm[100] - a.positions_mm[100], axis=1)) > 5.0


@pytest.mark.parametrize("camera", ["left", "right"])
def test_overlap_orientation_makes_the_closed_markers_overlap(camera):
    tap = TappingScenario(duration_s=2.0)
    cam = RIG.left if camera == "left" else RIG.right
    other = RIG.right if camera == "left" else RIG.left
    orientation = overlap_orientation_deg(tap, cam, separation_mm=3.0)
    turned = dataclasses.replace(tap, orientation_deg=orientation)
    sep, index_front = closed_marker_separation_mm(turned, cam)
    assert sep == pytest.approx(3.0, abs=0.05)  # mm: overlapping (diameter 5)
    assert index_front
    assert closed_marker_separation_mm(turned, other)[0] > 5.0  # the other camera: apart
    # and as the fingers open, they part in the overlapping view too
    truth = simulate_tapping(turned, seed=0)
    k = truth.taps[0]
    peak = round(k.t_max_aperture_s * truth.fps)
    px = cam.project(truth.positions_mm[peak, :2])
    assert np.linalg.norm(px[1] - px[0]) > 2 * F_PX * 5.0 / 500.0


def test_nail_glints_sit_beside_the_markers():
    truth = simulate_tapping(TappingScenario(duration_s=1.0), seed=1)
    layer = nail_glints(truth.model, CAM, 0.2, marker_radius_mm=2.5, peak=150.0)
    markers = truth.model.positions_mm(np.array([0.2]))[0]
    centres = layer.centres_mm[0]
    for k, m in ((0, markers[0]), (2, markers[1])):  # two glints per nail: thumb, index
        d = np.linalg.norm(centres[k : k + 2] - m, axis=1)
        assert np.all((d > 2.5) & (d < 8.0))  # mm: beside the marker, on its nail
    assert np.max(layer.peak) > 0


def test_session_with_hand_records_visibility(tmp_path):
    tap = TappingScenario(duration_s=0.6, turns=((0.0, 0.6, 90.0),))
    imaging = ImagingScenario(image_size=ImageSize(320, 256), skin_level=57.0, nail_glint_peak=120)
    session = simulate_session(tmp_path, seed=3, tapping=tap, imaging=imaging)
    vis = {c: np.array(session.truth["visibility"][c]) for c in ("left", "right")}
    assert vis["left"].shape == (60, 2)
    assert np.all((vis["left"] >= 0) & (vis["left"] <= 1))
    assert np.min(vis["left"][:, 0]) < 0.5  # the thumb is hidden as the hand rolls over
    assert np.max(vis["left"][:5]) == pytest.approx(1.0, abs=1e-3)  # not before
    doc = json.loads(session.truth_path.read_text())
    assert doc["scenario"]["turns"] == [[0.0, 0.6, 90.0]]
    assert doc["imaging"]["nail_glint_peak"] == 120

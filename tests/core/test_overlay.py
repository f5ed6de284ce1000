"""The review overlay (core.overlay): tracked markers projected into each video, detections."""

from __future__ import annotations

import numpy as np
import pytest
from rigs import verging_rig

from core.camera import ImageSize
from core.overlay import camera_overlay, overlay_document, positions_at, swap_overlay_labels
from core.pipeline import analyze_recording
from core.simulation.kinematics import TappingScenario
from core.simulation.session import ImagingScenario


def test_positions_at_interpolates_and_leaves_the_outside_unknown():
    pos = np.arange(4 * 1 * 3, dtype=float).reshape(4, 1, 3)
    pos[2, 0, 1] = np.nan
    out = positions_at(pos, np.array([0.0, 0.5, 3.0, -0.1, 3.1, 1.5, np.nan]))
    np.testing.assert_allclose(out[0, 0], pos[0, 0])
    np.testing.assert_allclose(out[1, 0], 0.5 * (pos[0, 0] + pos[1, 0]))  # exact midpoint
    np.testing.assert_allclose(out[2, 0], pos[3, 0])
    assert np.isnan(out[3]).all() and np.isnan(out[4]).all() and np.isnan(out[6]).all()
    assert np.isnan(out[5, 0, 1]) and np.isfinite(out[5, 0, 0])  # NaN neighbour stays NaN
    with pytest.raises(ValueError, match=r"\(T, M, 3\)"):
        positions_at(np.zeros((4, 3)), np.zeros(2))


def test_tracks_are_the_rig_projection_at_each_frames_left_instant():
    rig = verging_rig()
    rng = np.random.default_rng(0)
    pos = rng.uniform([-40, -40, 550], [40, 40, 650], size=(20, 2, 3))
    k = 3  # right frame j shows left frame j + 3
    dets = [np.zeros((0, 2))] * 15
    right = camera_overlay(
        rig.right, pos, ("thumb", "index"), dets, fps=100.0, left_frame=np.arange(15.0) + k
    )
    expected = rig.right.project(pos[k : k + 15].reshape(-1, 3)).reshape(15, 2, 2)
    np.testing.assert_allclose(right.tracks_px, expected, atol=1e-9)  # px
    left = camera_overlay(rig.left, pos, ("thumb", "index"), [np.zeros((0, 2))] * 20, fps=100.0)
    np.testing.assert_allclose(
        left.tracks_px, rig.left.project(pos.reshape(-1, 3)).reshape(20, 2, 2), atol=1e-9
    )
    doc = overlay_document([left, right], fps=100.0)
    assert doc["format"] == "bradyscope.overlay/1"
    assert [c["camera"] for c in doc["cameras"]] == ["left", "right"]
    assert doc["cameras"][1]["left_frame"][:2] == [3.0, 4.0]
    assert doc["cameras"][1]["tracks"]["thumb"][0] == pytest.approx(expected[0, 0], abs=1e-3)
    swapped = swap_overlay_labels(doc)
    assert swapped["cameras"][1]["tracks"]["index"] == doc["cameras"][1]["tracks"]["thumb"]
    with pytest.raises(ValueError, match="left_frame"):
        camera_overlay(rig.left, pos, ("thumb", "index"), dets, fps=100.0, left_frame=np.zeros(3))


@pytest.mark.parametrize("offset", [0, 4])
def test_overlay_of_an_analysis_lies_on_the_detections(simulated_session, offset):
    """Tracked markers drawn where the detector found them (within 0.2 px) in both videos,
    also when the right camera started late (the convention: right j = left j + K)."""
    session = simulated_session(
        seed=5,
        tapping=TappingScenario(duration_s=1.5, fps=100.0),
        imaging=ImagingScenario(image_size=ImageSize(640, 512), offset_frames=float(offset)),
    )
    from core.camera import read_rig

    rig = read_rig(session.rig_path)
    analysis = analyze_recording(rig, session.left_video, session.right_video, offset_frames=offset)
    for cam in analysis.overlays(rig):
        errors = []
        for f, dets in enumerate(cam.detections_px):
            for m in range(len(cam.labels)):
                p = cam.tracks_px[f, m]
                if np.isfinite(p).all() and len(dets):
                    errors.append(np.min(np.linalg.norm(dets - p, axis=1)))
        assert len(errors) > 0.8 * 2 * len(cam.detections_px), cam.camera
        assert np.percentile(errors, 99) < 0.2, cam.camera  # px
        if cam.camera == "right":
            np.testing.assert_allclose(cam.left_frame[:3], np.arange(3) + offset)

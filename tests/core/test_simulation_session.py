"""Simulated sessions: files, video properties, determinism, the offset convention, the CLI."""

from __future__ import annotations

import hashlib
import json

import cv2
import numpy as np
import pytest

from app.cli import main as cli_main
from core.camera import ImageSize, read_rig
from core.errors import InputError
from core.simulation.kinematics import TappingScenario
from core.simulation.render import intensity_centroid
from core.simulation.rig import default_rig
from core.simulation.session import ImagingScenario, read_truth, simulate_session

SIZE = ImageSize(640, 512)  # small but markers are still ~6 px wide (f = 625 px)
TAPPING = TappingScenario(duration_s=0.8, fps=100.0, hesitations=(), drift_mm=3.0)


def _read_all(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame)
    cap.release()
    return frames


def _digest(frames):
    h = hashlib.sha256()
    for f in frames:
        h.update(f.tobytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    imaging = ImagingScenario(
        image_size=SIZE,
        distractors_static=2,
        distractors_moving=1,
        occlusions=(("left", "index", 0.3, 0.2),),
        offset_frames=1.5,
    )
    out = tmp_path_factory.mktemp("sim")
    calls = []
    result = simulate_session(
        out, seed=11, tapping=TAPPING, imaging=imaging, progress=lambda *a: calls.append(a)
    )
    return result, calls


def test_files_and_video_properties(session):
    result, calls = session
    for p in (result.left_video, result.right_video, result.rig_path, result.truth_path):
        assert p.is_file()
    assert result.left_video.name == "left.mkv" and result.right_video.name == "right.mkv"
    for path in (result.left_video, result.right_video):
        cap = cv2.VideoCapture(str(path))
        assert cap.isOpened()
        assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(100.0)
        assert round(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 80  # what the container states
        assert int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)) == 640
        assert int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)) == 512
        cap.release()
        assert len(_read_all(path)) == 80
    assert calls[-1] == ("simulation", 80, 80)
    rig = read_rig(result.rig_path)
    np.testing.assert_allclose(rig.right.K, default_rig(image_size=SIZE).right.K)


def test_truth_document(session):
    result, _ = session
    doc = read_truth(result.truth_path)
    assert doc == result.truth
    assert doc["format"] == "bradyscope.truth/1"
    assert doc["fps"] == 100.0 and doc["frame_count"] == 80
    assert doc["offset_frames"] == 1.5
    assert doc["marker_names"] == ["thumb", "index"]
    pos = np.array(doc["positions_mm"])
    assert pos.shape == (80, 2, 3)
    d = np.linalg.norm(pos[:, 1] - pos[:, 0], axis=1)
    for tap in doc["taps"]:
        seg = d[tap["frame_start"] : tap["frame_end"] + 1]
        assert seg.max() - seg[0] == pytest.approx(tap["amplitude_mm"], abs=1e-6)  # mm
    for key in ("frequency_hz", "decrement_mm_per_tap", "hesitations", "halts", "taps"):
        assert key in doc
    (occ,) = doc["occlusions"]
    assert occ["camera"] == "left" and occ["marker"] == "index"
    assert occ["frames"] == [[30, 49]]  # left frames exposed at 0.30 <= t < 0.50 s
    assert len(doc["distractors"]["static"]) == 2
    assert np.array(doc["distractors"]["moving"][0]["positions_mm"]).shape == (80, 3)


def test_occlusion_hides_the_marker(session):
    result, _ = session
    doc = result.truth
    frames = _read_all(result.left_video)
    rig = read_rig(result.rig_path)
    pos = np.array(doc["positions_mm"])
    for j, expect_visible in ((40, False), (10, True), (70, True)):
        px = rig.left.project(pos[j, 1:2])[0]
        x, y = int(np.rint(px[0])), int(np.rint(px[1]))
        peak = frames[j][y - 2 : y + 3, x - 2 : x + 3].max()
        assert (peak > 120) == expect_visible, (j, peak)


def test_deterministic_for_a_seed(tmp_path):
    tapping = TappingScenario(duration_s=0.3)
    imaging = ImagingScenario(
        image_size=ImageSize(320, 256),
        distractors_static=2,
        distractors_moving=1,
        occlusions=(("right", "thumb", 0.1, 0.1),),
        offset_frames=1.5,
        skin_level=25.0,
    )
    a = simulate_session(tmp_path / "a", seed=11, tapping=tapping, imaging=imaging)
    b = simulate_session(tmp_path / "b", seed=11, tapping=tapping, imaging=imaging)
    assert a.truth_path.read_bytes() == b.truth_path.read_bytes()
    assert a.rig_path.read_bytes() == b.rig_path.read_bytes()
    for x, y in ((a.left_video, b.left_video), (a.right_video, b.right_video)):
        assert _digest(_read_all(x)) == _digest(_read_all(y))


def test_other_seed_differs(tmp_path):
    short = TappingScenario(duration_s=0.2)
    small = ImagingScenario(image_size=ImageSize(160, 128))
    a = simulate_session(tmp_path / "a", seed=1, tapping=short, imaging=small)
    b = simulate_session(tmp_path / "b", seed=2, tapping=short, imaging=small)
    assert a.truth["positions_mm"] != b.truth["positions_mm"]
    assert _digest(_read_all(a.left_video)) != _digest(_read_all(b.left_video))


@pytest.mark.parametrize("offset", [4, -3])
def test_offset_convention(tmp_path, offset):
    """Right frame j shows the instant of left frame j + K (INTERFACES.md).

    Clean images (no noise, no background, no blur) so the marker centroid is
    the projection of the true centre; the index moves several px per frame,
    so the opposite sign convention misses by far more than the tolerance.
    """
    tapping = TappingScenario(duration_s=1.5, rhythm_jitter=0.0, drift_mm=0.0)
    imaging = ImagingScenario(
        image_size=SIZE,
        noise_sigma=0.0,
        exposure_s=0.0,
        background_level=0.0,
        background_texture=0.0,
        offset_frames=float(offset),
    )
    result = simulate_session(tmp_path, seed=3, tapping=tapping, imaging=imaging)
    rig = read_rig(result.rig_path)
    pos = np.array(result.truth["positions_mm"])
    right = _read_all(result.right_video)
    left = _read_all(result.left_video)
    checked = 0
    for j in range(40, 130):
        if not (0 <= j + offset < 150 and 0 <= j - offset < 150):
            continue
        expected = rig.right.project(pos[j + offset, 1:2])[0]
        wrong = rig.right.project(pos[j - offset, 1:2])[0]
        if np.linalg.norm(expected - wrong) < 3.0:  # px: the finger is (nearly) still
            continue
        found = _centroid(right[j], expected)
        assert np.linalg.norm(found - expected) < 0.05, (j, found, expected)  # px
        checked += 1
        # And the left video is unshifted.
        assert (
            np.linalg.norm(
                _centroid(left[j], rig.left.project(pos[j, 1:2])[0])
                - rig.left.project(pos[j, 1:2])[0]
            )
            < 0.05
        )  # px
    assert checked >= 20


def _centroid(image, px, half=7):
    x0, y0 = int(np.rint(px[0])) - half, int(np.rint(px[1])) - half
    window = image[y0 : y0 + 2 * half + 1, x0 : x0 + 2 * half + 1].astype(np.float64)
    return intensity_centroid(window, x0=x0, y0=y0)


def test_fractional_offset_interpolates_in_time(tmp_path):
    tapping = TappingScenario(duration_s=0.5, rhythm_jitter=0.0, drift_mm=0.0)
    imaging = ImagingScenario(
        image_size=SIZE,
        noise_sigma=0.0,
        exposure_s=0.0,
        background_level=0.0,
        background_texture=0.0,
        offset_frames=0.5,
    )
    result = simulate_session(tmp_path, seed=3, tapping=tapping, imaging=imaging)
    from core.simulation.kinematics import simulate_tapping

    model = simulate_tapping(tapping, seed=3).model
    rig = read_rig(result.rig_path)
    right = _read_all(result.right_video)
    for j in (20, 25, 30):
        expected = rig.right.project(model.positions_mm([(j + 0.5) / 100.0])[0, 1:2])[0]
        assert np.linalg.norm(_centroid(right[j], expected) - expected) < 0.05  # px


def test_mp4v_codec(tmp_path):
    result = simulate_session(
        tmp_path,
        seed=1,
        tapping=TappingScenario(duration_s=0.2),
        imaging=ImagingScenario(image_size=ImageSize(160, 128), codec="mp4v"),
    )
    assert result.left_video.suffix == ".mp4"
    assert result.truth["imaging"]["codec"] == "mp4v"
    assert len(_read_all(result.left_video)) == 20 == len(_read_all(result.right_video))


def test_invalid_inputs(tmp_path):
    with pytest.raises(ValueError, match="occlusion marker"):
        simulate_session(
            tmp_path,
            seed=1,
            tapping=TappingScenario(duration_s=0.1),
            imaging=ImagingScenario(image_size=SIZE, occlusions=(("left", "hand", 0.0, 0.1),)),
        )
    with pytest.raises(ValueError, match="image_size"):
        simulate_session(
            tmp_path,
            seed=1,
            tapping=TappingScenario(duration_s=0.1),
            imaging=ImagingScenario(image_size=SIZE),
            rig=default_rig(),
        )
    with pytest.raises(ValueError):
        ImagingScenario(occlusions=(("middle", "index", 0.0, 0.1),))
    with pytest.raises(ValueError):
        ImagingScenario(codec="h265")


def test_cli_end_to_end(tmp_path, capsys):
    out = tmp_path / "cli"
    status = cli_main(
        [
            "simulate",
            "-o",
            str(out),
            "--seed",
            "5",
            "--duration",
            "0.3",
            "--size",
            "320x256",
            "--offset-frames",
            "2",
            "--hand-marker",
            "--distractors-static",
            "1",
            "--occlusion",
            "right:thumb:0.1:0.1",
            "--noise",
            "1.5",
            "--skin",
            "20",
            "--nail-glints",
            "90",
            "--turn",
            "0.0:0.3:40",
            "--overlap",
            "right:2.5",
        ]
    )
    assert status == 0
    assert "30 frames at 100 fps" in capsys.readouterr().out
    doc = json.loads((out / "truth.json").read_text())
    assert doc["frame_count"] == 30 and doc["offset_frames"] == 2.0
    assert doc["marker_names"] == ["thumb", "index", "hand"]
    assert doc["imaging"]["image_size"] == [320, 256]
    assert doc["imaging"]["skin_level"] == 20.0
    assert doc["imaging"]["nail_glint_peak"] == 90.0
    assert doc["scenario"]["turns"] == [[0.0, 0.3, 40.0]]
    assert np.linalg.norm(doc["scenario"]["orientation_deg"]) > 20  # degrees: turned to overlap
    assert len(doc["visibility"]["right"]) == 30
    assert (out / "left.mkv").is_file() and (out / "right.mkv").is_file()
    assert (out / "rig.json").is_file()


def test_cli_bad_input_is_one_sentence(tmp_path, capsys):
    status = cli_main(
        ["simulate", "-o", str(tmp_path), "--duration", "1", "--hesitation-taps", "50"]
    )
    assert status == 2
    err = capsys.readouterr().err
    assert "invalid scenario" in err and "Traceback" not in err
    status = cli_main(["simulate", "-o", str(tmp_path), "--occlusion", "left:pinky:0:1"])
    assert status == 2
    status = cli_main(["simulate", "-o", str(tmp_path), "--overlap", "right:30"])
    assert status == 2
    assert "invalid scenario" in capsys.readouterr().err
    # a lost frame past the video's end: said before anything is rendered, no traceback
    status = cli_main(["simulate", "-o", str(tmp_path / "d"), "--drop", "left:99999"])
    assert status == 2
    err = capsys.readouterr().err
    assert "invalid scenario" in err and "99999" in err and "Traceback" not in err
    assert not (tmp_path / "d").exists()
    a_file = tmp_path / "not-a-folder"
    a_file.write_text("x")
    status = cli_main(["simulate", "-o", str(a_file), "--duration", "0.1"])
    assert status == 2
    assert "cannot create the output folder" in capsys.readouterr().err


def test_cli_boards_writes_calibration_recordings_of_the_same_rig(tmp_path):
    out = tmp_path / "with-boards"
    status = cli_main(
        ["simulate", "-o", str(out), "--duration", "0.1", "--size", "160x128", "--boards"]
    )
    assert status == 0
    calib = out / "calibration"
    assert (calib / "rig_true.json").is_file()
    assert any(calib.glob("chessboard_left.*")) and any(calib.glob("charuco_right.*"))
    np.testing.assert_allclose(
        read_rig(calib / "rig_true.json").right.t_cam_from_world_mm,
        read_rig(out / "rig.json").right.t_cam_from_world_mm,
    )


def test_moving_distractors_are_no_ghosts_of_the_fingertips():
    """Glints move with the hand's drift and their own wobble, not with the tapping."""
    from core.simulation.kinematics import simulate_tapping
    from core.simulation.session import StereoRenderer

    truth = simulate_tapping(TappingScenario(duration_s=6.0), seed=4)
    renderer = StereoRenderer(
        truth, rig=default_rig(), imaging=ImagingScenario(distractors_moving=4), seed=4
    )
    doc = renderer.truth_document(video_names={"left": "l", "right": "r"})
    index_v = np.diff(truth.positions_mm[:, 1], axis=0)  # mm/frame
    for glint in doc["distractors"]["moving"]:
        pos = np.array(glint["positions_mm"])
        v = np.diff(pos, axis=0)
        for axis in range(3):
            corr = np.corrcoef(v[:, axis], index_v[:, axis])[0, 1]
            assert abs(corr) < 0.3, (axis, corr)
        # Slow and small next to the index (which moves ~50 mm at ~0.5 m/s).
        assert np.ptp(pos, axis=0).max() < 25.0  # mm
        assert np.linalg.norm(v, axis=1).max() * 100.0 < 60.0  # mm/s
        # Never on top of a fingertip marker.
        d = np.linalg.norm(truth.positions_mm[:, :2] - pos[:, None, :], axis=2)
        assert d.min() > 20.0  # mm


def test_read_truth_errors(tmp_path):
    with pytest.raises(InputError, match="cannot read"):
        read_truth(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="not a JSON truth file"):
        read_truth(bad)
    bad.write_text(json.dumps({"format": "bradyscope.rig/1"}))
    with pytest.raises(InputError, match=r"bradyscope\.truth/1"):
        read_truth(bad)

"""analyze_recording end to end on simulated recordings with exact ground truth (issue 4 acceptance).

Sessions are rendered once per test run (module scope) and shared:

- ``messy``: 1280x1024, 100 fps, 10 s, MPEG-4 (mp4v) compression, 6 ms
  motion blur, noise sigma 3, 3 static and 2 moving distractors, a third
  marker on the back of the hand (never thumb or index), a right
  frame offset of -7 frames (not given), the index hidden from the right
  camera for 0.08 s while it moves fast, and the thumb hidden from the left
  camera for 0.3 s (too long to fill).
- ``clean``: 1280x1024, 100 fps, lossless, default noise and blur, 2 s (the
  accuracy figure does not depend on the length; 10 s is the bench's job).
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core.camera import ImageSize, read_rig, write_rig
from core.errors import DetectionError, InputError
from core.pipeline import CSV_HEADER, Analysis, analyze_recording, write_analysis, write_markers_csv
from core.simulation.kinematics import TappingScenario
from core.simulation.session import ImagingScenario, SimulatedSession, simulate_session
from core.video import VideoWriter

FULL = ImageSize(1280, 1024)
MESSY_OFFSET = -7
FAST_OCCLUSION = (2.02, 0.08)  # (t_start_s, duration_s): index hidden from the right camera
LONG_OCCLUSION = (5.0, 0.3)  # thumb hidden from the left camera


def truth_positions(session: SimulatedSession) -> np.ndarray:
    return np.asarray(session.truth["positions_mm"], dtype=float)[:, :2]


def errors_mm(analysis: Analysis, session: SimulatedSession) -> np.ndarray:
    return np.linalg.norm(analysis.positions_mm - truth_positions(session), axis=2)


def aperture_error_mm(analysis: Analysis, session: SimulatedSession) -> np.ndarray:
    truth = truth_positions(session)
    ap = np.linalg.norm(analysis.positions_mm[:, 0] - analysis.positions_mm[:, 1], axis=1)
    ap_true = np.linalg.norm(truth[:, 0] - truth[:, 1], axis=1)
    return ap - ap_true


@pytest.fixture(scope="module")
def messy(run_once: Any) -> tuple[SimulatedSession, Analysis]:
    """Made once per test run, in whichever xdist worker asks first (``run_once``)."""
    return run_once("pipeline-messy", _messy)


def _messy(out: Path) -> tuple[SimulatedSession, Analysis]:
    session = simulate_session(
        out,
        seed=21,
        tapping=TappingScenario(
            duration_s=10.0, fps=100.0, frequency_hz=3.0, amplitude_mm=50.0, hand_marker=True
        ),
        imaging=ImagingScenario(
            image_size=FULL,
            codec="mp4v",
            exposure_s=0.006,
            noise_sigma=3.0,
            distractors_static=3,
            distractors_moving=2,
            offset_frames=MESSY_OFFSET,
            occlusions=(
                ("right", "index", *FAST_OCCLUSION),
                ("left", "thumb", *LONG_OCCLUSION),
            ),
        ),
    )
    stages: list[str] = []
    analysis = analyze_recording(
        read_rig(session.rig_path),
        session.left_video,
        session.right_video,
        progress=lambda stage, done, total: stages.append(stage),
    )
    assert {"detection", "synchronisation", "triangulation", "tracking"} <= set(stages)
    return session, analysis


@pytest.fixture(scope="module")
def clean(run_once: Any) -> tuple[SimulatedSession, Analysis]:
    """Made once per test run, in whichever xdist worker asks first (``run_once``)."""
    return run_once("pipeline-clean", _clean)


def _clean(out: Path) -> tuple[SimulatedSession, Analysis]:
    session = simulate_session(
        out,
        seed=5,
        tapping=TappingScenario(duration_s=2.0, fps=100.0, frequency_hz=3.5),
        imaging=ImagingScenario(image_size=FULL, codec="lossless"),
    )
    analysis = analyze_recording(
        read_rig(session.rig_path), session.left_video, session.right_video
    )
    return session, analysis


# --------------------------------------------------------------------------- clean


def test_clean_accuracy(clean: tuple[SimulatedSession, Analysis]) -> None:
    session, analysis = clean
    meas = analysis.status == "measured"
    assert np.mean(meas) >= 0.99
    err = errors_mm(analysis, session)[meas]
    assert np.sqrt(np.mean(err**2)) <= 0.03  # mm (acceptance, clean)
    ap = aperture_error_mm(analysis, session)
    both = np.all(meas, axis=1)
    assert np.sqrt(np.mean(ap[both] ** 2)) <= 0.05  # mm (acceptance: thumb-index distance)
    assert analysis.sync["offset_frames"] == 0.0 and analysis.sync["method"] == "auto"
    assert analysis.quality["reprojection_px_median"] < 0.1  # px


def test_clean_identities_and_shapes(clean: tuple[SimulatedSession, Analysis]) -> None:
    session, analysis = clean
    n = len(session.truth["positions_mm"])
    assert analysis.positions_mm.shape == (n, 2, 3)
    assert analysis.status.shape == analysis.reprojection_px.shape == (n, 2)
    assert analysis.marker_names == ("thumb", "index")
    np.testing.assert_array_equal(analysis.frame_numbers, np.arange(n))
    assert np.nanmax(errors_mm(analysis, session)) < 1.0  # mm: never the other finger


# --------------------------------------------------------------------------- messy


def test_messy_sync_found_exactly(messy: tuple[SimulatedSession, Analysis]) -> None:
    _, analysis = messy
    assert analysis.sync["offset_frames"] == float(MESSY_OFFSET)
    assert analysis.sync["method"] == "auto"
    assert analysis.sync["confidence"] > 0.5


def test_messy_accuracy_and_identities(messy: tuple[SimulatedSession, Analysis]) -> None:
    session, analysis = messy
    truth = truth_positions(session)
    n = truth.shape[0]
    meas = analysis.status == "measured"
    err = errors_mm(analysis, session)
    assert np.sqrt(np.mean(err[meas] ** 2)) <= 0.1  # mm (acceptance with blur/compression/noise)
    # Distractors never become thumb or index, identities never swap.
    assert np.nanmax(err) < 1.0  # mm
    ap = aperture_error_mm(analysis, session)
    both = np.all(meas, axis=1)
    assert np.sqrt(np.mean(ap[both] ** 2)) <= 0.1  # mm
    # Frames where both cameras see the marker: the right frame j = i - K exists
    # and no occlusion hides it.
    k = MESSY_OFFSET
    paired = (np.arange(n) - k >= 0) & (np.arange(n) - k < n)  # right frame i - K exists
    visible = np.repeat(paired[:, None], 2, axis=1)
    for occ in session.truth["occlusions"]:
        m = 0 if occ["marker"] == "thumb" else 1
        for first, last in occ["frames"]:
            if occ["camera"] == "right":  # right frame j pairs with left frame j + K
                first, last = first + k, last + k
            visible[max(first, 0) : last + 1, m] = False
    assert np.count_nonzero(meas & visible) >= 0.99 * np.count_nonzero(visible)


def test_messy_short_occlusion_interpolated(messy: tuple[SimulatedSession, Analysis]) -> None:
    session, analysis = messy
    occ = next(o for o in session.truth["occlusions"] if o["marker"] == "index")
    ((first, last),) = occ["frames"]
    left_frames = np.arange(first, last + 1) + MESSY_OFFSET  # right camera numbering -> left
    assert len(left_frames) <= 10
    assert np.all(analysis.status[left_frames, 1] == "interpolated")
    err = errors_mm(analysis, session)[left_frames, 1]
    assert np.max(err) <= 0.5  # mm (acceptance)


def test_messy_long_occlusion_missing(messy: tuple[SimulatedSession, Analysis]) -> None:
    session, analysis = messy
    occ = next(o for o in session.truth["occlusions"] if o["marker"] == "thumb")
    ((first, last),) = occ["frames"]
    inner = np.arange(first + 2, last - 1)
    assert np.all(analysis.status[inner, 0] == "missing")
    assert np.all(np.isnan(analysis.positions_mm[inner, 0]))


def test_outputs_follow_interfaces(
    messy: tuple[SimulatedSession, Analysis], tmp_path: Path
) -> None:
    session, analysis = messy
    write_analysis(analysis, tmp_path / "out")
    text = (tmp_path / "out" / "markers.csv").read_text(encoding="utf-8")
    rows = list(csv.reader(io.StringIO(text)))
    assert tuple(rows[0]) == CSV_HEADER
    n = analysis.positions_mm.shape[0]
    assert len(rows) == 1 + 2 * n
    assert rows[1][:3] == ["0", "0.0", "thumb"] and rows[2][:3] == ["0", "0.0", "index"]
    for row in rows[1:]:
        assert row[6] in ("measured", "interpolated", "missing")
        if row[6] == "missing":
            assert row[3:6] == ["", "", ""] and row[7] == ""
        else:
            assert all(v != "" for v in row[3:6])
        if row[6] == "measured":
            assert float(row[7]) >= 0
    frame, m = 123, 1
    row = rows[1 + 2 * frame + m]
    assert float(row[1]) == pytest.approx(frame / 100.0)
    np.testing.assert_allclose(
        [float(v) for v in row[3:6]], analysis.positions_mm[frame, m], atol=1e-4
    )
    doc = json.loads((tmp_path / "out" / "result.json").read_text(encoding="utf-8"))
    assert doc["format"] == "bradyscope.result/1"
    assert doc["fps"] == 100.0
    assert set(doc["sync"]) >= {"offset_frames", "method"}
    assert isinstance(doc["metrics"], dict) and isinstance(doc["taps"], list)
    q = doc["quality"]
    assert set(q) >= {
        "tracked_fraction",
        "interpolated_fraction",
        "reprojection_px_median",
        "warnings",
    }
    assert 0.9 < q["tracked_fraction"] <= 1.0 and 0 < q["interpolated_fraction"] < 0.05
    # The tapping metrics, end to end (core.metrics). The 0.3-s gap hides one
    # tap and the last 7 frames have no right frame, so up to 2 taps are lost;
    # every tap reported must be a true one.
    true_starts = np.array([t["t_start_s"] for t in session.truth["taps"]])
    assert len(true_starts) - 2 <= doc["metrics"]["tap_count"] <= len(true_starts)
    for tap in doc["taps"]:
        assert np.min(np.abs(true_starts - tap["t_start_s"])) < 0.05  # s
    assert doc["metrics"]["frequency_hz"] == pytest.approx(session.truth["frequency_hz"], rel=0.02)
    buf = io.StringIO()
    write_markers_csv(analysis, buf)
    assert buf.getvalue() == text


# --------------------------------------------------------------------------- errors


def _write_video(path: Path, *, fps: float, size: ImageSize, n: int, value: int = 10) -> Path:
    with VideoWriter(path, fps=fps, image_size=size, codec="mjpg") as w:
        for _ in range(n):
            w.write(np.full((size.height, size.width), value, np.uint8))
    return path


def test_bad_inputs_give_one_sentence(
    clean: tuple[SimulatedSession, Analysis], tmp_path: Path
) -> None:
    session, _ = clean
    rig = read_rig(session.rig_path)
    not_video = tmp_path / "notes.mp4"
    not_video.write_text("hello", encoding="utf-8")
    with pytest.raises(InputError, match=r"could not be opened|no frame"):
        analyze_recording(rig, not_video, session.right_video)
    with pytest.raises(InputError, match="does not exist"):
        analyze_recording(rig, tmp_path / "missing.mkv", session.right_video)
    small = ImageSize(160, 128)
    a = _write_video(tmp_path / "a.avi", fps=100.0, size=small, n=20)
    # Different frame rates are measured now (core.clock); a size the rig was not
    # calibrated at is still refused.
    with pytest.raises(InputError, match="calibrated at 1280x1024"):
        analyze_recording(rig, a, a)
    # A rig for the small size and a pair of black videos: no markers.
    from core.simulation.rig import default_rig

    small_rig = default_rig(image_size=small)
    write_rig(small_rig, tmp_path / "rig.json")
    with pytest.raises(DetectionError, match="markers were found in only 0 of 20 frames"):
        analyze_recording(read_rig(tmp_path / "rig.json"), a, a)


# --------------------------------------------------------------------------- calibrated rig


def test_end_to_end_with_a_calibrated_rig(
    clean: tuple[SimulatedSession, Analysis], tmp_path_factory: pytest.TempPathFactory
) -> None:
    """Rig from simulated chessboard recordings (not the true rig): aperture within 0.1 mm."""
    from core.calibration import calibrate_stereo_from_paths
    from core.simulation.boards import DEFAULT_CHESSBOARD, write_board_recordings

    session, _ = clean
    true_rig = read_rig(session.rig_path)
    out = tmp_path_factory.mktemp("boards")
    write_board_recordings(
        true_rig, out, seed=3, board="chessboard", duration_s=2.4, fps=10.0, pose_interval_s=0.1
    )
    rig = calibrate_stereo_from_paths(
        out / "chessboard_left.mkv", out / "chessboard_right.mkv", DEFAULT_CHESSBOARD
    ).rig
    assert not np.allclose(
        rig.right.t_cam_from_world_mm, true_rig.right.t_cam_from_world_mm, atol=1e-6
    )
    analysis = analyze_recording(rig, session.left_video, session.right_video)
    meas = np.all(analysis.status == "measured", axis=1)
    assert np.mean(meas) >= 0.99
    ap = aperture_error_mm(analysis, session)
    assert np.sqrt(np.mean(ap[meas] ** 2)) <= 0.1  # mm (acceptance, estimated rig)


def test_cameras_of_different_resolutions_end_to_end(tmp_path: Path) -> None:
    """Two different cameras (960x768 and 640x512): calibrated from board videos at their own
    sizes, then measured with that rig (issue 11): aperture within 0.1 mm."""
    from core.calibration import calibrate_stereo_from_paths
    from core.camera import StereoRig
    from core.simulation.boards import DEFAULT_CHESSBOARD, write_board_recordings
    from core.simulation.rig import default_rig
    from core.simulation.timing import CameraTiming

    left_size, right_size = ImageSize(960, 768), ImageSize(640, 512)
    true_rig = StereoRig(
        default_rig(image_size=left_size).left, default_rig(image_size=right_size).right
    )
    session = simulate_session(
        tmp_path / "session",
        seed=5,
        tapping=TappingScenario(duration_s=2.0, fps=100.0, frequency_hz=3.5),
        imaging=ImagingScenario(
            image_size=left_size,
            codec="lossless",
            right_timing=CameraTiming(image_size=right_size),
        ),
        rig=true_rig,
    )
    boards = tmp_path / "boards"
    write_board_recordings(
        true_rig,
        boards,
        seed=3,
        board="chessboard",
        duration_s=2.4,
        fps=10.0,
        pose_interval_s=0.1,
        supersample=2,
    )
    rig = calibrate_stereo_from_paths(
        boards / "chessboard_left.mkv", boards / "chessboard_right.mkv", DEFAULT_CHESSBOARD
    ).rig
    assert (rig.left.image_size, rig.right.image_size) == (left_size, right_size)
    analysis = analyze_recording(rig, session.left_video, session.right_video)
    meas = np.all(analysis.status == "measured", axis=1)
    assert np.mean(meas) >= 0.99
    ap = aperture_error_mm(analysis, session)
    assert np.sqrt(np.mean(ap[meas] ** 2)) <= 0.1  # mm (0.016 measured)


# --------------------------------------------------------------------------- sub-frame offset


def test_fractional_offset_is_found_and_used(tmp_path: Path) -> None:
    """Cameras not triggered together: a -3.5-frame offset, found and paired sub-frame."""
    session = simulate_session(
        tmp_path,
        seed=12,
        tapping=TappingScenario(duration_s=2.5, fps=100.0, frequency_hz=3.0),
        imaging=ImagingScenario(image_size=ImageSize(640, 512), offset_frames=-3.5),
    )
    analysis = analyze_recording(
        read_rig(session.rig_path), session.left_video, session.right_video
    )
    assert analysis.sync["offset_frames"] == pytest.approx(-3.5, abs=0.05)  # frames
    meas = analysis.status == "measured"
    assert np.mean(meas) > 0.95
    err = errors_mm(analysis, session)[meas]
    # 640x512 halves the resolution. Pairing whole frames instead (offset -4) measured
    # 63 % of the frames with 0.28 mm RMS and 1.3 mm worst error on such a recording.
    assert np.sqrt(np.mean(err**2)) <= 0.06  # mm


def test_a_hand_at_rest_at_the_start_does_not_make_the_offset_a_loss(tmp_path: Path) -> None:
    """A 2.5-frame offset with the fingers still for the first half second: the window at
    rest, whose cost is flat but for the left frames that have no right partner under
    some candidates, was taken for a sharp minimum; the offset came out as -0.1 frames
    with lost right frames and clock drift that were not there (on the reviewer's 4-s
    recording: -0.23 frames, three losses, -1106 ppm, 0.16 mm RMS and 1.2 mm worst)."""
    session = simulate_session(
        tmp_path,
        seed=8,
        tapping=TappingScenario(duration_s=2.5),
        imaging=ImagingScenario(image_size=ImageSize(640, 512), offset_frames=2.5),
    )
    analysis = analyze_recording(
        read_rig(session.rig_path), session.left_video, session.right_video
    )
    sync = analysis.sync
    assert sync["offset_subframe"] == pytest.approx(2.5, abs=0.02)  # frames
    assert sync["dropped_frames_left"] == [] and sync["dropped_frames_right"] == []
    assert abs(sync["drift_ppm"]) < 50  # ppm
    assert analysis.warnings == []
    meas = analysis.status == "measured"
    err = errors_mm(analysis, session)[meas]
    assert np.sqrt(np.mean(err**2)) <= 0.06  # mm


def test_subframe_refinement_survives_a_frame_without_detections() -> None:
    """core.sync.refine_offset (batched undistortion) on the pipeline's per-frame arrays."""
    import cv2

    from core.camera import Camera, StereoRig
    from core.pipeline import _undistort_all
    from core.simulation.kinematics import simulate_tapping
    from core.sync import estimate_offset, refine_offset

    size = FULL
    K = np.array([[1800.0, 0, 645.0], [0, 1795.0, 508.0], [0, 0, 1]])
    R = np.asarray(cv2.Rodrigues(np.array([0.01, -0.31, 0.005]))[0], dtype=np.float64)
    rig = StereoRig(
        Camera("left", size, K, np.array([-0.12, 0.08, 0.0005, -0.0003, -0.02])),
        Camera("right", size, K, np.array([-0.10, 0.05, -0.0004, 0.0002, 0.0]), R,
               -R @ np.array([160.0, 2.0, 0.0])),
    )  # fmt: skip
    truth = simulate_tapping(TappingScenario(duration_s=2.0, fps=100.0), seed=4)
    k_true = -1.3  # frames
    n = truth.positions_mm.shape[0]
    right_pos = truth.model.positions_mm((np.arange(n) + k_true) / truth.fps)
    rng = np.random.default_rng(2)
    left_px = [rig.left.project(p) + rng.normal(0, 0.1, (len(p), 2)) for p in truth.positions_mm]
    right_px = [rig.right.project(p) + rng.normal(0, 0.1, (len(p), 2)) for p in right_pos]
    right_px[10] = np.zeros((0, 2))  # a frame without detections
    left_norm, right_norm = _undistort_all(rig.left, left_px), _undistort_all(rig.right, right_px)
    est = estimate_offset(rig, left_norm, right_norm, max_offset_frames=10)
    ref = refine_offset(rig, left_norm, right_px, est, max_step_px=60.0)
    assert ref.offset_frames == round(k_true)
    assert abs(ref.offset_subframe - k_true) < 0.05  # frames


def test_fallback_searches_back_off_but_reacquire_within_one_frame() -> None:
    """A blob gone for a while: full searches on its first two missing frames, then on
    every other frame; when it comes back it is picked up at most one frame later."""
    from core.markers import UNPRODUCTIVE_FALLBACKS_BEFORE_BACKOFF, _CameraDetections

    fixed = np.array([[100.0, 100.0], [300.0, 200.0]])  # px, always visible
    extra = np.array([[600.0, 500.0]])  # px, hidden in frames 23..34
    hidden = range(23, 35)
    calls: list[tuple[int, bool]] = []

    def detect(image, search_xy_px, radius_px):
        frame = int(image[0, 0])
        calls.append((frame, search_xy_px is None))
        pts = fixed if frame in hidden else np.vstack([fixed, extra])
        if search_xy_px is not None:  # windowed: only blobs near a predicted position
            d = np.linalg.norm(pts[:, None] - search_xy_px[None], axis=2).min(axis=1)
            pts = pts[d <= radius_px]
        return pts, np.full(len(pts), 10.0), np.ones(len(pts))

    state = _CameraDetections(detect, full_every=10)
    for frame in range(50):
        state.process(np.full((4, 4), frame, np.uint8))
    full_frames = sorted({f for f, full in calls if full})
    fallbacks = [f for f in full_frames if f % 10 and f in hidden]
    k = UNPRODUCTIVE_FALLBACKS_BEFORE_BACKOFF
    assert fallbacks[:k] == [23, 24]  # at once while it may just have moved out of its window
    assert all(f % 2 == 0 for f in fallbacks[k:])  # then every other frame
    assert len(fallbacks) < len([f for f in hidden if f % 10])  # fewer than one per frame
    seen_again = min(f for f in range(35, 50) if len(state.frames[f]) == 3)
    assert seen_again <= 36  # back in frame 35: found at most one frame later
    assert all(len(state.frames[f]) == 3 for f in range(seen_again, 50))


@pytest.fixture(scope="module")
def small_session(tmp_path_factory: pytest.TempPathFactory) -> SimulatedSession:
    return simulate_session(
        tmp_path_factory.mktemp("small"),
        seed=8,
        tapping=TappingScenario(duration_s=1.0, fps=100.0),
        imaging=ImagingScenario(image_size=ImageSize(640, 512), codec="mp4v", distractors_static=1),
    )


def _live_detection_threads() -> list[str]:
    import threading

    return [t.name for t in threading.enumerate() if t.name.startswith(("detect-", "decode-"))]


# The cores the process may use: 2 (each camera's thread decodes its own frames, one
# decoder thread each) or 8 (a background reader per video, 4 decoder threads each).
CORES = pytest.mark.parametrize("cores", [2, 8])


def _with_cores(monkeypatch: pytest.MonkeyPatch, cores: int) -> None:
    import core.video

    monkeypatch.setattr(core.video.os, "sched_getaffinity", lambda _pid: set(range(cores)))
    assert core.video.decode_in_background(2) is (cores > 2)


@CORES
def test_concurrent_cameras_give_the_one_at_a_time_detections(
    small_session: SimulatedSession, monkeypatch: pytest.MonkeyPatch, cores: int
) -> None:
    """The two camera threads (compiled search without the GIL, at the same time)
    return exactly what searching one camera after the other returns, however the
    videos are decoded; the frame sinks get every decoded frame, in order."""
    from core.markers import _CameraDetections, _default_detector
    from core.pipeline import _detect_videos
    from core.video import iter_frames, probe_video

    _with_cores(monkeypatch, cores)
    info = [probe_video(small_session.left_video), probe_video(small_session.right_video)]
    paths = (info[0].path, info[1].path)
    counts = (info[0].frame_count, info[1].frame_count)
    stages: list[tuple[int, int]] = []
    sunk: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
    together = _detect_videos(
        paths,
        counts,
        None,
        lambda s, d, t: stages.append((d, t)),
        frame_sinks=(lambda f: sunk[0].append(f.copy()), lambda f: sunk[1].append(f.copy())),
    )
    for k in (0, 1):
        alone = _CameraDetections(_default_detector(None))
        frames = list(iter_frames(paths[k], gray=True))
        for image in frames:
            alone.process(image)
        assert len(together[k]) == len(alone.frames) == counts[k]
        assert all(np.array_equal(a, b) for a, b in zip(together[k], alone.frames, strict=True))
        assert sum(len(f) for f in alone.frames) >= 2 * counts[k]  # the markers were found
        assert len(sunk[k]) == len(frames)
        assert all(np.array_equal(a, b) for a, b in zip(sunk[k], frames, strict=True))
    assert stages[-1] == (sum(counts), sum(counts))  # progress reaches the end
    assert _live_detection_threads() == []


@CORES
def test_detection_error_stops_both_cameras(
    small_session: SimulatedSession, monkeypatch: pytest.MonkeyPatch, cores: int
) -> None:
    """A truncated video: one-sentence InputError, and no decoder or search thread left."""
    from core.pipeline import _detect_videos
    from core.video import probe_video

    _with_cores(monkeypatch, cores)

    info = [probe_video(small_session.left_video), probe_video(small_session.right_video)]
    paths = (info[0].path, info[1].path)
    too_many = (info[0].frame_count + 40, info[1].frame_count)  # the left one looks truncated
    with pytest.raises(InputError, match="truncated"):
        _detect_videos(paths, too_many, None, None)
    assert _live_detection_threads() == []


@CORES
def test_a_failing_frame_sink_stops_both_cameras(
    small_session: SimulatedSession, monkeypatch: pytest.MonkeyPatch, cores: int
) -> None:
    """A frame sink's exception (the caller's code) stops the analysis with that exception,
    and no decoder or search thread is left."""
    from core.pipeline import _detect_videos
    from core.video import probe_video

    _with_cores(monkeypatch, cores)
    info = [probe_video(small_session.left_video), probe_video(small_session.right_video)]
    seen: list[int] = []

    def sink(frame: np.ndarray) -> None:
        seen.append(1)
        if len(seen) == 5:
            raise RuntimeError("the sink's own failure")

    with pytest.raises(RuntimeError, match="the sink's own failure"):
        _detect_videos(
            (info[0].path, info[1].path),
            (info[0].frame_count, info[1].frame_count),
            None,
            None,
            frame_sinks=(None, sink),
        )
    assert len(seen) == 5
    assert _live_detection_threads() == []


def test_most_taps_not_measured_whole_is_said() -> None:
    """Taps with filled-in frames at their widest opening or a closure are left out of
    amplitude and speed; when most are, the metrics alone only showed missing values (a
    nail glint beside 6-px markers: 12 taps, none whole, no warning)."""
    from core.pipeline import _few_whole_taps
    from core.tasks import Task

    (said,) = _few_whole_taps({"tap_count": 12, "reliable_tap_count": 0}, Task.FINGER_TAPPING)
    assert said.startswith("only 0 of the 12 taps") and "could not be measured" in said
    (said,) = _few_whole_taps({"tap_count": 9, "reliable_tap_count": 4}, Task.TOE_TAPPING)
    assert said.startswith("only 4 of the 9 cycles") and "over those 4 only" in said
    assert _few_whole_taps({"tap_count": 12, "reliable_tap_count": 6}, Task.FINGER_TAPPING) == []
    assert _few_whole_taps({"tap_count": 2, "reliable_tap_count": 0}, Task.FINGER_TAPPING) == []

"""Stereo calibration: OpenCV's real stereo images, then simulated recordings of a known rig."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from core.boards import BoardSpec
from core.calibration import (
    MIN_VIEWS,
    StereoView,
    ViewCollection,
    calibrate_stereo,
    calibrate_stereo_from_paths,
    collect_views,
    edge_width_px,
    image_coverage,
    quality_verdict,
    select_views,
)
from core.camera import ImageSize, StereoRig, read_rig
from core.errors import CalibrationError, DetectionError, InputError
from core.simulation.boards import example_rig, write_board_recordings

# OpenCV's published left_intrinsics.yml (13 views, CALIB_FIX_ASPECT_RATIO).
OPENCV_LEFT_F_PX = 535.916
OPENCV_LEFT_CX_PX = 342.283
OPENCV_LEFT_CY_PX = 235.571

# Simulated recordings: a new board pose every frame, 24 pairs per board.
SIM_FPS = 10.0
SIM_DURATION_S = 2.4


def _rotation_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.rad2deg(np.arccos(np.clip(c, -1.0, 1.0))))


def _assert_rig_close(est: StereoRig, true: StereoRig) -> None:
    """The acceptance tolerances of issue 3."""
    for e, t in zip(est.cameras, true.cameras, strict=True):
        f_rel = np.array([e.K[0, 0] / t.K[0, 0], e.K[1, 1] / t.K[1, 1]]) - 1.0
        assert np.all(np.abs(f_rel) < 0.002), f"{e.name} focal error {100 * f_rel} %"  # 0.2 %
        pp = e.K[:2, 2] - t.K[:2, 2]
        assert np.all(np.abs(pp) < 1.0), f"{e.name} principal point error {pp} px"  # px
    assert abs(est.baseline_mm - true.baseline_mm) < 0.1  # mm
    assert _rotation_deg(est.R_right_from_left, true.R_right_from_left) < 0.05  # degrees
    # The direction of the baseline, too.
    te, tt = est.t_right_from_left_mm, true.t_right_from_left_mm
    cos = te @ tt / (np.linalg.norm(te) * np.linalg.norm(tt))
    assert np.rad2deg(np.arccos(min(cos, 1.0))) < 0.05  # degrees


# -- real images: OpenCV's stereo sample ------------------------------------------


@pytest.fixture(scope="module")
def opencv_folders(tmp_path_factory, shared_data_dir):
    # shared_data_dir skips outside CI when ../shared/data is absent, and fails in CI.
    data = shared_data_dir / "opencv-stereo"
    root = tmp_path_factory.mktemp("opencv-stereo")
    for side in ("left", "right"):
        (root / side).mkdir()
        for f in sorted(data.glob(f"{side}*.jpg")):
            (root / side / f.name).symlink_to(f)
    return root / "left", root / "right"


def test_opencv_stereo_sample(opencv_folders):
    left, right = opencv_folders
    board = BoardSpec("chessboard", cols=9, rows=6, square_mm=25.0)
    collection = collect_views(left, right, board)
    result = calibrate_stereo(collection, board)
    q = result.quality
    assert q["views_used"] == 13 and q["views_rejected"] == 0
    K = result.rig.left.K
    assert abs(K[0, 0] / OPENCV_LEFT_F_PX - 1) < 0.01  # 1 %
    assert abs(K[1, 1] / OPENCV_LEFT_F_PX - 1) < 0.01  # 1 %
    assert abs(K[0, 2] - OPENCV_LEFT_CX_PX) < 5.0  # px
    assert abs(K[1, 2] - OPENCV_LEFT_CY_PX) < 5.0  # px

    # Peers on the same detections: plain OpenCV (per-camera calibration, then
    # stereoCalibrate with the intrinsics fixed), and the stereo_calib sample's flags.
    obj = [v.left.object_points_mm.astype(np.float32) for v in collection.views]
    img_l = [v.left.corners_px.astype(np.float32) for v in collection.views]
    img_r = [v.right.corners_px.astype(np.float32) for v in collection.views]
    size = tuple(collection.image_size)
    _, K1, D1, _, _ = cv2.calibrateCamera(obj, img_l, size, None, None)
    _, K2, D2, _, _ = cv2.calibrateCamera(obj, img_r, size, None, None)
    rms_plain = cv2.stereoCalibrate(obj, img_l, img_r, K1, D1, K2, D2, size)[0]
    sample_flags = (
        cv2.CALIB_FIX_ASPECT_RATIO
        | cv2.CALIB_ZERO_TANGENT_DIST
        | cv2.CALIB_USE_INTRINSIC_GUESS
        | cv2.CALIB_SAME_FOCAL_LENGTH
        | cv2.CALIB_RATIONAL_MODEL
        | cv2.CALIB_FIX_K3
        | cv2.CALIB_FIX_K4
        | cv2.CALIB_FIX_K5
    )
    K0 = cv2.initCameraMatrix2D(obj, img_l, size, 0)
    rms_sample = cv2.stereoCalibrate(
        obj,
        img_l,
        img_r,
        K0.copy(),
        np.zeros(8),
        K0.copy(),
        np.zeros(8),
        size,
        flags=sample_flags,
        criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-5),
    )[0]
    assert q["rms_px"] <= rms_plain + 1e-4  # px
    assert q["rms_px"] <= rms_sample + 1e-4  # px
    # OpenCV's own left-only calibration reports 0.39 px; the stereo fit is in that range.
    assert q["epipolar_px_mean"] < 0.5  # px
    assert abs(q["square_error_mm_mean"]) < 0.05  # mm, on 25 mm squares


def test_opencv_stereo_sample_from_paths_with_progress(opencv_folders):
    left, right = opencv_folders
    calls = []
    result = calibrate_stereo_from_paths(
        left,
        right,
        BoardSpec("chessboard", cols=9, rows=6, square_mm=25.0),
        progress=lambda stage, done, total: calls.append((stage, done, total)),
    )
    assert ("detection", 13, 13) in calls and ("calibration", 4, 4) in calls
    assert result.rig.quality is not result.quality or result.rig.quality == result.quality
    json.dumps(result.rig.quality)  # JSON-serialisable
    assert result.rig.quality["rms_px"] == result.quality["rms_px"]


# -- simulated recordings of a known rig ------------------------------------------


@pytest.fixture(scope="module")
def sim_dir(run_once):
    """Made once per test run, in whichever xdist worker asks first (``run_once``)."""
    return run_once("calibration-boards", _write_boards)


def _write_boards(out):
    write_board_recordings(
        example_rig(),
        out,
        seed=1,
        board="both",
        duration_s=SIM_DURATION_S,
        fps=SIM_FPS,
        pose_interval_s=1.0 / SIM_FPS,
    )
    return out


@pytest.fixture(scope="module")
def sim(sim_dir, run_once):
    """Per board kind: (true rig, board, collection, result); once per test run."""
    return run_once("calibration-boards-calibrated", lambda _out: _calibrate_boards(sim_dir))


def _calibrate_boards(sim_dir):
    out = {}
    for kind in ("chessboard", "charuco"):
        board = BoardSpec.from_dict(json.loads((sim_dir / f"{kind}.json").read_text()))
        collection = collect_views(
            sim_dir / f"{kind}_left.mkv", sim_dir / f"{kind}_right.mkv", board
        )
        out[kind] = (
            read_rig(sim_dir / "rig_true.json"),
            board,
            collection,
            calibrate_stereo(collection, board),
        )
    return out


def test_recordings_written(sim_dir):
    names = sorted(p.name for p in sim_dir.iterdir())
    assert names == sorted(
        [
            "chessboard_left.mkv",
            "chessboard_right.mkv",
            "chessboard.json",
            "charuco_left.mkv",
            "charuco_right.mkv",
            "charuco.json",
            "rig_true.json",
        ]
    )
    true = read_rig(sim_dir / "rig_true.json")
    assert true.left.image_size == ImageSize(1280, 1024)
    assert 240 < true.baseline_mm < 260  # mm


@pytest.mark.parametrize("kind", ["chessboard", "charuco"])
def test_simulated_rig_is_recovered(sim, kind):
    true, _board, collection, result = sim[kind]
    assert collection.frames_tried == round(SIM_DURATION_S * SIM_FPS)
    _assert_rig_close(result.rig, true)
    q = result.quality
    assert q["rms_px"] < 0.1  # px: rendered corners are found to ~0.04 px
    assert q["epipolar_px_mean"] < 0.1  # px
    assert abs(q["square_error_mm_mean"]) < 0.01  # mm
    assert q["coverage_left"] > 0.5 and q["coverage_right"] > 0.5
    assert q["views_used"] >= 20
    assert quality_verdict(q)[0] == "good"
    # A lab rig: its frames are paired by number, and the offset measured is nil.
    assert q["sync"]["method"] == "synchronous"
    assert abs(q["sync"]["offset_frames"]) < 0.05  # frames


def test_swapping_the_cameras_gives_the_swapped_rig(sim):
    """Convention: feeding right as left must give the same rig seen from the other side."""
    true, board, collection, _ = sim["chessboard"]
    swapped = ViewCollection(
        [dataclasses.replace(v, left=v.right, right=v.left) for v in collection.views],
        collection.image_size,
        collection.frames_total,
        collection.source,
    )
    result = calibrate_stereo(swapped, board)
    _assert_rig_close(result.rig, true.swapped())
    # ...and is clearly not the unswapped rig.
    assert abs(result.rig.left.K[0, 2] - true.left.K[0, 2]) > 5.0  # px


def test_outlier_view_is_rejected(sim):
    true, board, collection, _ = sim["chessboard"]
    views = list(collection.views)
    k = next(i for i, v in enumerate(views) if v.both)
    bad = views[k].right
    rng = np.random.default_rng(0)
    corrupted = dataclasses.replace(
        bad, corners_px=bad.corners_px + rng.normal(0, 4.0, bad.corners_px.shape)
    )
    views[k] = dataclasses.replace(views[k], right=corrupted)
    result = calibrate_stereo(dataclasses.replace(collection, views=views), board)
    assert views[k].frame in result.quality["views_rejected_frames"]
    _assert_rig_close(result.rig, true)


def test_half_turn_numbering_is_reconciled_and_shifted_grid_rejected(sim):
    """A right view numbered a half turn off is renumbered; one shifted by a square is dropped."""
    from core.boards import BoardDetection

    true, board, collection, _ = sim["chessboard"]
    views = list(collection.views)
    both = [i for i, v in enumerate(views) if v.both]
    k_flip, k_shift = both[0], both[1]
    views[k_flip] = dataclasses.replace(views[k_flip], right=views[k_flip].right.flipped(board))
    det = views[k_shift].right
    cols = board.cols
    keep = det.ids % cols != 0  # drop column 0, call column c column c - 1
    ids = det.ids[keep] - 1
    shifted = BoardDetection(ids, det.corners_px[keep], board.object_points()[ids], det.image_size)
    views[k_shift] = dataclasses.replace(views[k_shift], right=shifted)
    result = calibrate_stereo(dataclasses.replace(collection, views=views), board)
    rejected = result.quality["views_rejected_frames"]
    assert views[k_shift].frame in rejected
    assert views[k_flip].frame not in rejected
    assert views[k_flip].frame in [pv["frame"] for pv in result.quality["per_view"]]
    _assert_rig_close(result.rig, true)


def test_held_out_views_check_the_square_length(sim):
    _true, board, collection, _ = sim["chessboard"]
    result = calibrate_stereo(collection, board, max_views=14, max_held_out=6)
    q = result.quality
    assert q["views_used"] <= 14
    assert q["square_check_method"] == "held_out" and q["square_check_views"] == 6
    assert abs(q["square_error_mm_mean"]) < 0.02  # mm
    assert q["square_error_mm_rms"] < 0.1  # mm


def test_selection_skips_near_duplicates_and_blurred_views(sim):
    _true, _board, collection, _ = sim["chessboard"]
    n = len(collection.views)
    # Each pose twice (a board held still), and one view marked as blurred.
    views = list(collection.views) + [
        dataclasses.replace(v, frame=v.frame + 1000) for v in collection.views
    ]
    views[0] = dataclasses.replace(views[0], edge_width_px=8.0)
    sel = select_views(dataclasses.replace(collection, views=views), max_views=40, max_held_out=0)
    assert 0 in sel.blurred and 0 not in sel.used
    assert len(sel.used) <= n
    assert sel.duplicates >= n - 1
    assert len({views[i].frame % 1000 for i in sel.used}) == len(sel.used)


def test_edge_width_grows_with_blur(sim_dir):
    board = BoardSpec.from_dict(json.loads((sim_dir / "chessboard.json").read_text()))
    from core.boards import detect_board
    from core.video import iter_frames

    frame = next(iter(iter_frames(sim_dir / "chessboard_left.mkv")))
    det = detect_board(frame, board)
    assert det is not None
    sharp = edge_width_px(frame, det)
    blurred = edge_width_px(cv2.GaussianBlur(frame, (0, 0), 2.0), det)
    assert sharp < 3.0  # px: a sharp edge, with the Sobel kernel's own smoothing
    assert blurred > sharp + 2.0  # px: about 2.5 x sigma wider


def test_sampling_bounds_the_frames_searched(sim_dir):
    board = BoardSpec.from_dict(json.loads((sim_dir / "chessboard.json").read_text()))
    collection = collect_views(
        sim_dir / "chessboard_left.mkv", sim_dir / "chessboard_right.mkv", board, max_candidates=8
    )
    frames = [v.frame for v in collection.views]
    assert len(frames) == 8 and frames[0] == 0 and frames[-1] == 23
    assert collection.frames_total == 24


# -- errors -------------------------------------------------------------------------


def test_too_few_views_is_a_clear_error(sim):
    _true, board, collection, _ = sim["chessboard"]
    few = dataclasses.replace(collection, views=collection.views[: MIN_VIEWS - 2])
    with pytest.raises(DetectionError, match=r"found in 4 of 4 left frames; at least 6 are needed"):
        calibrate_stereo(few, board)
    # Found in each camera, but never in both at once.
    views = [
        dataclasses.replace(v, right=None) if i % 2 else dataclasses.replace(v, left=None)
        for i, v in enumerate(collection.views)
    ]
    with pytest.raises(CalibrationError, match="in both cameras"):
        calibrate_stereo(dataclasses.replace(collection, views=views), board)


def test_input_errors(tmp_path, opencv_folders):
    left, right = opencv_folders
    board = BoardSpec("chessboard", cols=9, rows=6, square_mm=25.0)
    with pytest.raises(InputError, match="does not exist"):
        collect_views(tmp_path / "nope", right, board)
    short = tmp_path / "short"
    short.mkdir()
    for f in sorted(left.iterdir())[:5]:
        (short / f.name).symlink_to(f.resolve())
    with pytest.raises(InputError, match="holds 5 images but the right 13"):
        collect_views(short, right, board)
    video = tmp_path / "v.mkv"
    video.write_bytes(b"not a video")
    with pytest.raises(InputError):
        collect_views(video, right, board)


def test_cameras_of_different_resolutions(tmp_path, opencv_folders):
    """A right camera at half the resolution: calibrated at its own size, same geometry.

    (Before issue 11 two sizes were refused; a rig may hold two different cameras.)
    """
    left, right = opencv_folders
    board = BoardSpec("chessboard", cols=9, rows=6, square_mm=25.0)
    small = tmp_path / "small"
    small.mkdir()
    for f in sorted(right.iterdir()):
        image = cv2.imread(str(f))
        cv2.imwrite(str(small / f"{f.stem}.png"), cv2.resize(image, (320, 240), cv2.INTER_AREA))
    full = calibrate_stereo_from_paths(left, right, board).rig
    half = calibrate_stereo_from_paths(left, small, board).rig
    assert half.left.image_size == ImageSize(640, 480)
    assert half.right.image_size == ImageSize(320, 240)
    # A pixel of the half-size image spans two of the full one (centre at (x + 0.5) / 2 - 0.5).
    assert half.right.K[0, 0] == pytest.approx(full.right.K[0, 0] / 2, rel=0.01)  # 1 %
    assert half.right.K[0, 2] == pytest.approx((full.right.K[0, 2] + 0.5) / 2 - 0.5, abs=2.0)  # px
    assert half.baseline_mm == pytest.approx(full.baseline_mm, rel=0.01)  # 1 %
    assert _rotation_deg(half.R_right_from_left, full.R_right_from_left) < 0.3  # degrees


# -- quality --------------------------------------------------------------------------


def test_quality_verdict_levels():
    good = {
        "rms_px": 0.2,
        "epipolar_px_mean": 0.1,
        "square_mm": 25.0,
        "square_error_mm_mean": 0.01,
        "coverage_left": 0.7,
        "coverage_right": 0.6,
        "views_used": 30,
    }
    assert quality_verdict(good) == ("good", [])
    verdict, reasons = quality_verdict({**good, "rms_px": 0.8})
    assert verdict == "acceptable" and len(reasons) == 1 and "reprojection" in reasons[0]
    verdict, reasons = quality_verdict({**good, "square_error_mm_mean": -0.5, "coverage_left": 0.1})
    assert verdict == "poor" and len(reasons) == 2
    assert quality_verdict({"rms_px": 0.3}) == ("good", [])  # missing figures are not judged


def test_image_coverage():
    size = ImageSize(100, 80)
    assert image_coverage(np.zeros((0, 2)), size) == 0.0
    xs, ys = np.meshgrid(np.arange(5, 100, 10.0), np.arange(5, 80, 10.0))
    assert image_coverage(np.column_stack([xs.ravel(), ys.ravel()]), size) == 1.0
    assert image_coverage(np.array([[1.0, 1.0], [2.0, 2.0]]), size) == pytest.approx(1 / 80)


def test_stereo_view_both():
    assert not StereoView(0, None, None).both


def test_motion_blurred_frames_are_dropped(tmp_path):
    """A board moved between still poses: frames taken while it moves fast are not used."""
    rig = example_rig(image_size=ImageSize(640, 512))
    fps = 10.0
    write_board_recordings(
        rig,
        tmp_path,
        seed=5,
        board="chessboard",
        duration_s=2.0,
        fps=fps,
        pose_interval_s=1.0,
        exposure_s=0.01,
        supersample=2,
    )
    board = BoardSpec.from_dict(json.loads((tmp_path / "chessboard.json").read_text()))
    collection = collect_views(
        tmp_path / "chessboard_left.mkv", tmp_path / "chessboard_right.mkv", board
    )
    sel = select_views(collection)
    blurred = [collection.views[i].frame for i in sel.blurred]
    # The board holds still for frames 0-4 of every second and moves during frames 5-9.
    assert len(blurred) >= 3
    assert all(f % 10 >= 5 for f in blurred)
    widths = np.array([v.edge_width_px for v in collection.views if v.both])
    still = np.array([v.edge_width_px for v in collection.views if v.both and v.frame % 10 < 5])
    assert np.max(still) < 1.3 * np.median(widths)  # no still frame is called blurred
    result = calibrate_stereo(collection, board)
    assert result.quality["views_blurred"] == len(blurred)
    assert abs(result.rig.baseline_mm - rig.baseline_mm) < 2.0  # mm, from a few views at 640x512


def test_recordings_as_image_folders_calibrate_from_folders(tmp_path):
    rig = example_rig(image_size=ImageSize(640, 512))
    written = write_board_recordings(
        rig,
        tmp_path,
        seed=2,
        board="charuco",
        duration_s=1.0,
        fps=10.0,
        pose_interval_s=0.1,
        as_images=True,
        supersample=2,
    )
    assert [p.name for p in written] == [
        "charuco_left",
        "charuco_right",
        "charuco.json",
        "rig_true.json",
    ]
    assert len(list((tmp_path / "charuco_left").glob("*.png"))) == 10
    board = BoardSpec.from_dict(json.loads((tmp_path / "charuco.json").read_text()))
    result = calibrate_stereo_from_paths(
        tmp_path / "charuco_left", tmp_path / "charuco_right", board
    )
    assert result.quality["source"] == "images"
    assert abs(result.rig.baseline_mm - rig.baseline_mm) < 2.0  # mm, 10 views at 640x512


# -- free-running cameras (issue 11) ---------------------------------------------------

#: Right camera starts this much later (s); 4.5 frames at 15 fps.
LATE_START_S = 0.3


@pytest.fixture(scope="module")
def free_running_dir(tmp_path_factory):
    """Two free-running 1280x1024 H.264 cameras with variable-frame-rate timestamps
    (0.5 ms jitter), the right one starting 0.3 s later with a 100 ppm faster clock;
    a board held still 0.2 s in each of 15 poses, moved in between (6 s at 15 fps)."""
    from core.simulation.timing import CameraTiming

    out = tmp_path_factory.mktemp("free-running-boards")
    write_board_recordings(
        example_rig(),
        out,
        seed=11,
        board="chessboard",
        duration_s=6.0,
        fps=15.0,
        pose_interval_s=0.4,
        supersample=2,
        codec="h264",
        timing=(
            CameraTiming(vfr=True, jitter_s=0.0005),
            CameraTiming(start_s=LATE_START_S, drift_ppm=100.0, vfr=True, jitter_s=0.0005),
        ),
    )
    return out


def test_free_running_videos_calibrate_and_report_the_offset(free_running_dir):
    """Acceptance (issue 11): baseline within 0.1 mm and rotation within 0.05 degrees of
    the truth from two free-running board videos, one starting 0.3 s later; the offset
    is reported. Pairing the frames by number, this recording failed with "the board
    corners do not fit one rig (reprojection error 47.7 px)"."""
    d = free_running_dir
    board = BoardSpec.from_dict(json.loads((d / "chessboard.json").read_text()))
    truth = json.loads((d / "timing_true.json").read_text())
    assert truth["offset_s"] == pytest.approx(LATE_START_S)
    result = calibrate_stereo_from_paths(
        d / "chessboard_left.mp4", d / "chessboard_right.mp4", board
    )
    true = read_rig(d / "rig_true.json")
    assert abs(result.rig.baseline_mm - true.baseline_mm) < 0.1  # mm (0.008 measured)
    assert _rotation_deg(result.rig.R_right_from_left, true.R_right_from_left) < 0.05  # deg
    sync = result.quality["sync"]
    assert sync["method"] == "estimated" and sync["refined"]
    assert abs(sync["offset_s"] - LATE_START_S) < 0.003  # s: 0.0002-0.0016 measured
    assert sync["offset_frames"] == pytest.approx(sync["offset_s"] * 15.0, abs=0.01)  # frames
    assert result.quality["views_used"] >= 12
    assert result.quality["rms_px"] < 0.1  # px
    json.dumps(result.quality)


def test_images_that_do_not_pair_up_are_refused(tmp_path):
    """Each left image paired with the next pose's right image: the error says the
    folders do not pair up (before: "the board corners do not fit one rig")."""
    write_board_recordings(
        example_rig(image_size=ImageSize(640, 512)),
        tmp_path,
        seed=2,
        board="chessboard",
        duration_s=1.2,
        fps=10.0,
        pose_interval_s=0.1,
        as_images=True,
        supersample=2,
    )
    right = tmp_path / "chessboard_right"
    names = sorted(f.name for f in right.iterdir())
    for old, new in zip(names, names[1:] + names[:1], strict=True):
        (right / old).rename(right / f"x{new}")
    for f in right.iterdir():
        f.rename(right / f.name[1:])
    board = BoardSpec.from_dict(json.loads((tmp_path / "chessboard.json").read_text()))
    with pytest.raises(CalibrationError, match="images do not pair up") as err:
        calibrate_stereo_from_paths(tmp_path / "chessboard_left", right, board)
    assert "file-name order" in str(err.value)


def test_videos_of_different_sessions_are_refused(tmp_path):
    """Two recordings that were not made together: no offset explains them, and the
    error says so instead of blaming the board."""
    rig = example_rig(image_size=ImageSize(640, 512))
    for seed in (5, 6):
        write_board_recordings(
            rig,
            tmp_path / str(seed),
            seed=seed,
            board="chessboard",
            duration_s=3.0,
            fps=10.0,
            pose_interval_s=0.5,
            supersample=2,
        )
    board = BoardSpec.from_dict(json.loads((tmp_path / "5" / "chessboard.json").read_text()))
    with pytest.raises(CalibrationError, match="do not show the board at the same moments"):
        calibrate_stereo_from_paths(
            tmp_path / "5" / "chessboard_left.mkv", tmp_path / "6" / "chessboard_right.mkv", board
        )


@pytest.fixture(scope="module")
def two_rate_boards(tmp_path_factory):
    """The true rig and a folder of chessboard videos from a 15-fps and a 30-fps camera, the
    faster starting 0.25 s later."""
    from core.simulation.timing import CameraTiming

    rig = example_rig(image_size=ImageSize(640, 512))
    folder = tmp_path_factory.mktemp("two-rate-boards")
    write_board_recordings(
        rig,
        folder,
        seed=7,
        board="chessboard",
        duration_s=5.0,
        fps=15.0,
        pose_interval_s=0.6,
        supersample=2,
        timing=(CameraTiming(), CameraTiming(fps=30.0, start_s=0.25)),
    )
    return rig, folder


def test_timestamps_files_stand_in_for_a_squeezed_container_clock(two_rate_boards, tmp_path):
    """A browser take's WebM can carry the recorder's squeezed times (on a loaded machine one
    camera's file spanned half its take): the capture page's timestamps files give each
    frame's real capture time, and the calibration pairs the views by them."""
    from core.video import VideoWriter, iter_frames, probe_video

    rig, folder = two_rate_boards
    board = BoardSpec.from_dict(json.loads((folder / "chessboard.json").read_text()))
    left, right = folder / "chessboard_left.mkv", folder / "chessboard_right.mkv"
    squeezed = tmp_path / "squeezed_right.mkv"  # the same frames, stamped at twice the rate
    with VideoWriter(squeezed, fps=60.0, image_size=rig.right.image_size) as writer:
        for frame in iter_frames(right):
            writer.write(frame)
    n_right = probe_video(squeezed).frame_count
    times = tmp_path / "right_times.csv"  # on the camera's own clock: any origin
    times.write_text(
        "frame,time_s\n" + "".join(f"{i},{1000.0 + i / 30.0:.6f}\n" for i in range(n_right))
    )

    with pytest.raises(CalibrationError, match="same moment"):  # paired by the container's clock
        calibrate_stereo_from_paths(left, squeezed, board)
    result = calibrate_stereo_from_paths(left, squeezed, board, right_times=times)
    sync = result.quality["sync"]
    assert sync["method"] == "estimated" and abs(sync["fps_right"] - 30.0) < 0.01  # Hz
    assert abs(sync["offset_s"] - 0.25) < 0.003  # s, as with the true container clock
    assert abs(result.rig.baseline_mm - rig.baseline_mm) < 0.5  # mm
    with pytest.raises(InputError, match="frames"):
        calibrate_stereo_from_paths(left, squeezed, board, left_times=times)  # not its file
    # A file two frames short (a damaged container's slack) is continued at its rate.
    short = tmp_path / "short_times.csv"
    short.write_text("".join(times.read_text().splitlines(keepends=True)[:-2]))
    cut = calibrate_stereo_from_paths(left, squeezed, board, right_times=short)
    assert abs(cut.quality["sync"]["offset_s"] - 0.25) < 0.003  # s

    # A raw H.264 stream (no container, so no rate of its own) is timed by its file too.
    from stream_support import write_raw_h264

    raw = tmp_path / "right.h264"
    write_raw_h264(
        raw,
        iter_frames(right),
        size=rig.right.image_size,
        rate=30,
        options={"preset": "ultrafast", "crf": "12"},
    )
    with pytest.raises(InputError, match="neither frame timestamps nor a frame rate"):
        calibrate_stereo_from_paths(left, raw, board)
    from_raw = calibrate_stereo_from_paths(left, raw, board, right_times=times)
    assert abs(from_raw.quality["sync"]["offset_s"] - 0.25) < 0.003  # s
    assert abs(from_raw.rig.baseline_mm - rig.baseline_mm) < 0.5  # mm


def test_free_running_cameras_at_different_frame_rates(two_rate_boards):
    """A 15-fps and a 30-fps camera, the faster starting 0.25 s later: paired in time."""
    rig, folder = two_rate_boards
    board = BoardSpec.from_dict(json.loads((folder / "chessboard.json").read_text()))
    result = calibrate_stereo_from_paths(
        folder / "chessboard_left.mkv", folder / "chessboard_right.mkv", board
    )
    sync = result.quality["sync"]
    assert sync["method"] == "estimated" and sync["fps_right"] == 30.0
    assert abs(sync["offset_s"] - 0.25) < 0.003  # s (0.0002 measured)
    assert abs(result.rig.baseline_mm - rig.baseline_mm) < 0.5  # mm, 8 views at 640x512 (0.05)
    assert result.quality["warnings"] == []

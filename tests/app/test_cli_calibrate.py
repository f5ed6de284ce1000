"""`bradyscope calibrate` end to end: a rig file on success, one sentence and exit 2 on bad input."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from core.camera import ImageSize, StereoRig, read_rig
from core.simulation.boards import example_rig, write_board_recordings
from core.video import VideoWriter

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "opencv-stereo"
SMALL = ImageSize(640, 512)


def _one_sentence_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err
    assert len(err.splitlines()) == 1, err
    assert err.startswith("bradyscope calibrate: ")
    return err


def _blank_video(path: Path, size: ImageSize, n_frames: int, seed: int) -> Path:
    rng = np.random.default_rng(seed)
    with VideoWriter(path, fps=10.0, image_size=size, codec="lossless") as w:
        for _ in range(n_frames):
            frame = 110 + rng.normal(0, 3, (size.height, size.width))
            w.write(frame.clip(0, 255).astype(np.uint8))
    return path


@pytest.fixture(scope="module")
def small_recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli-boards")
    write_board_recordings(
        example_rig(image_size=SMALL),
        out,
        seed=4,
        board="chessboard",
        duration_s=0.8,
        fps=10.0,
        pose_interval_s=0.1,
    )
    return out


CHESSBOARD_ARGS = ["--board", "chessboard", "--cols", "9", "--rows", "6", "--square-mm", "25"]


def test_calibrate_writes_a_rig_file(tmp_path, capsys):
    if not DATA.is_dir():
        pytest.skip(f"OpenCV's stereo sample images are not in {DATA}")
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
        for f in sorted(DATA.glob(f"{side}*.jpg")):
            (tmp_path / side / f.name).symlink_to(f)
    out = tmp_path / "rig.json"
    code = main(
        [
            "calibrate",
            "--left",
            str(tmp_path / "left"),
            "--right",
            str(tmp_path / "right"),
            *CHESSBOARD_ARGS,
            "-o",
            str(out),
        ]
    )
    assert code == 0
    rig = read_rig(out)
    assert rig.left.image_size == ImageSize(640, 480)
    assert 0 < rig.quality["rms_px"] < 0.5  # px
    assert rig.quality["views_used"] == 13
    printed = capsys.readouterr().out
    assert "rig.json" in printed and "RMS" in printed


def test_board_larger_than_described(tmp_path, capsys):
    """OpenCV's 9x6 board described as 8x6: found as a sub-grid, refused with a sentence."""
    if not DATA.is_dir():
        pytest.skip(f"OpenCV's stereo sample images are not in {DATA}")
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
        for f in sorted(DATA.glob(f"{side}*.jpg")):
            (tmp_path / side / f.name).symlink_to(f)
    code = main(
        [
            "calibrate",
            "--left",
            str(tmp_path / "left"),
            "--right",
            str(tmp_path / "right"),
            "--board",
            "chessboard",
            "--cols",
            "8",
            "--rows",
            "6",
            "--square-mm",
            "25",
            "-o",
            str(tmp_path / "rig.json"),
        ]
    )
    assert code == 2
    assert "more inner corners than the 8x6 given" in _one_sentence_error(capsys)


def test_board_never_in_view(tmp_path, capsys):
    left = _blank_video(tmp_path / "l.mkv", SMALL, 10, seed=1)
    right = _blank_video(tmp_path / "r.mkv", SMALL, 10, seed=2)
    code = main(
        [
            "calibrate",
            "--left",
            str(left),
            "--right",
            str(right),
            *CHESSBOARD_ARGS,
            "-o",
            str(tmp_path / "rig.json"),
        ]
    )
    assert code == 2
    err = _one_sentence_error(capsys)
    assert "found in 0 of 10 left frames" in err and "--cols/--rows" in err
    assert not (tmp_path / "rig.json").exists()


def test_board_size_that_does_not_match(small_recording, tmp_path, capsys):
    code = main(
        [
            "calibrate",
            "--left",
            str(small_recording / "chessboard_left.mkv"),
            "--right",
            str(small_recording / "chessboard_right.mkv"),
            "--board",
            "chessboard",
            "--cols",
            "7",
            "--rows",
            "5",
            "--square-mm",
            "25",
            "-o",
            str(tmp_path / "rig.json"),
        ]
    )
    assert code == 2
    err = _one_sentence_error(capsys)
    assert "7x5 inner-corner chessboard" in err and "found in 0 of 8 left frames" in err


def test_left_and_right_of_different_sizes(tmp_path, capsys):
    """Two cameras of different resolutions calibrate, each at its own size (issue 11;
    they were refused before)."""
    rig = example_rig(image_size=SMALL)
    rig = StereoRig(rig.left, example_rig(image_size=ImageSize(480, 384)).right)
    write_board_recordings(
        rig, tmp_path, seed=4, board="chessboard", duration_s=0.8, fps=10.0, pose_interval_s=0.1
    )
    out = tmp_path / "rig.json"
    code = main(
        [
            "calibrate",
            "--left",
            str(tmp_path / "chessboard_left.mkv"),
            "--right",
            str(tmp_path / "chessboard_right.mkv"),
            *CHESSBOARD_ARGS,
            "-o",
            str(out),
        ]
    )
    assert code == 0, capsys.readouterr().err
    found = read_rig(out)
    assert found.left.image_size == SMALL and found.right.image_size == ImageSize(480, 384)
    assert abs(found.baseline_mm - rig.baseline_mm) < 1.0  # mm, from only 8 views


def test_small_recording_calibrates(small_recording, tmp_path):
    """The error tests' recording is itself a valid calibration input (so they test the right thing)."""
    out = tmp_path / "rig.json"
    code = main(
        [
            "calibrate",
            "--left",
            str(small_recording / "chessboard_left.mkv"),
            "--right",
            str(small_recording / "chessboard_right.mkv"),
            *CHESSBOARD_ARGS,
            "-o",
            str(out),
        ]
    )
    assert code == 0
    true = read_rig(small_recording / "rig_true.json")
    assert abs(read_rig(out).baseline_mm - true.baseline_mm) < 1.0  # mm, from only 8 views


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (["--board", "charuco", "--cols", "10", "--rows", "7", "--square-mm", "25"], "marker_mm"),
        (["--board", "chessboard", "--cols", "6", "--rows", "6", "--square-mm", "25"], "symmetric"),
        ([*CHESSBOARD_ARGS, "--marker-mm", "18"], "ChArUco"),
    ],
)
def test_bad_board_description(tmp_path, capsys, extra, match):
    code = main(
        [
            "calibrate",
            "--left",
            str(tmp_path),
            "--right",
            str(tmp_path),
            *extra,
            "-o",
            str(tmp_path / "rig.json"),
        ]
    )
    assert code == 2
    assert match in _one_sentence_error(capsys)


def test_missing_input(tmp_path, capsys):
    code = main(
        [
            "calibrate",
            "--left",
            str(tmp_path / "nope.mp4"),
            "--right",
            str(tmp_path / "nope2.mp4"),
            *CHESSBOARD_ARGS,
            "-o",
            str(tmp_path / "rig.json"),
        ]
    )
    assert code == 2
    assert "does not exist" in _one_sentence_error(capsys)


# -- free-running cameras, lengths, board layouts (issue 11) ---------------------------


@pytest.fixture(scope="module")
def late_start_recording(tmp_path_factory):
    """The issue's case: the right camera starts 3 frames (0.3 s at 10 fps) late."""
    from core.simulation.timing import CameraTiming

    out = tmp_path_factory.mktemp("cli-late-start")
    write_board_recordings(
        example_rig(image_size=SMALL),
        out,
        seed=4,
        board="chessboard",
        duration_s=5.0,
        fps=10.0,
        pose_interval_s=0.6,
        supersample=2,
        timing=(CameraTiming(), CameraTiming(start_s=0.3)),
    )
    return out


def test_free_running_videos_calibrate_and_print_the_offset(late_start_recording, tmp_path, capsys):
    """Before: "the board corners do not fit one rig (reprojection error 19.9 px)..."."""
    out = tmp_path / "rig.json"
    code = main(
        [
            "calibrate",
            "--left",
            str(late_start_recording / "chessboard_left.mkv"),
            "--right",
            str(late_start_recording / "chessboard_right.mkv"),
            *CHESSBOARD_ARGS,
            "-o",
            str(out),
        ]
    )
    printed = capsys.readouterr()
    assert code == 0, printed.err
    found = re.search(
        r"the right video starts ([0-9.]+) s \(([0-9.]+) frames\) after the left", printed.out
    )
    assert found, printed.out
    assert abs(float(found.group(1)) - 0.3) < 0.005  # s
    assert abs(float(found.group(2)) - 3.0) < 0.05  # frames
    rig = read_rig(out)
    assert rig.quality["sync"]["method"] == "estimated"
    true = read_rig(late_start_recording / "rig_true.json")
    assert abs(rig.baseline_mm - true.baseline_mm) < 1.0  # mm, at 640x512


def test_timestamps_files_reach_the_calibration(late_start_recording, tmp_path, capsys):
    """--left-times/--right-times as for analyze: a file that does not fit its video is one
    sentence naming it (core.timing reads it; the squeezed-clock case is in
    tests/core/test_calibration.py)."""
    times = tmp_path / "right_times.csv"
    times.write_text("frame,time_s\n" + "".join(f"{i},{i / 10:.3f}\n" for i in range(5)))
    code = main(
        [
            "calibrate",
            "--left",
            str(late_start_recording / "chessboard_left.mkv"),
            "--right",
            str(late_start_recording / "chessboard_right.mkv"),
            "--right-times",
            str(times),
            *CHESSBOARD_ARGS,
            "-o",
            str(tmp_path / "rig.json"),
        ]
    )
    assert code == 2
    err = _one_sentence_error(capsys)
    assert "right_times.csv" in err and "frames" in err, err
    assert not (tmp_path / "rig.json").exists()


def test_videos_of_different_lengths_get_a_warning(late_start_recording, tmp_path, capsys):
    """Before, the longer video was cut to the shorter one without a word."""
    from core.video import iter_frames

    right = tmp_path / "right.mkv"
    with VideoWriter(right, fps=10.0, image_size=SMALL, codec="lossless") as w:
        for frame in iter_frames(late_start_recording / "chessboard_right.mkv", stop=45):
            w.write(frame)
    out = tmp_path / "rig.json"
    code = main(
        [
            "calibrate",
            "--left",
            str(late_start_recording / "chessboard_left.mkv"),
            "--right",
            str(right),
            *CHESSBOARD_ARGS,
            "-o",
            str(out),
        ]
    )
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert (
        "bradyscope calibrate: warning: the left video has 50 frames and the right 45"
        in printed.err
    )
    assert read_rig(out).quality["warnings"] == [
        "the left video has 50 frames and the right 45; the frames past the end of the shorter"
        " one (45) are not used."
    ]


@pytest.fixture(scope="module")
def legacy_charuco_images(tmp_path_factory):
    """A ChArUco board printed in OpenCV's layout of before 4.6 (8x6 squares: even rows)."""
    from core.boards import BoardSpec

    out = tmp_path_factory.mktemp("cli-legacy")
    board = BoardSpec("charuco", cols=8, rows=6, square_mm=30.0, marker_mm=22.0, legacy=True)
    write_board_recordings(
        example_rig(image_size=SMALL),
        out,
        seed=3,
        board="charuco",
        charuco=board,
        duration_s=0.8,
        fps=10.0,
        pose_interval_s=0.1,
        as_images=True,
        supersample=2,
    )
    return out


CHARUCO_ARGS = ["--board", "charuco", "--square-mm", "30", "--marker-mm", "22"]


@pytest.mark.parametrize(
    ("extra", "hint"),
    [
        (["--cols", "8", "--rows", "6"], "add --legacy"),
        (["--cols", "6", "--rows", "8", "--legacy"], "swap --cols and --rows (--cols 8 --rows 6)"),
    ],
)
def test_charuco_board_described_wrong_gets_a_hint(
    legacy_charuco_images, tmp_path, capsys, extra, hint
):
    code = main(
        [
            "calibrate",
            "--left",
            str(legacy_charuco_images / "charuco_left"),
            "--right",
            str(legacy_charuco_images / "charuco_right"),
            *CHARUCO_ARGS,
            *extra,
            "-o",
            str(tmp_path / "rig.json"),
        ]
    )
    assert code == 2
    err = _one_sentence_error(capsys)
    assert "found in 0 of 8 left frames" in err and hint in err


def test_legacy_charuco_board_calibrates(legacy_charuco_images, tmp_path):
    out = tmp_path / "rig.json"
    code = main(
        [
            "calibrate",
            "--left",
            str(legacy_charuco_images / "charuco_left"),
            "--right",
            str(legacy_charuco_images / "charuco_right"),
            *CHARUCO_ARGS,
            "--cols",
            "8",
            "--rows",
            "6",
            "--legacy",
            "-o",
            str(out),
        ]
    )
    assert code == 0
    rig = read_rig(out)
    assert rig.quality["board"]["legacy"] is True
    assert rig.quality["sync"]["method"] == "images"
    true = read_rig(legacy_charuco_images / "rig_true.json")
    assert abs(rig.baseline_mm - true.baseline_mm) < 1.0  # mm, from 8 views at 640x512


def test_a_truncated_board_video_is_refused_in_one_sentence(small_recording, tmp_path, capsys):
    """An operations review: calibrate measured a cut MKV (the container still announcing
    all its frames) without a word, where the upload and analyze refuse the same file."""
    whole = small_recording / "chessboard_left.mkv"
    cut = tmp_path / "cut_left.mkv"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    code = main(
        ["calibrate", "--left", str(cut), "--right", str(small_recording / "chessboard_right.mkv"),
         *CHESSBOARD_ARGS, "-o", str(tmp_path / "rig.json")]
    )  # fmt: skip
    assert code == 2
    err = _one_sentence_error(capsys)
    assert "cut_left.mkv ends after" in err and "truncated" in err
    assert not (tmp_path / "rig.json").exists()


def test_board_videos_given_the_wrong_way_round_are_pointed_out(small_recording, tmp_path, capsys):
    """An operations review: a calibration from the two board videos exchanged was
    accepted as good, the right camera to the left; every analysis with it would fail."""
    out = tmp_path / "rig.json"
    code = main(
        ["calibrate", "--left", str(small_recording / "chessboard_right.mkv"),
         "--right", str(small_recording / "chessboard_left.mkv"), *CHESSBOARD_ARGS,
         "-o", str(out)]
    )  # fmt: skip
    assert code == 0
    warnings = read_rig(out).quality["warnings"]
    assert any("sits" in w and "to the left of the camera given as left" in w for w in warnings)
    printed = capsys.readouterr()
    assert "to the left of the camera given as left" in printed.out + printed.err
    right_way = tmp_path / "right-way.json"
    assert main(["calibrate", "--left", str(small_recording / "chessboard_left.mkv"),
                 "--right", str(small_recording / "chessboard_right.mkv"), *CHESSBOARD_ARGS,
                 "-o", str(right_way)]) == 0  # fmt: skip
    assert not any("to the left of" in w for w in read_rig(right_way).quality["warnings"])

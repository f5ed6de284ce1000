"""`bradyscope analyze` on a small simulated recording: files, sync option, errors."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from stream_support import write_raw_h264

from app.cli import main
from core.camera import ImageSize
from core.simulation.kinematics import TappingScenario
from core.simulation.session import ImagingScenario, SimulatedSession, simulate_session

OFFSET = 10  # frames: the largest offset the acceptance names


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> SimulatedSession:
    return simulate_session(
        tmp_path_factory.mktemp("cli"),
        seed=8,
        tapping=TappingScenario(duration_s=2.5, fps=100.0, frequency_hz=3.0),
        imaging=ImagingScenario(
            image_size=ImageSize(640, 512), offset_frames=OFFSET, distractors_static=1
        ),
    )


def test_analyze_writes_outputs_and_finds_the_offset(
    session: SimulatedSession, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    code = main(
        ["analyze", "--rig", str(session.rig_path), "--left", str(session.left_video),
         "--right", str(session.right_video), "-o", str(out), "--auto-sync"]
    )  # fmt: skip
    assert code == 0
    doc = json.loads((out / "result.json").read_text(encoding="utf-8"))
    assert doc["format"] == "bradyscope.result/1"
    assert doc["task"] == "finger_tapping"  # the default --task
    assert doc["sync"]["offset_frames"] == float(OFFSET) and doc["sync"]["method"] == "auto"
    with open(out / "markers.csv", newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    n = len(session.truth["positions_mm"])
    assert len(rows) == 2 * n
    truth = np.asarray(session.truth["positions_mm"])[:, :2]
    measured = [r for r in rows if r["status"] == "measured"]
    assert len(measured) > 0.9 * 2 * (n - OFFSET)
    for r in measured[::25]:
        m = 0 if r["marker"] == "thumb" else 1
        xyz = np.array([float(r["x_mm"]), float(r["y_mm"]), float(r["z_mm"])])
        assert (
            np.linalg.norm(xyz - truth[int(r["frame"]), m]) < 0.3
        )  # mm (640x512: half the resolution)


def test_given_offset_and_swap(session: SimulatedSession, tmp_path: Path) -> None:
    out = tmp_path / "out"
    code = main(
        ["analyze", "--rig", str(session.rig_path), "--left", str(session.left_video),
         "--right", str(session.right_video), "-o", str(out), "--offset-frames", str(OFFSET),
         "--swap-labels"]
    )  # fmt: skip
    assert code == 0
    doc = json.loads((out / "result.json").read_text(encoding="utf-8"))
    given = {"offset_frames": float(OFFSET), "method": "given", "confidence": 1.0}
    assert {k: doc["sync"][k] for k in given} == given  # plus the time model's keys (docs/sync.md)
    assert doc["sync"]["drift_ppm"] == 0.0 and doc["sync"]["dropped_frames_right"] == []
    with open(out / "markers.csv", newline="", encoding="utf-8") as fh:
        row = next(
            r for r in csv.DictReader(fh) if r["status"] == "measured" and r["marker"] == "thumb"
        )
    truth = np.asarray(session.truth["positions_mm"])[int(row["frame"]), 1]  # the index finger
    xyz = np.array([float(row["x_mm"]), float(row["y_mm"]), float(row["z_mm"])])
    assert np.linalg.norm(xyz - truth) < 0.3  # mm


def test_bad_input_is_one_sentence(
    session: SimulatedSession, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(
        ["analyze", "--rig", str(session.rig_path), "--left", str(tmp_path / "nope.mkv"),
         "--right", str(session.right_video), "-o", str(tmp_path / "out")]
    )  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bradyscope analyze:") and "nope.mkv" in err and "\n" not in err
    assert "Traceback" not in err
    # Convention: left and right exchanged must fail loudly, not measure garbage.
    code = main(
        ["analyze", "--rig", str(session.rig_path), "--left", str(session.right_video),
         "--right", str(session.left_video), "-o", str(tmp_path / "out")]
    )  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert "swapped" in err and "\n" not in err
    with pytest.raises(SystemExit):
        main(["analyze", "--rig", "r", "--left", "l", "--right", "r", "-o", "o",
              "--offset-frames", "1", "--auto-sync"])  # fmt: skip
    with pytest.raises(SystemExit):  # gait is not an MDS-UPDRS 3.4-3.8 task
        main(["analyze", "--rig", "r", "--left", "l", "--right", "r", "-o", "o",
              "--task", "gait"])  # fmt: skip


def _one_sentence(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("bradyscope analyze:") and "\n" not in err and "Traceback" not in err
    return err


def _analyze(session: SimulatedSession, out: Path, *extra: str, left=None, right=None) -> int:
    left = left or session.left_video
    right = right or session.right_video
    return main(
        ["analyze", "--rig", str(session.rig_path), "--left", str(left), "--right", str(right),
         "-o", str(out), *extra]
    )  # fmt: skip


def test_unrelated_recordings_are_refused_in_one_sentence(
    session: SimulatedSession, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The right video of another test (another patient's rhythm, the hand at the same place
    before the same rig). Before, this was measured (exit 0, half the frames tracked, no tap)
    with a warning."""
    other = simulate_session(
        tmp_path / "other",
        seed=9,
        tapping=TappingScenario(duration_s=2.5, fps=100.0, frequency_hz=2.0),
        imaging=ImagingScenario(image_size=ImageSize(640, 512)),
    )
    out = tmp_path / "out"
    assert _analyze(session, out, right=other.right_video) == 2
    err = _one_sentence(capsys)
    assert "do not show the same motion" in err and "recordings of the same test" in err
    assert not (out / "result.json").exists()


def test_a_timestamps_file_of_another_video_is_refused(
    session: SimulatedSession, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    n = len(session.truth["positions_mm"])
    times = tmp_path / "right_times.csv"
    times.write_text("frame,time_s\n" + "".join(f"{i},{i / 100:.6f}\n" for i in range(n // 2)))
    out = tmp_path / "out"
    assert _analyze(session, out, "--right-times", str(times)) == 2
    err = _one_sentence(capsys)
    assert f"right_times.csv gives the times of {n // 2} frames but its video has {n}" in err
    assert not (out / "result.json").exists()


def _raw_h264(src: Path, dst: Path) -> int:
    """``src`` re-encoded as a raw H.264 stream (no container: no rate, no timestamps)."""
    import av

    with av.open(str(src)) as inp:
        frames = (frame.to_ndarray(format="gray") for frame in inp.decode(video=0))
        return write_raw_h264(
            dst, frames, size=(640, 512), rate=100, options={"crf": "12", "preset": "veryfast"}
        )


def test_free_running_bad_input_is_one_sentence_and_exit_2(
    session: SimulatedSession, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 11's bad inputs: a video with no timestamps and no frame rate, a stream damaged
    part-way (two unrelated recordings: above); each one sentence naming the cause, exit 2."""

    def analyze(left: Path, right: Path, *extra: str) -> tuple[int, str]:
        code = main(
            ["analyze", "--rig", str(session.rig_path), "--left", str(left),
             "--right", str(right), "-o", str(tmp_path / "out"), *extra]
        )  # fmt: skip
        err = capsys.readouterr().err.strip()
        if code:
            assert err.startswith("bradyscope analyze:") and "\n" not in err, err
            assert "Traceback" not in err
        return code, err

    raw = tmp_path / "left.h264"
    n = _raw_h264(session.left_video, raw)
    code, err = analyze(raw, session.right_video)
    assert code == 2 and "neither frame timestamps nor a frame rate" in err
    # As the sentence says: its capture times in a timestamps file make it measurable.
    times = tmp_path / "left_times.csv"
    times.write_text("frame,time_s\n" + "".join(f"{i},{i / 100:.6f}\n" for i in range(n)))
    code, _ = analyze(raw, session.right_video, "--left-times", str(times))
    assert code == 0
    doc = json.loads((tmp_path / "out" / "result.json").read_text(encoding="utf-8"))
    assert doc["sync"]["time_source"] == ["file", "fps"]
    assert doc["sync"]["offset_frames"] == pytest.approx(OFFSET, abs=0.05)

    # The middle third of the file overwritten: the demuxer skips what it cannot read.
    data = bytearray(session.left_video.read_bytes())
    third = len(data) // 3
    data[third : 2 * third] = np.random.default_rng(0).integers(0, 256, third, np.uint8).tobytes()
    damaged = tmp_path / f"damaged{session.left_video.suffix}"
    damaged.write_bytes(bytes(data))
    code, err = analyze(damaged, session.right_video)
    assert code == 2 and "has no frames between" in err and "damaged" in err


def test_numbers_out_of_range_are_one_sentence_and_a_long_gap_is_filled(
    session: SimulatedSession, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An operations review: --max-gap-s above 0.15 s (and nan) and --offset-frames nan
    ended in a traceback; a longer gap is a choice the tracker should take."""
    for extra in (["--max-gap-s", "nan"], ["--max-gap-s", "-1"], ["--offset-frames", "nan"]):
        assert _analyze(session, tmp_path / "bad", *extra) == 2, extra
        _one_sentence(capsys)
    out = tmp_path / "long-gaps"
    assert _analyze(session, out, "--max-gap-s", "0.5") == 0, capsys.readouterr().err
    doc = json.loads((out / "result.json").read_text(encoding="utf-8"))
    assert doc["metrics"]["frequency_hz"] > 0


@pytest.mark.parametrize("how", ["same path", "a copy"])
def test_one_video_for_both_cameras_is_refused_at_once_as_the_server_does(
    session: SimulatedSession,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    how: str,
) -> None:
    """The same file for --left and --right ran the whole analysis before a vague sync
    error; the server refuses it at upload. Refused before anything is decoded."""
    import shutil

    import core.pipeline
    from app.upload_checks import SAME_FILE_MESSAGE

    def measured(*args: object, **kwargs: object) -> None:
        raise AssertionError("the pair was measured")

    monkeypatch.setattr(core.pipeline, "analyze_recording", measured)
    right = session.left_video
    if how == "a copy":
        right = tmp_path / "copy.mkv"
        shutil.copyfile(session.left_video, right)
    assert _analyze(session, tmp_path / "out", right=right) == 2
    assert _one_sentence(capsys) == f"bradyscope analyze: {SAME_FILE_MESSAGE}"
    assert not (tmp_path / "out").exists()

# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Timestamps files with a trial (``left_times`` / ``right_times``): checked, stored, used.

A timestamps file (``frame,time_s``, each frame's capture time on its camera's
clock; what the capture page writes) is checked against its video's decoded
frames, stored beside the video and handed to the pipeline by the worker. A
bad one refuses the whole upload with one sentence and leaves nothing behind.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from api_support import (  # noqa: F401 - fixtures
    Api,
    api,
    seed_recording_target,
    trial_files,
    video_pair,
)
from sqlalchemy import select

from app.models import Video
from app.services.trial_inputs import analysis_inputs
from app.storage import Storage

N_FRAMES = 12  # frames of api_support's test videos


def _times_csv(t_s, *, header: str = "frame,time_s") -> bytes:
    lines = [header] + [f"{i},{t:.6f}" for i, t in enumerate(t_s)]
    return ("\n".join(lines) + "\n").encode()


def _browser_like(seed: int, *, fps: float = 30.0, lost_after: int | None = None) -> np.ndarray:
    """Irregular capture times (s) of ``N_FRAMES`` frames: jitter, one lost frame, own clock."""
    rng = np.random.default_rng(seed)
    steps = np.full(N_FRAMES - 1, 1.0 / fps) + rng.normal(0, 0.0015, N_FRAMES - 1)
    if lost_after is not None:
        steps[lost_after] += 1.0 / fps  # one frame lost after frame `lost_after`
    return 1234.5 + np.concatenate([[0.0], np.cumsum(steps)])  # s, this camera's clock


def _upload(api: Api, session_id: int, files: dict):
    return api.client.post(
        f"/api/v1/sessions/{session_id}/trials",
        data={"hand": "right"},
        files=files,
        headers=api.headers,
    )


def test_timestamps_files_are_stored_with_their_videos_and_measure_the_take(
    api: Api, video_pair
) -> None:
    seeded = seed_recording_target(api)
    left_t, right_t = _browser_like(1), _browser_like(2, lost_after=5)
    csv = {"left": _times_csv(left_t), "right": _times_csv(right_t)}
    files = trial_files(*video_pair)
    files["left_times"] = ("left_times.csv", csv["left"], "text/csv")
    files["right_times"] = ("right_times.csv", csv["right"], "text/csv")
    r = _upload(api, seeded.session_id, files)
    assert r.status_code == 201, r.text
    body = r.json()
    # The quick check of the take, known before the analysis.
    take = body["take"]
    assert take["left"]["frame_count"] == take["right"]["frame_count"] == N_FRAMES
    assert take["left"]["time_source"] == "file"
    assert take["left"]["dropped_frames"] == 0 and take["right"]["dropped_frames"] == 1
    interval = np.median(np.diff(left_t))
    assert take["left"]["duration_s"] == pytest.approx(left_t[-1] - left_t[0] + interval, abs=1e-3)
    assert take["left"]["fps"] == pytest.approx(1 / interval, abs=0.01)  # Hz
    with api.sessions() as db:
        videos = {v.side: v for v in db.scalars(select(Video).where(Video.trial_id == body["id"]))}
    for side in ("left", "right"):
        video = videos[side]
        assert video.times_path is not None and video.times_path != video.path
        stored = api.settings.data_dir / video.times_path
        assert stored.read_bytes() == csv[side]  # byte for byte
        assert video.times_sha256 == hashlib.sha256(csv[side]).hexdigest()
        assert video.duration_s == pytest.approx(take[side]["duration_s"], abs=1e-3)  # s
    read = api.client.get(f"/api/v1/trials/{body['id']}", headers=api.headers).json()
    assert [v["has_times"] for v in read["videos"]] == [True, True]
    # The worker reads the stored files back for the pipeline.
    with api.sessions() as db:
        inputs = analysis_inputs(db, Storage.from_settings(api.settings), body["id"])
    assert inputs.left_times == api.settings.data_dir / videos["left"].times_path
    assert inputs.right_times == api.settings.data_dir / videos["right"].times_path
    assert set(inputs.files) == {
        inputs.left,
        inputs.right,
        inputs.left_times,
        inputs.right_times,
    }


def test_a_trial_without_timestamps_files_is_unchanged(api: Api, video_pair) -> None:
    seeded = seed_recording_target(api)
    r = _upload(api, seeded.session_id, trial_files(*video_pair))
    assert r.status_code == 201, r.text
    assert r.json()["take"]["left"] == {
        "frame_count": N_FRAMES,
        "duration_s": pytest.approx(N_FRAMES / 30.0, abs=1e-3),
        "fps": 30.0,
        "dropped_frames": None,  # constant-rate timestamps cannot tell
        "time_source": "fps",
    }
    with api.sessions() as db:
        inputs = analysis_inputs(db, Storage.from_settings(api.settings), r.json()["id"])
    assert inputs.left_times is None and inputs.right_times is None


GOOD = _browser_like(3)


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"", "The right timestamps file is empty"),
        (_times_csv(GOOD, header="index,t"), "must start with the header frame,time_s"),
        (_times_csv(GOOD[::-1]), "increase from frame to frame"),
        (_times_csv(GOOD[:8]), "gives the times of 8 frames but its video has 12"),
        (_times_csv(np.concatenate([GOOD, GOOD[-1] + np.arange(1, 5) / 30])), "16 frames"),
        (b"frame,time_s\n0,0.0\n1,abc\n", "Line 3 of the right timestamps file"),
        (b"frame,time_s\n0,0.0\n2,0.033\n", "must run 0, 1, 2"),
    ],
)
def test_a_bad_timestamps_file_refuses_the_upload_and_leaves_nothing(
    api: Api, video_pair, content: bytes, words: str
) -> None:
    seeded = seed_recording_target(api)
    files = trial_files(*video_pair)
    files["left_times"] = ("left_times.csv", _times_csv(GOOD), "text/csv")
    files["right_times"] = ("right_times.csv", content, "text/csv")
    r = _upload(api, seeded.session_id, files)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert words in detail and detail.endswith("."), detail
    assert "tmp" not in detail and ".csv" not in detail  # the server's file names stay inside
    assert api.recording_rows() == (0, 0, 0)
    assert api.stored_files() == []

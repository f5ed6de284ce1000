# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""A take sent again (``take_id``): the same take answers its first trial; another one is 409.

A hospital integrator's review found that a ``take_id`` reused for another recording
(another hand, task or pair of videos) answered 201 with the earlier trial and an
empty quick check, so that the new recording was lost without a word.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from api_support import (  # noqa: F401 - fixtures
    Api,
    api,
    seed_recording_target,
    trial_files,
    write_video,
)
from sqlalchemy import select

from app.models import AuditEvent

N_FRAMES = 12  # frames of api_support's test videos


def _times_csv(*, lost_after: int | None = None) -> bytes:
    """Capture times (s) of the test videos' frames at 30 Hz; one frame lost if asked."""
    steps = np.full(N_FRAMES - 1, 1 / 30)
    if lost_after is not None:
        steps[lost_after] += 1 / 30
    t_s = 50.0 + np.concatenate([[0.0], np.cumsum(steps)])
    return ("frame,time_s\n" + "".join(f"{i},{t:.6f}\n" for i, t in enumerate(t_s))).encode()


@pytest.fixture
def take(api: Api, tmp_path: Path):  # type: ignore[no-untyped-def]
    """``send(data, files)`` to the seeded session, and two pairs of distinct videos."""
    seeded = seed_recording_target(api)
    first = write_video(tmp_path / "l1.mp4"), write_video(tmp_path / "r1.mp4", shift_px=2)
    other = (
        write_video(tmp_path / "l2.mp4", shift_px=4),
        write_video(tmp_path / "r2.mp4", shift_px=6),
    )

    def send(data: dict, files: dict):  # type: ignore[no-untyped-def]
        return api.client.post(
            f"/api/v1/sessions/{seeded.session_id}/trials",
            data=data,
            files=files,
            headers=api.headers,
        )

    return send, first, other


def test_a_take_resent_unchanged_answers_its_trial_with_its_quick_check(api: Api, take) -> None:
    send, first, _ = take
    data = {"hand": "right", "task": "finger_tapping", "take_id": "take-0001"}
    files = trial_files(*first)
    files["right_times"] = ("right_times.csv", _times_csv(lost_after=4), "text/csv")
    stored = send(data, files)
    assert stored.status_code == 201, stored.text
    rows = api.recording_rows()
    again = send(data, files)
    assert again.status_code == 201, again.text
    body = again.json()
    assert body["stored_before"] is True and body["id"] == stored.json()["id"]
    assert body["job_id"] == stored.json()["job_id"]
    # The quick check of the stored take, as the first answer gave it (not {}).
    assert body["take"] == stored.json()["take"]
    assert body["take"]["right"]["dropped_frames"] == 1
    assert body["take"]["right"]["time_source"] == "file"
    assert body["take"]["left"]["frame_count"] == N_FRAMES
    assert body["take"]["left"]["time_source"] == "fps"
    assert api.recording_rows() == rows


@pytest.mark.parametrize(
    ("change", "named"),
    [
        ({"hand": "left"}, "hand"),
        ({"task": "hand_movements"}, "task"),
        ({"offset_frames": "3"}, "offset_frames"),
        ({"videos": "other"}, "left_video, right_video"),
        ({"times": "right"}, "right_times"),
        ({"hand": "left", "task": "hand_movements", "videos": "other"}, "hand, task, left_video"),
    ],
)
def test_a_take_id_reused_for_another_recording_is_409(
    api: Api, take, change: dict, named: str
) -> None:
    send, first, other = take
    data = {"hand": "right", "take_id": "take-0001"}
    stored = send(data, trial_files(*first))
    assert stored.status_code == 201, stored.text
    rows, files_before = api.recording_rows(), api.stored_files()
    events_before = len(api.audit_events())

    files = trial_files(*(other if change.get("videos") == "other" else first))
    if change.get("times"):
        files["right_times"] = ("right_times.csv", _times_csv(), "text/csv")
    fields = {k: v for k, v in change.items() if k not in ("videos", "times")}
    refused = send(data | fields, files)

    assert refused.status_code == 409, refused.text
    detail = refused.json()["detail"]
    assert named in detail and f"trial {stored.json()['id']}" in detail
    assert "new take_id" in detail and detail.endswith(".")
    # Nothing stored; the refusal is one audit event, denied, naming the trial it hit.
    assert api.recording_rows() == rows and api.stored_files() == files_before
    with api.sessions() as db:
        new = list(db.scalars(select(AuditEvent).order_by(AuditEvent.id).offset(events_before)))
    assert [(e.action, e.resource_type, e.resource_id, e.outcome) for e in new] == [
        ("create", "trial", str(stored.json()["id"]), "denied")
    ]


def test_a_take_of_the_sessions_rig_named_or_not_is_the_same_take(api: Api, take) -> None:
    """Naming the session's own rig is the same as naming none (docs/api.md)."""
    send, first, _ = take
    data = {"hand": "right", "take_id": "take-0002"}
    stored = send(data, trial_files(*first))
    with api.sessions() as db:
        from app.models import Trial

        rig_id = db.get(Trial, stored.json()["id"]).session.rig_id
    again = send(data | {"rig_id": str(rig_id)}, trial_files(*first))
    assert again.status_code == 201 and again.json()["stored_before"] is True, again.text


def _vfr_video(path: Path, t_s: np.ndarray, *, shift_px: int = 0) -> Path:
    """An H.264 video whose frames carry the presentation times ``t_s`` (variable frame
    rate: a lost frame is a longer interval), a dot moving on grey."""
    from api_support import VIDEO_FPS, VIDEO_SIZE

    from core.video import VideoWriter

    size = VIDEO_SIZE
    yy, xx = np.mgrid[0 : size.height, 0 : size.width]
    with VideoWriter(path, fps=VIDEO_FPS, image_size=size, codec="h264") as writer:
        for i, t in enumerate(t_s):
            frame = np.full((size.height, size.width), 60, np.uint8)
            frame[(xx - 20 - shift_px - 3 * i) ** 2 + (yy - size.height / 2) ** 2 < 36] = 230
            writer.write(frame, time_s=float(t))
    return path


def test_the_quick_check_of_a_variable_frame_rate_take_reads_the_container_times(
    api: Api, take, tmp_path: Path
) -> None:
    """Without a timestamps file, the check counts the frames a camera lost as the analysis
    does, from the container's times: a reviewer found ``time_source: "fps"`` and
    ``dropped_frames: null`` for a take whose analysis found them."""
    from core.timing import frame_times_from_timestamps
    from core.video import iter_frames

    send, _, _ = take
    slots = np.delete(np.arange(33), [10, 21, 22])  # lost after frames 9, 19 and 19 again
    jitter = np.random.default_rng(8).normal(scale=0.001, size=slots.size)  # s
    left = _vfr_video(tmp_path / "vfr-left.mp4", 0.01 + slots / 30.0 + jitter)
    right = _vfr_video(tmp_path / "vfr-right.mp4", np.arange(30) / 30.0, shift_px=2)
    data = {"hand": "right", "take_id": "take-vfr"}
    r = send(data, trial_files(left, right))
    assert r.status_code == 201, r.text
    check = r.json()["take"]
    assert check["left"]["time_source"] == "container", check
    assert check["left"]["dropped_frames"] == 3, check
    assert check["left"]["frame_count"] == 30
    assert check["left"]["duration_s"] == pytest.approx(33 / 30, abs=0.005)  # s, lost included
    assert check["left"]["fps"] == pytest.approx(30.0, abs=0.5)  # Hz, median of jittered steps
    # A constant-rate file's times cannot tell: as before.
    assert check["right"]["time_source"] == "fps" and check["right"]["dropped_frames"] is None
    # What the analysis finds from the decoded frames' timestamps (core.pipeline's rule).
    stamps: list[float] = []
    for _ in iter_frames(left, times_out=stamps):
        pass
    decoded = frame_times_from_timestamps(stamps, fps=30.0)
    assert decoded.source == "container" and len(decoded.dropped_after) == 3
    assert check["left"]["fps"] == round(decoded.fps, 2)
    # The take sent again answers the same check, read again from the stored files.
    again = send(data, trial_files(left, right))
    assert again.status_code == 201 and again.json()["stored_before"] is True
    assert again.json()["take"] == check

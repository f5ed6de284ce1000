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

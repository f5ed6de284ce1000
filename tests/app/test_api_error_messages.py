# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Errors a client can act on (a hospital integrator's review of the API's answers).

Each refusal says what is wrong and what to do, and a 422 about a field names it in
``errors`` (``loc``, ``msg``, ``type``), for multipart fields and query parameters as
for JSON bodies: waiting for a failed trial, asking the administrator for a scope no
key can hold, "names no rig" for ``1.0``, or blaming the video pair for a timestamps
file written in milliseconds sent the client the wrong way.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from api_support import (  # noqa: F401 - fixtures
    Api,
    add_result,
    api,
    rig_document,
    seed_recording_target,
    trial_files,
    video_pair,
)
from sqlalchemy import select

from app.models import AuditEvent, Job, Trial


def _upload(api: Api, session_id: int, data: dict, files: dict):  # type: ignore[no-untyped-def]
    return api.client.post(
        f"/api/v1/sessions/{session_id}/trials", data=data, files=files, headers=api.headers
    )


@pytest.mark.parametrize(
    ("data", "loc", "kind", "words"),
    [
        ({"hand": "left", "rig_id": "1.0"}, "rig_id", "int_parsing", "a whole number"),
        ({"hand": "left", "rig_id": "77"}, "rig_id", "value_error", "rig_id '77' names no rig"),
        (
            {"hand": "left", "offset_frames": "100000"},
            "offset_frames",
            "value_error",
            "from -10000 to 10000",
        ),
        ({"hand": "both"}, "hand", "enum", "'left' or 'right'"),
        ({"hand": "left", "task": "typing"}, "task", "enum", "finger_tapping"),
        ({"hand": "left", "take_id": "x"}, "take_id", "string_pattern_mismatch", "8 to 64"),
        ({}, "hand", "missing", "lacks the form field 'hand'"),
    ],
)
def test_a_bad_trial_field_is_named_in_errors(
    api: Api, video_pair, data: dict, loc: str, kind: str, words: str
) -> None:
    seeded = seed_recording_target(api)
    r = _upload(api, seeded.session_id, data, trial_files(*video_pair))
    assert r.status_code == 422, r.text
    body = r.json()
    assert words in body["detail"] and body["detail"].endswith(".")
    assert body["errors"] == [{"loc": ["body", loc], "msg": body["detail"], "type": kind}]


def test_a_missing_video_and_bad_board_fields_are_named_in_errors(api: Api, video_pair) -> None:
    seeded = seed_recording_target(api)
    files = {"left_video": trial_files(*video_pair)["left_video"]}
    r = _upload(api, seeded.session_id, {"hand": "left"}, files)
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "right_video"]
    assert r.json()["errors"][0]["type"] == "missing"
    url = f"/api/v1/rigs/{seeded.rig_id}/calibrations"
    for fields, loc in (
        ({"board": "chessboard", "cols": "1", "rows": "5", "square_mm": "30"}, "cols"),
        ({"board": "circles", "cols": "7", "rows": "5", "square_mm": "30"}, "board"),
        ({"board": "chessboard", "rows": "5", "square_mm": "30"}, "cols"),
    ):
        r = api.client.post(url, data=fields, files=trial_files(*video_pair), headers=api.headers)
        assert r.status_code == 422, r.text
        assert [e["loc"] for e in r.json()["errors"]] == [["body", loc]]
    rig_file = {"rig_json": ("rig.json", json.dumps(rig_document()).encode(), "application/json")}
    r = api.client.post(url, data={"valid_from": "soon"}, files=rig_file, headers=api.headers)
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "valid_from"]


def test_a_bad_audit_filter_is_named_in_errors(api: Api) -> None:
    r = api.client.get("/api/v1/audit?actor=bogus", headers=api.headers)
    assert r.status_code == 422 and "user:3" in r.json()["detail"]
    assert r.json()["errors"] == [
        {"loc": ["query", "actor"], "msg": r.json()["detail"], "type": "value_error"}
    ]
    r = api.client.get("/api/v1/audit?since=2026-02-01&until=2026-01-01", headers=api.headers)
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["query", "until"]


def test_a_timestamps_file_in_milliseconds_is_said_to_be_in_milliseconds(
    api: Api, video_pair
) -> None:
    seeded = seed_recording_target(api)
    t_ms = 1_234_500.0 + np.arange(12) * 1000 / 30  # a 30 Hz camera's times, in ms
    csv = "frame,time_s\n" + "".join(f"{i},{t:.3f}\n" for i, t in enumerate(t_ms))
    files = trial_files(*video_pair)
    files["left_times"] = ("left_times.csv", csv.encode(), "text/csv")
    r = _upload(api, seeded.session_id, {"hand": "left"}, files)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert detail.startswith("The left timestamps file seems to be written in milliseconds")
    assert "30 frames per second" in detail and "divide its times by 1000" in detail
    assert "pair" not in detail
    assert api.recording_rows() == (0, 0, 0)


@pytest.fixture
def failed_trial(api: Api, video_pair) -> int:
    """A trial whose analysis failed (no result), as the worker leaves it."""
    seeded = seed_recording_target(api)
    trial_id = _upload(api, seeded.session_id, {"hand": "left"}, trial_files(*video_pair)).json()[
        "id"
    ]
    with api.sessions() as db:
        db.get(Trial, trial_id).status = "failed"
        for job in db.scalars(select(Job).where(Job.trial_id == trial_id)):
            job.status = "failed"
            job.error = "the markers were found in 4 of 120 left frames."
        db.commit()
    return trial_id


@pytest.mark.parametrize("name", ["result", "markers.csv", "markers.c3d", "markers.trc", "fhir"])
def test_a_failed_trial_says_it_failed_and_how_to_measure_it_again(
    api: Api, failed_trial: int, name: str
) -> None:
    r = api.client.get(f"/api/v1/trials/{failed_trial}/{name}", headers=api.headers)
    assert r.status_code == 409, r.text
    detail = r.json()["detail"]
    assert f"The analysis of trial {failed_trial} failed: the markers were found" in detail
    assert "offset_frames" in detail and "swap_cameras" in detail
    assert "wait" not in detail and "frames., so" not in detail


def test_correcting_a_failed_trial_says_it_failed(api: Api, failed_trial: int) -> None:
    r = api.client.post(
        f"/api/v1/trials/{failed_trial}/revisions",
        json={"exclude_taps": [1], "reason": "tap 2 was a cough"},
        headers=api.headers,
    )
    assert r.status_code == 409, r.text
    assert "failed" in r.json()["detail"] and "wait" not in r.json()["detail"]
    assert "swap_cameras" in r.json()["detail"]


def test_restoring_with_an_api_key_says_who_restores_and_where(api: Api, video_pair) -> None:
    seeded = seed_recording_target(api)
    trial_id = _upload(api, seeded.session_id, {"hand": "left"}, trial_files(*video_pair)).json()[
        "id"
    ]
    assert api.client.delete(f"/api/v1/trials/{trial_id}", headers=api.headers).status_code == 204
    r = api.client.post(f"/api/v1/trials/{trial_id}/restore", headers=api.headers)
    assert r.status_code == 403, r.text
    detail = r.json()["detail"]
    assert "administrator, logged in to the browser" in detail and "Restore" in detail
    assert "grant" not in detail
    with api.sessions() as db:
        last = db.scalars(select(AuditEvent).order_by(AuditEvent.id.desc())).first()
    assert (last.action, last.outcome) == ("access", "denied")

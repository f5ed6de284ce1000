"""A trial and the rig's calibration being computed (findings 2 and 3 of the failure review).

An analysis whose session a calibration still being computed may cover waits for it
(queued, no attempt spent) and fails, saying so, when that calibration fails; a failed
calibration is not a rig's first, so the corrected one covers the earlier sessions.
Real API, real worker loop and handlers, real (board-less) videos.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime

# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
from api_support import Api, api, rig_document, trial_files, video_pair, write_video  # noqa: F401

from app import jobs
from app.handlers import HANDLERS
from app.job_waits import WAITING_FOR_CALIBRATION
from app.models import Job
from app.worker import run_job, run_worker

BOARD = {"board": "chessboard", "cols": "9", "rows": "6", "square_mm": "25"}


def _board_calibration(api: Api, rig_id: int, tmp_path) -> dict:
    """A calibration from two videos that show no board (its job fails: board not found)."""
    left = write_video(tmp_path / "board_left.mp4")
    right = write_video(tmp_path / "board_right.mp4", shift_px=3)
    r = api.client.post(
        f"/api/v1/rigs/{rig_id}/calibrations",
        data=BOARD,
        files=trial_files(left, right),
        headers=api.headers,
    )
    assert r.status_code == 201 and r.json()["status"] == "pending", r.text
    return r.json()


def _rig_and_patient(api: Api) -> tuple[int, int]:
    h = api.headers
    patient = api.client.post("/api/v1/patients", json={"code": "RV-0001"}, headers=h).json()
    rig = api.client.post("/api/v1/rigs", json={"name": "review-rig"}, headers=h).json()
    return rig["id"], patient["id"]


def _session(api: Api, patient_id: int, rig_id: int, recorded_at: str) -> int:
    r = api.client.post(
        "/api/v1/sessions",
        json={"patient_id": patient_id, "rig_id": rig_id, "recorded_at": recorded_at},
        headers=api.headers,
    )
    assert r.status_code == 201, r.text
    return int(r.json()["id"])


def _valid_from(api: Api, calibration_id: int) -> str:
    r = api.client.get(f"/api/v1/calibrations/{calibration_id}", headers=api.headers)
    return str(r.json()["valid_from"])


def _job(api: Api, job_id: int) -> Job:
    with api.sessions() as db:
        job = db.get(Job, job_id)
        assert job is not None
        return job


def test_an_analysis_waits_for_the_calibration_being_computed_and_says_when_it_failed(
    api: Api, tmp_path, video_pair
) -> None:
    rig_id, patient_id = _rig_and_patient(api)
    cal = _board_calibration(api, rig_id, tmp_path)
    session_id = _session(api, patient_id, rig_id, "2026-11-28T10:00:00Z")
    up = api.client.post(
        f"/api/v1/sessions/{session_id}/trials",
        data={"hand": "right"},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    assert up.status_code == 201, up.text
    analysis_id = up.json()["job_id"]
    # another worker is computing the calibration
    calibrating = jobs.claim_next(
        api.sessions, worker_name="other", lease_s=60.0, kinds=("calibrate",)
    )
    assert calibrating is not None and calibrating.calibration_id == cal["id"]

    # this worker finds nothing it may run: the analysis waits, spending no attempt
    assert run_worker(api.settings, once=True) == 0
    waiting = _job(api, analysis_id)
    assert (waiting.status, waiting.attempts, waiting.error) == ("queued", 0, None)
    seen = api.client.get(f"/api/v1/jobs/{analysis_id}", headers=api.headers).json()
    assert (seen["status"], seen["stage"]) == ("queued", WAITING_FOR_CALIBRATION)

    # the calibration fails (the real handler: no board in the videos)
    assert run_job(calibrating, settings=api.settings, handler=HANDLERS["calibrate"]) == "failed"
    board_error = _job(api, calibrating.id).error
    assert board_error

    run_worker(api.settings, once=True)
    failed = _job(api, analysis_id)
    assert (failed.status, failed.attempts) == ("failed", 1)
    assert failed.error.startswith(f"The calibration v1 of rig {rig_id} (id {cal['id']}) failed: ")
    assert board_error.rstrip(".") in failed.error
    assert "upload a corrected calibration of this rig (it will cover this session)" in failed.error


def test_an_upload_no_calibration_can_measure_is_refused_even_with_one_being_computed(
    api: Api, tmp_path, video_pair
) -> None:
    """A later calibration being computed applies from its upload on: a session before it
    has nothing to wait for, so its trial is refused at once (409), not failed later."""
    rig_id, patient_id = _rig_and_patient(api)
    r = api.client.post(
        f"/api/v1/rigs/{rig_id}/calibrations",
        files={"rig_json": ("rig.json", json.dumps(rig_document()).encode(), "application/json")},
        data={"valid_from": "2026-11-01T00:00:00Z"},
        headers=api.headers,
    )
    assert r.status_code == 201, r.text
    _board_calibration(api, rig_id, tmp_path)  # valid from now on
    session_id = _session(api, patient_id, rig_id, "2026-10-28T10:00:00Z")
    up = api.client.post(
        f"/api/v1/sessions/{session_id}/trials",
        data={"hand": "right"},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    assert up.status_code == 409, up.text
    assert "no ready calibration valid on 2026-10-28 10:00 UTC" in up.json()["detail"]


def test_a_failed_calibration_is_not_the_rigs_first(api: Api, tmp_path) -> None:
    rig_id, _ = _rig_and_patient(api)
    failed = _board_calibration(api, rig_id, tmp_path)
    assert _valid_from(api, failed["id"]) == "1970-01-01T00:00:00Z"  # the first: every session
    run_worker(api.settings, once=True)
    assert _job(api, failed["job_id"]).status == "failed"
    corrected = api.client.post(
        f"/api/v1/rigs/{rig_id}/calibrations",
        files={"rig_json": ("rig.json", json.dumps(rig_document()).encode(), "application/json")},
        headers=api.headers,
    ).json()
    assert _valid_from(api, corrected["id"]) == "1970-01-01T00:00:00Z"
    # a later one (the rig has a usable calibration now) applies from its upload on
    later = api.client.post(
        f"/api/v1/rigs/{rig_id}/calibrations",
        files={"rig_json": ("rig.json", json.dumps(rig_document()).encode(), "application/json")},
        headers=api.headers,
    ).json()
    later_from = datetime.fromisoformat(_valid_from(api, later["id"]).replace("Z", "+00:00"))
    assert later_from.year >= 2026 and later_from <= datetime.now(UTC)

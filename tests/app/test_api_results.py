# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Trials, jobs, results and exports over the REST API."""

from __future__ import annotations

import csv
import io

import pytest
from api_support import (  # noqa: F401 - pytest fixtures
    Api,
    add_result,
    api,
    make_api_key,
    seed_recording_target,
    trial_files,
    video_pair,
)
from sqlalchemy import select

from app.models import AuditEvent, Job, Patient


def _upload(api: Api, video_pair, hand: str = "left") -> dict:
    seeded = seed_recording_target(api)
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": hand, "offset_frames": "1.5"},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    assert r.status_code == 201, r.text
    return {**r.json(), "session_id": seeded.session_id}


def test_trial_job_and_listing(api: Api, video_pair) -> None:
    up = _upload(api, video_pair)
    h = api.headers
    job = api.client.get(f"/api/v1/jobs/{up['job_id']}", headers=h)
    assert job.status_code == 200
    body = job.json()
    assert (body["status"], body["progress"], body["error"], body["trial_id"]) == (
        "queued",
        0.0,
        None,
        up["id"],
    )
    trial = api.client.get(f"/api/v1/trials/{up['id']}", headers=h).json()
    assert trial["hand"] == "left" and trial["offset_frames"] == 1.5
    assert trial["job_id"] == up["job_id"] and trial["has_result"] is False
    assert sorted(v["side"] for v in trial["videos"]) == ["left", "right"]
    listed = api.client.get(f"/api/v1/sessions/{up['session_id']}/trials", headers=h).json()
    assert [t["id"] for t in listed] == [up["id"]]
    assert api.client.get("/api/v1/jobs/999", headers=h).status_code == 404
    assert api.client.delete(f"/api/v1/trials/{up['id']}", headers=h).status_code == 204
    assert api.client.get(f"/api/v1/trials/{up['id']}", headers=h).status_code == 404
    assert api.client.get(f"/api/v1/sessions/{up['session_id']}/trials", headers=h).json() == []


def _job(api: Api, job_id: int) -> dict:
    r = api.client.get(f"/api/v1/jobs/{job_id}", headers=api.headers)
    assert r.status_code == 200, r.text
    return r.json()


def _stored_job(api: Api, job_id: int) -> dict:
    """A job as stored (the API hides the job of a hidden trial, session or patient)."""
    with api.sessions() as db:
        job = db.get(Job, job_id)
        assert job is not None
        return {"status": job.status, "error": job.error or ""}


def test_deleting_a_trial_cancels_its_queued_job(api: Api, video_pair) -> None:
    up = _upload(api, video_pair)
    assert _job(api, up["job_id"])["status"] == "queued"
    assert api.client.delete(f"/api/v1/trials/{up['id']}", headers=api.headers).status_code == 204
    job = _stored_job(api, up["job_id"])
    assert job["status"] == "failed" and "deleted" in job["error"]
    # the job of a hidden trial is hidden like the trial (security review item 4)
    assert api.client.get(f"/api/v1/jobs/{up['job_id']}", headers=api.headers).status_code == 404


def test_deleting_a_session_or_patient_cancels_the_jobs_of_its_trials(api: Api, video_pair) -> None:
    from app import jobs

    up = _upload(api, video_pair)
    h = api.headers
    # The worker is measuring it: a cancelled running job loses its lease.
    claimed = jobs.claim_next(api.sessions, worker_name="test", lease_s=60.0)
    assert claimed is not None and claimed.id == up["job_id"]
    assert api.client.delete(f"/api/v1/sessions/{up['session_id']}", headers=h).status_code == 204
    job = _stored_job(api, up["job_id"])
    assert job["status"] == "failed" and "deleted" in job["error"]
    with pytest.raises(jobs.LeaseLostError):
        jobs.heartbeat(api.sessions, claimed, lease_s=60.0)

    patient_id, rig_id = _patient_and_rig(api, up["session_id"])
    second = api.client.post(
        "/api/v1/sessions",
        json={
            "patient_id": patient_id,
            "rig_id": rig_id,
            "recorded_at": "2026-03-02T09:30:00Z",
            "medication_state": "on",
        },
        headers=h,
    )
    assert second.status_code == 201, second.text
    r = api.client.post(
        f"/api/v1/sessions/{second.json()['id']}/trials",
        data={"hand": "right"},
        files=trial_files(*video_pair),
        headers=h,
    )
    assert r.status_code == 201, r.text
    assert api.client.delete(f"/api/v1/patients/{patient_id}", headers=h).status_code == 204
    job = _stored_job(api, r.json()["job_id"])
    assert job["status"] == "failed" and "deleted" in job["error"]


def _patient_and_rig(api: Api, session_id: int) -> tuple[int, int]:
    from app.models import RecordingSession

    with api.sessions() as db:
        row = db.get(RecordingSession, session_id)
        assert row is not None
        return row.patient_id, row.rig_id


def test_result_is_409_until_the_analysis_succeeded(api: Api, video_pair) -> None:
    up = _upload(api, video_pair)
    suffixes = ("result", "markers.csv", "markers.c3d", "markers.trc", "report.html")
    for suffix in (*suffixes, "report.pdf", "fhir"):
        r = api.client.get(f"/api/v1/trials/{up['id']}/{suffix}", headers=api.headers)
        assert r.status_code == 409, suffix
        assert "no result yet" in r.json()["detail"]
    assert api.client.get("/api/v1/trials/999/result", headers=api.headers).status_code == 404


def test_result_and_exports(api: Api, video_pair) -> None:
    from sample_trial import synthetic_trial

    up = _upload(api, video_pair)
    add_result(api, up["id"])
    h = api.headers
    _, expected = synthetic_trial()
    result = api.client.get(f"/api/v1/trials/{up['id']}/result", headers=h)
    assert result.status_code == 200
    # The stored document, with its revision and (no) edits (INTERFACES.md).
    assert result.json() == {**expected, "revision": 1, "edits": []}
    markers = api.client.get(f"/api/v1/trials/{up['id']}/markers.csv", headers=h)
    assert markers.status_code == 200 and markers.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(markers.text)))
    assert list(rows[0]) == [
        "frame",
        "time_s",
        "marker",
        "x_mm",
        "y_mm",
        "z_mm",
        "status",
        "reprojection_px",
    ]
    html = api.client.get(f"/api/v1/trials/{up['id']}/report.html", headers=h)
    assert html.status_code == 200 and "PD-0042" in html.text
    fhir = api.client.get(f"/api/v1/trials/{up['id']}/fhir", headers=h)
    assert fhir.status_code == 200
    assert fhir.headers["content-type"].startswith("application/fhir+json")
    assert fhir.json()["resourceType"] == "Bundle"
    assert api.client.get("/api/v1/trials/1/result").status_code == 401
    # The trajectories for motion-capture tools, with a key (they were pages only).
    trc = api.client.get(f"/api/v1/trials/{up['id']}/markers.trc", headers=h)
    assert trc.status_code == 200 and trc.text.startswith("PathFileType\t4")
    c3d = api.client.get(f"/api/v1/trials/{up['id']}/markers.c3d", headers=h)
    assert c3d.status_code == 200 and len(c3d.content) > 512
    assert "markers.c3d" in c3d.headers["content-disposition"]
    reader = make_api_key(api.sessions, name="reader", scopes=("patients:read",))
    assert (
        api.client.get(
            f"/api/v1/trials/{up['id']}/markers.c3d", headers={"Authorization": f"Bearer {reader}"}
        ).status_code
        == 403
    )


def test_rig_file_calibration_round_trip(api: Api) -> None:
    import json

    from api_support import rig_document

    h = api.headers
    rig = api.client.post("/api/v1/rigs", json={"name": "clinic-R"}, headers=h).json()
    doc = rig_document()
    r = api.client.post(
        f"/api/v1/rigs/{rig['id']}/calibrations",
        files={"rig_json": ("rig.json", json.dumps(doc).encode(), "application/json")},
        data={"valid_from": "2026-01-01T00:00:00Z"},
        headers=h,
    )
    assert r.status_code == 201, r.text
    assert r.json()["status"] == "ready" and r.json()["job_id"] is None
    cal = api.client.get(f"/api/v1/calibrations/{r.json()['id']}", headers=h).json()
    assert (cal["version"], cal["rms_px"], cal["source"]) == (1, 0.2, "rig_file")
    assert cal["valid_from"] == "2026-01-01T00:00:00Z"
    back = api.client.get(f"/api/v1/calibrations/{cal['id']}/rig.json", headers=h).json()
    assert back["cameras"][1]["t"] == doc["cameras"][1]["t"]
    second = api.client.post(
        f"/api/v1/rigs/{rig['id']}/calibrations",
        files={"rig_json": ("rig.json", json.dumps(doc).encode(), "application/json")},
        headers=h,
    ).json()
    listed = api.client.get(f"/api/v1/rigs/{rig['id']}/calibrations", headers=h).json()
    assert [c["version"] for c in listed] == [1, 2] and listed[1]["id"] == second["id"]
    assert api.client.post("/api/v1/rigs", json={"name": "CLINIC-r"}, headers=h).status_code == 409
    assert api.client.get("/api/v1/rigs", headers=h).json()["total"] == 1


def test_a_take_sent_again_through_the_api_is_stored_once(api: Api, tmp_path) -> None:
    """An operations review: a hospital client retrying after a timeout doubled the trial,
    without a word. A take_id makes the retry safe; without one the second copy warns."""
    from api_support import seed_recording_target, trial_files, write_video

    seeded = seed_recording_target(api)
    left, right = write_video(tmp_path / "l.mp4"), write_video(tmp_path / "r.mp4", shift_px=3)
    url = f"/api/v1/sessions/{seeded.session_id}/trials"

    def send(**fields: str):
        return api.client.post(url, data={"hand": "left", **fields},
                               files=trial_files(left, right), headers=api.headers)  # fmt: skip

    first = send(take_id="his-gateway-0001")
    again = send(take_id="his-gateway-0001")
    assert first.status_code == again.status_code == 201, again.text
    assert again.json()["id"] == first.json()["id"] and again.json()["stored_before"] is True
    assert first.json()["stored_before"] is False
    plain = send()
    assert plain.status_code == 201 and plain.json()["id"] != first.json()["id"]
    assert any(f"trial {first.json()['id']} of this session holds the same two videos" in w
               for w in plain.json()["warnings"])  # fmt: skip
    # the same two videos with the cameras the other way round: said so (finding 12)
    swapped = api.client.post(url, data={"hand": "left"}, files=trial_files(right, left),
                              headers=api.headers)  # fmt: skip
    assert swapped.status_code == 201, swapped.text
    said = [w for w in swapped.json()["warnings"] if "this session holds" in w]
    t = first.json()["id"]
    assert f"trial {t} of this session holds these two videos with the cameras the other way" \
        " round" in said[0] and len(said) == 2  # fmt: skip
    assert not any("holds the same two videos" in w for w in said)


def test_job_status_follows_the_rights_of_the_trials_results(api: Api, video_pair) -> None:
    """A security review: job status (a trial's id, its analysis error) was served to any
    valid key, an audit-only one or a rigs:write-only one too, for a hidden patient too,
    and was not audited; rigs and calibrations were served to an audit-only key."""
    up = _upload(api, video_pair)
    url = f"/api/v1/jobs/{up['job_id']}"
    rigs_only = {
        "Authorization": f"Bearer {make_api_key(api.sessions, name='r', scopes=('rigs:write',))}"
    }
    audit_only = {
        "Authorization": f"Bearer {make_api_key(api.sessions, name='a', scopes=('audit:read',))}"
    }
    for h in (rigs_only, audit_only):
        assert api.client.get(url, headers=h).status_code == 403
    for path in ("/api/v1/rigs", "/api/v1/rigs/1", "/api/v1/rigs/1/calibrations"):
        assert api.client.get(path, headers=audit_only).status_code == 403, path
        assert api.client.get(path, headers=rigs_only).status_code == 200, path
    with api.sessions() as db:
        patient_id = db.scalar(select(Patient.id))
        before = db.scalar(select(AuditEvent.id).order_by(AuditEvent.id.desc()))
    r = api.client.get(url, headers=api.headers)
    assert r.status_code == 200 and r.json()["trial_id"] == up["id"]
    with api.sessions() as db:
        new = list(db.scalars(select(AuditEvent).where(AuditEvent.id > before)))
    assert [(e.action, e.resource_type, e.resource_id, e.patient_id) for e in new] == [
        ("read", "trial", str(up["id"]), patient_id)
    ]
    assert (
        api.client.delete(f"/api/v1/patients/{patient_id}", headers=api.headers).status_code == 204
    )
    r = api.client.get(url, headers=api.headers)
    assert r.status_code == 404 and "deleted" not in r.text  # the trial's analysis error

# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Patients and sessions over the REST API: create, list, search, paginate, update, delete."""

from __future__ import annotations

import pytest
from api_support import (
    Api,
    api,  # noqa: F401 - pytest fixtures
    video_pair,  # noqa: F401 - pytest fixtures
)

from app.models import Patient


def _create(api: Api, code: str, **fields) -> dict:
    r = api.client.post("/api/v1/patients", json={"code": code, **fields}, headers=api.headers)
    assert r.status_code == 201, r.text
    return r.json()


def test_create_read_update_patient(api: Api) -> None:
    created = _create(api, "PD-0042", birth_year=1951, sex="female")
    assert created["code"] == "PD-0042" and created["created_at"].endswith("Z")
    r = api.client.get(f"/api/v1/patients/{created['id']}", headers=api.headers)
    assert r.json() == created
    r = api.client.patch(
        f"/api/v1/patients/{created['id']}",
        json={"notes": "DBS since 2021", "birth_year": None, "code": None},
        headers=api.headers,
    )
    assert r.status_code == 200
    body = r.json()
    assert body["notes"] == "DBS since 2021" and body["birth_year"] is None
    assert body["code"] == "PD-0042"  # code cannot be cleared; null is ignored


def test_patient_validation_and_conflicts(api: Api) -> None:
    _create(api, "PD-1")
    h = api.headers
    for bad in (
        {"code": ""},
        {"code": "has space"},
        {"code": "PD-2", "birth_year": 1700},
        {"code": "PD-2", "sex": "x"},
        {"code": "PD-2", "name": "Jane Doe"},
        {},
    ):
        r = api.client.post("/api/v1/patients", json=bad, headers=h)
        assert r.status_code == 422, bad
        assert r.json()["detail"].startswith("The request is invalid")
        assert isinstance(r.json()["errors"], list)
    r = api.client.post("/api/v1/patients", json={"code": "pd-1"}, headers=h)
    assert r.status_code == 409  # codes are unique regardless of case
    other = _create(api, "PD-3")
    r = api.client.patch(f"/api/v1/patients/{other['id']}", json={"code": "PD-1"}, headers=h)
    assert r.status_code == 409
    assert api.client.get("/api/v1/patients/999", headers=h).status_code == 404
    r = api.client.post(
        "/api/v1/patients", content=b"{not json", headers={**h, "Content-Type": "application/json"}
    )
    assert r.status_code == 400 and "not valid JSON" in r.json()["detail"]  # docs/api.md


def test_list_search_and_paginate(api: Api) -> None:
    for i in range(7):
        _create(api, f"PD-{i:04d}")
    _create(api, "MSA-0001")
    h = api.headers
    page = api.client.get("/api/v1/patients", params={"limit": 3}, headers=h).json()
    assert page["total"] == 8 and page["limit"] == 3 and page["offset"] == 0
    assert [p["code"] for p in page["items"]] == ["MSA-0001", "PD-0000", "PD-0001"]
    seen = []
    for offset in range(0, 8, 3):
        seen += api.client.get(
            "/api/v1/patients", params={"limit": 3, "offset": offset}, headers=h
        ).json()["items"]
    assert len({p["id"] for p in seen}) == 8
    found = api.client.get("/api/v1/patients", params={"q": "msa"}, headers=h).json()
    assert [p["code"] for p in found["items"]] == ["MSA-0001"] and found["total"] == 1
    # LIKE wildcards in the search are taken literally
    assert api.client.get("/api/v1/patients", params={"q": "%"}, headers=h).json()["total"] == 0
    assert api.client.get("/api/v1/patients", params={"limit": 0}, headers=h).status_code == 422
    assert api.client.get("/api/v1/patients", params={"limit": 201}, headers=h).status_code == 422


def test_delete_is_soft_and_keeps_the_code_reserved(api: Api) -> None:
    h = api.headers
    p = _create(api, "PD-9")
    rig = api.client.post("/api/v1/rigs", json={"name": "r"}, headers=h).json()
    s = api.client.post(
        "/api/v1/sessions",
        json={"patient_id": p["id"], "rig_id": rig["id"], "recorded_at": "2026-02-01T08:00:00"},
        headers=h,
    ).json()
    assert api.client.delete(f"/api/v1/patients/{p['id']}", headers=h).status_code == 204
    assert api.client.get(f"/api/v1/patients/{p['id']}", headers=h).status_code == 404
    assert api.client.get(f"/api/v1/sessions/{s['id']}", headers=h).status_code == 404
    assert api.client.get("/api/v1/patients", headers=h).json()["total"] == 0
    assert api.client.delete(f"/api/v1/patients/{p['id']}", headers=h).status_code == 404
    r = api.client.post("/api/v1/patients", json={"code": "PD-9"}, headers=h)
    assert r.status_code == 409 and "deleted" in r.json()["detail"]
    with api.sessions() as db:
        row = db.get(Patient, p["id"])
        assert row is not None and row.deleted_at is not None  # the row is kept


def test_sessions_create_list_update_delete(api: Api) -> None:
    h = api.headers
    p = _create(api, "PD-5")
    rig = api.client.post("/api/v1/rigs", json={"name": "clinic-A"}, headers=h).json()
    ids = []
    for day, med in ((1, "off"), (3, "on"), (2, "unknown")):
        r = api.client.post(
            "/api/v1/sessions",
            json={
                "patient_id": p["id"],
                "rig_id": rig["id"],
                "recorded_at": f"2026-02-0{day}T08:00:00+01:00",
                "medication_state": med,
            },
            headers=h,
        )
        assert r.status_code == 201, r.text
        ids.append(r.json()["id"])
    first = api.client.get(f"/api/v1/sessions/{ids[0]}", headers=h).json()
    assert first["recorded_at"] == "2026-02-01T07:00:00Z"  # stored and returned in UTC
    listed = api.client.get("/api/v1/sessions", params={"patient_id": p["id"]}, headers=h).json()
    assert [s["id"] for s in listed["items"]] == [ids[1], ids[2], ids[0]]  # newest first
    via_patient = api.client.get(f"/api/v1/patients/{p['id']}/sessions", headers=h).json()
    assert via_patient == listed
    r = api.client.patch(
        f"/api/v1/sessions/{ids[0]}",
        json={"medication_state": "on", "time_since_levodopa_min": 90, "dbs_state": None},
        headers=h,
    )
    assert r.status_code == 200
    body = r.json()
    assert (body["medication_state"], body["time_since_levodopa_min"], body["dbs_state"]) == (
        "on",
        90,
        "unknown",
    )
    assert (
        api.client.patch(
            f"/api/v1/sessions/{ids[0]}", json={"more_affected_side": "both"}, headers=h
        ).status_code
        == 422
    )
    for minutes in (True, "90", 90.0):  # strict: not read as 1 or 90
        r = api.client.patch(
            f"/api/v1/sessions/{ids[0]}", json={"time_since_levodopa_min": minutes}, headers=h
        )
        assert r.status_code == 422 and "valid integer" in r.text, (minutes, r.text)
    # The session-level rating moved to the trials: a clear 422 says where.
    r = api.client.patch(f"/api/v1/sessions/{ids[0]}", json={"updrs_34_rating": 3}, headers=h)
    assert r.status_code == 422 and "PATCH /api/v1/trials/" in r.text
    assert (
        api.client.patch(
            f"/api/v1/sessions/{ids[0]}", json={"calibration_id": 77}, headers=h
        ).status_code
        == 422
    )
    assert api.client.delete(f"/api/v1/sessions/{ids[0]}", headers=h).status_code == 204
    listed = api.client.get("/api/v1/sessions", params={"patient_id": p["id"]}, headers=h).json()
    assert listed["total"] == 2
    bad = {"patient_id": p["id"], "rig_id": 999, "recorded_at": "2026-02-01T08:00:00Z"}
    assert api.client.post("/api/v1/sessions", json=bad, headers=h).status_code == 404
    bad = {"patient_id": p["id"], "rig_id": rig["id"], "recorded_at": "0001-01-01T00:00:00+05:00"}
    assert api.client.post("/api/v1/sessions", json=bad, headers=h).status_code == 422


@pytest.mark.postgres
def test_api_on_postgresql(pg_settings, video_pair) -> None:
    """The same use cases on PostgreSQL: search, conflicts, an upload, the audit trail."""
    from api_support import Api, make_api_key, seed_recording_target, trial_files
    from fastapi.testclient import TestClient
    from sqlalchemy import func, select

    from app.db import get_sessionmaker
    from app.main import create_app
    from app.models import AuditEvent

    sessions = get_sessionmaker(pg_settings)
    key = make_api_key(sessions)
    with TestClient(create_app(pg_settings)) as client:
        api = Api(client.app, client, pg_settings, sessions, key)
        seeded = seed_recording_target(api)
        h = api.headers
        assert (
            client.post("/api/v1/patients", json={"code": "pd-0042"}, headers=h).status_code == 409
        )
        found = client.get("/api/v1/patients", params={"q": "d-00", "limit": 1}, headers=h).json()
        assert found["total"] == 1 and found["items"][0]["id"] == seeded.patient_id
        r = client.post(
            f"/api/v1/sessions/{seeded.session_id}/trials",
            data={"hand": "left"},
            files=trial_files(*video_pair),
            headers=h,
        )
        assert r.status_code == 201, r.text
        assert client.get("/api/v1/patients/99999", headers=h).status_code == 404
        with sessions() as db:
            outcomes = dict(
                db.execute(
                    select(AuditEvent.outcome, func.count()).group_by(AuditEvent.outcome)
                ).all()
            )
        # created: patient, rig, calibration, session, trial; one list; one read that
        # missed; one create refused for a taken code
        assert outcomes == {"success": 6, "not_found": 1, "denied": 1}


def test_json_bodies_are_capped_at_1_mib(api: Api) -> None:
    h = {**api.headers, "Content-Type": "application/json"}
    big = b'{"code": "PD-BIG", "notes": "' + b"x" * 1_100_000 + b'"}'
    r = api.client.post("/api/v1/patients", content=big, headers=h)
    assert r.status_code == 413  # declared length: refused unread
    assert "1024 KiB" in r.json()["detail"]

    def chunked():  # no length announced: cut off while streaming
        for i in range(0, len(big), 65536):
            yield big[i : i + 65536]

    r = api.client.post("/api/v1/patients", content=chunked(), headers=h)
    assert r.status_code == 413
    assert api.client.get("/api/v1/patients", headers=api.headers).json()["total"] == 0


def test_a_session_recorded_in_the_future_is_refused(api: Api) -> None:
    """A session dated 2099 was accepted (a typo, or a date format read the wrong way): it
    would head every list and report. A day of slack for a clock or a zone left out."""
    from datetime import timedelta

    from app.models import RecordingSession, utcnow

    h = api.headers
    patient = api.client.post("/api/v1/patients", json={"code": "PD-F"}, headers=h).json()
    rig = api.client.post("/api/v1/rigs", json={"name": "rig-F"}, headers=h).json()

    def create(when: str):  # type: ignore[no-untyped-def]
        body = {"patient_id": patient["id"], "rig_id": rig["id"], "recorded_at": when}
        return api.client.post("/api/v1/sessions", json=body, headers=h)

    r = create("2099-01-01T09:30:00Z")
    assert r.status_code == 422, r.text
    assert "2099-01-01 09:30 UTC, is more than a day ahead of now" in r.json()["detail"]
    assert r.json()["errors"][0]["loc"] == ["body", "recorded_at"]
    assert api.count(RecordingSession) == 0
    soon = (utcnow() + timedelta(hours=23)).strftime("%Y-%m-%dT%H:%M:%S")  # UTC, no zone
    assert create(soon).status_code == 201
    late = (utcnow() + timedelta(hours=25)).strftime("%Y-%m-%dT%H:%M:%SZ")
    assert create(late).status_code == 422

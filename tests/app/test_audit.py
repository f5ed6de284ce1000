# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""The audit trail: each patient-data route writes exactly one event, with no clinical values."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from api_support import Api, add_result, api, seed_recording_target, trial_files, video_pair  # noqa: F401 - pytest fixtures
from fastapi.routing import iter_route_contexts
from sqlalchemy import func, select

from app.models import AuditEvent, Patient, Result

NOTES = "tremor worse after coffee, lives alone"  # a clinical free text that must never be audited
# API routes that serve no patient data (not audited): rigs and calibrations, who-am-I
# and login/logout (audited as login/logout themselves). A trial's job status is a read
# of the trial (a calibration's job is not audited: no patient data).
NOT_PATIENT_DATA = {
    ("POST", "/api/v1/auth/login"),
    ("POST", "/api/v1/auth/logout"),
    ("GET", "/api/v1/auth/me"),
    ("POST", "/api/v1/rigs"),
    ("GET", "/api/v1/rigs"),
    ("GET", "/api/v1/rigs/{rig_id}"),
    ("POST", "/api/v1/rigs/{rig_id}/calibrations"),
    ("GET", "/api/v1/rigs/{rig_id}/calibrations"),
    ("GET", "/api/v1/calibrations/{calibration_id}"),
    ("GET", "/api/v1/calibrations/{calibration_id}/rig.json"),
    # the audit trail itself (scope audit:read; its reads are audited, see test_audit_trail.py)
    ("GET", "/api/v1/audit"),
}
# Audited like the others, but only an administrator may call them (the key here is not
# one): tests/app/test_revisions.py::test_hide_and_restore_follow_the_roles counts their events.
ADMIN_ONLY = {("POST", "/api/v1/trials/{trial_id}/restore")}
# Only a person with a password signs (an API key cannot): tests/app/test_signatures.py
# counts the events of signing (the re-authentication and the signature).
PERSON_ONLY = {("POST", "/api/v1/sessions/{session_id}/sign")}


@dataclass(frozen=True)
class Case:
    method: str
    route: str  # as declared
    action: str
    resource_type: str
    expect_patient: bool = True


CASES = [
    Case("POST", "/api/v1/patients", "create", "patient"),
    Case("GET", "/api/v1/patients", "list", "patient", expect_patient=False),
    Case("GET", "/api/v1/patients/{patient_id}", "read", "patient"),
    Case("PATCH", "/api/v1/patients/{patient_id}", "update", "patient"),
    Case("DELETE", "/api/v1/patients/{patient_id}", "delete", "patient"),
    Case("GET", "/api/v1/patients/{patient_id}/sessions", "list", "session"),
    Case("POST", "/api/v1/sessions", "create", "session"),
    Case("GET", "/api/v1/sessions", "list", "session"),
    Case("GET", "/api/v1/sessions/{session_id}", "read", "session"),
    Case("PATCH", "/api/v1/sessions/{session_id}", "update", "session"),
    Case("DELETE", "/api/v1/sessions/{session_id}", "delete", "session"),
    Case("GET", "/api/v1/sessions/{session_id}/report.html", "export", "visit_report_html"),
    Case("GET", "/api/v1/sessions/{session_id}/report.pdf", "export", "visit_report_pdf"),
    Case("POST", "/api/v1/sessions/{session_id}/trials", "create", "trial"),
    Case("GET", "/api/v1/sessions/{session_id}/trials", "list", "trial"),
    Case("GET", "/api/v1/trials/{trial_id}", "read", "trial"),
    Case("GET", "/api/v1/jobs/{job_id}", "read", "trial"),
    Case("PATCH", "/api/v1/trials/{trial_id}", "update", "trial"),
    Case("GET", "/api/v1/trials/{trial_id}/result", "read", "result"),
    Case("GET", "/api/v1/trials/{trial_id}/markers.csv", "export", "markers_csv"),
    Case("GET", "/api/v1/trials/{trial_id}/markers.c3d", "export", "c3d_file"),
    Case("GET", "/api/v1/trials/{trial_id}/markers.trc", "export", "trc_file"),
    Case("GET", "/api/v1/trials/{trial_id}/report.html", "export", "report_html"),
    Case("GET", "/api/v1/trials/{trial_id}/report.pdf", "export", "report_pdf"),
    Case("GET", "/api/v1/trials/{trial_id}/fhir", "export", "fhir_bundle"),
    Case("GET", "/api/v1/sessions/{session_id}/signatures", "read", "signature"),
    Case("POST", "/api/v1/trials/{trial_id}/revisions", "create", "revision"),
    Case("GET", "/api/v1/trials/{trial_id}/revisions", "read", "revision"),
    Case("DELETE", "/api/v1/trials/{trial_id}", "delete", "trial"),
]


@pytest.fixture
def world(api: Api, video_pair) -> dict[str, int]:
    seeded = seed_recording_target(api)
    h = api.headers
    r = api.client.patch(f"/api/v1/patients/{seeded.patient_id}", json={"notes": NOTES}, headers=h)
    assert r.status_code == 200
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "left"},
        files=trial_files(*video_pair),
        headers=h,
    )
    assert r.status_code == 201, r.text
    add_result(api, r.json()["id"])
    return {
        "patient_id": seeded.patient_id,
        "rig_id": seeded.rig_id,
        "session_id": seeded.session_id,
        "trial_id": r.json()["id"],
        "job_id": r.json()["job_id"],
    }


def _request(api: Api, case: Case, ids: dict[str, int], video_pair) -> tuple[int, int]:
    """Run one case; returns (status, patient id it concerns)."""
    c, h = api.client, api.headers
    url = case.route.format(**ids)
    if (case.method, case.route) == ("POST", "/api/v1/patients"):
        r = c.post(url, json={"code": "PD-NEW", "notes": NOTES}, headers=h)
        return r.status_code, r.json()["id"]
    if case.method == "PATCH" and case.route == "/api/v1/trials/{trial_id}":
        r = c.patch(url, json={"clinician_rating": 2, "comment": NOTES}, headers=h)
    elif case.method == "PATCH":
        r = c.patch(url, json={"notes": NOTES + " (updated)"}, headers=h)
    elif case.route == "/api/v1/sessions" and case.method == "POST":
        body = {
            "patient_id": ids["patient_id"],
            "rig_id": ids["rig_id"],
            "recorded_at": "2026-04-01T10:00:00Z",
            "notes": NOTES,
            "time_since_levodopa_min": 90,
        }
        r = c.post(url, json=body, headers=h)
    elif case.route == "/api/v1/sessions" and case.method == "GET":
        r = c.get(url, params={"patient_id": ids["patient_id"]}, headers=h)
    elif case.route.endswith("/revisions") and case.method == "POST":
        r = c.post(url, json={"exclude_taps": [0], "reason": NOTES}, headers=h)
    elif case.method == "POST":  # trial upload
        r = c.post(url, data={"hand": "right"}, files=trial_files(*video_pair), headers=h)
    else:
        r = c.request(case.method, url, headers=h)
    return r.status_code, ids["patient_id"]


def test_cases_cover_every_patient_data_route(api: Api) -> None:
    declared = {
        (method, rc.path)
        for rc in iter_route_contexts(api.app.routes)
        if rc.path.startswith("/api/v1/")
        for method in (getattr(rc, "methods", None) or ())
        if method != "HEAD"
    }
    covered = {(c.method, c.route) for c in CASES}
    assert declared - NOT_PATIENT_DATA - ADMIN_ONLY - PERSON_ONLY == covered


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c.method} {c.route}")
def test_each_patient_data_route_writes_exactly_one_audit_event(
    api: Api, world: dict[str, int], video_pair, case: Case
) -> None:
    before = {e.id for e in api.audit_events()}
    status, patient_id = _request(api, case, world, video_pair)
    assert status < 300, status
    new = [e for e in api.audit_events() if e.id not in before]
    assert len(new) == 1, [(e.action, e.resource_type) for e in new]
    event = new[0]
    assert (event.action, event.resource_type, event.outcome) == (
        case.action,
        case.resource_type,
        "success",
    )
    assert event.patient_id == (patient_id if case.expect_patient else None)
    assert event.actor_type == "api_client" and event.actor_id is not None
    assert event.request_id and event.at is not None


def test_audit_rows_hold_no_clinical_values(api: Api, world: dict[str, int], video_pair) -> None:
    for case in CASES:
        if case.route.endswith(("/report.pdf", "/fhir")):
            continue  # slow (PDF rendering) and audited exactly like report.html
        _request(api, case, world, video_pair)
    with api.sessions() as db:
        rows = list(db.scalars(select(AuditEvent)))
        result = db.scalar(select(Result))
    assert len(rows) > len(CASES)
    metric_values = {
        str(v) for v in result.document["metrics"].values() if isinstance(v, float)
    }  # e.g. "2.5", "51.2": none may appear in an audit row
    for row in rows:
        text = " ".join(
            str(getattr(row, col.name)) for col in AuditEvent.__table__.columns if col.name != "at"
        )
        assert "tremor" not in text and "coffee" not in text
        assert not any(v in text.split() for v in metric_values)


def test_failed_lookups_and_refusals_are_audited(api: Api) -> None:
    r = api.client.get("/api/v1/patients/4242", headers=api.headers)
    assert r.status_code == 404
    with api.sessions() as db:
        event = db.scalar(select(AuditEvent).order_by(AuditEvent.id.desc()))
    assert event is not None
    assert (event.action, event.resource_type, event.resource_id, event.outcome) == (
        "read",
        "patient",
        "4242",
        "not_found",
    )


def test_a_failed_change_is_not_audited_as_success(api: Api) -> None:
    h = api.headers
    first = api.client.post("/api/v1/patients", json={"code": "PD-7"}, headers=h)
    assert first.status_code == 201
    r = api.client.post("/api/v1/patients", json={"code": "pd-7"}, headers=h)
    assert r.status_code == 409
    with api.sessions() as db:
        creates = db.scalar(
            select(func.count())
            .select_from(AuditEvent)
            .where(AuditEvent.action == "create", AuditEvent.outcome == "success")
        )
    assert creates == 1


def test_a_duplicate_code_is_audited_as_denied(api: Api) -> None:
    h = api.headers
    first = api.client.post("/api/v1/patients", json={"code": "PD-7"}, headers=h).json()["id"]
    other = api.client.post("/api/v1/patients", json={"code": "PD-8"}, headers=h).json()["id"]
    before = {e.id for e in api.audit_events()}
    assert api.client.post("/api/v1/patients", json={"code": "pd-7"}, headers=h).status_code == 409
    r = api.client.patch(f"/api/v1/patients/{other}", json={"code": "PD-7"}, headers=h)
    assert r.status_code == 409
    new = [e for e in api.audit_events() if e.id not in before]
    assert [(e.action, e.resource_type, e.patient_id, e.outcome, e.actor_type) for e in new] == [
        ("create", "patient", first, "denied", "api_client"),  # the patient holding the code
        ("update", "patient", other, "denied", "api_client"),
    ]
    with api.sessions() as db:
        assert db.get(Patient, other).code == "PD-8"  # the refused change changed nothing


def test_an_update_keeps_what_changed_and_the_rater_changes_with_the_rating_only(
    api: Api, world: dict[str, int]
) -> None:
    """A security review: a colleague's comment fix credited the rating they never touched
    to them, and the trail said "update trial 3" twice: no fields, no previous values.
    The event names the fields (no values: an auditor reads it, it outlives an erasure);
    the previous and new values are kept beside it, sealed by the chain."""
    from api_support import make_user
    from fastapi.testclient import TestClient

    from app.chain import verify_chain

    password = "correct horse battery"
    clients = {}
    for email in ("one@example.org", "two@example.org"):
        user_id = make_user(api.sessions, email, password)
        client = TestClient(api.app)
        r = client.post("/api/v1/auth/login", json={"email": email, "password": password})
        client.headers["X-CSRF-Token"] = r.json()["csrf_token"]
        clients[email] = (client, user_id)
    one, one_id = clients["one@example.org"]
    two, _ = clients["two@example.org"]
    url = f"/api/v1/trials/{world['trial_id']}"
    r = one.patch(url, json={"clinician_rating": 1, "comment": "mild, first rater"})
    assert r.status_code == 200 and r.json()["rated_by_user_id"] == one_id
    rated_at = r.json()["rated_at"]
    r = two.patch(url, json={"comment": "typo fix", "clinician_rating": 1})  # same rating
    assert r.json()["comment"] == "typo fix" and r.json()["clinician_rating"] == 1
    assert (r.json()["rated_by_user_id"], r.json()["rated_at"]) == (one_id, rated_at)
    r = api.client.patch(f"/api/v1/patients/{world['patient_id']}", json={"notes": "new notes"},
                         headers=api.headers)  # fmt: skip
    assert r.status_code == 200
    r = api.client.patch(f"/api/v1/sessions/{world['session_id']}",
                         json={"medication_state": "on", "notes": NOTES}, headers=api.headers)  # fmt: skip
    assert r.status_code == 200

    updates = [e for e in api.audit_events() if e.action == "update"]
    assert [(e.resource_type, e.details["fields"]) for e in updates] == [
        ("patient", ["notes"]),  # the world fixture's
        ("trial", ["clinician_rating", "comment"]),
        ("trial", ["comment"]),
        ("patient", ["notes"]),
        ("session", ["medication_state", "notes"]),
    ]
    for event in updates:  # identifiers and names only in the trail
        assert "typo" not in str(event.details) and "first rater" not in str(event.details)
    trail = api.client.get("/api/v1/audit?limit=100", headers=api.headers).json()["items"]
    kept = {e["id"]: e["changes"] for e in trail if e["action"] == "update"}
    assert [kept[e.id] for e in updates[1:]] == [
        {"clinician_rating": [None, 1], "comment": [None, "mild, first rater"]},
        {"comment": ["mild, first rater", "typo fix"]},
        {"notes": [NOTES, "new notes"]},
        {"medication_state": ["off", "on"], "notes": [None, NOTES]},
    ]
    with api.sessions() as db:
        assert verify_chain(db).ok

"""Reading the trail's kept values names, in the trail, the patients whose values were shown.

A security review: an admin reading ``GET /api/v1/audit`` or ``/admin/audit`` saw the
previous and new values of updates of patients A and B (their notes), and the trail kept
one ``list audit`` event naming neither, so "who saw patient A's data" missed it. Such a
read now adds one ``read field_changes`` event naming A and B, indexed in
``audit_event_patients`` as a list of patients is; a patient whose values were not shown
(C: named by an event on the same page, or an auditor's read without values) is not named.
On SQLite and PostgreSQL.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from api_support import Api, make_api_key, make_user
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.audit_check import verify_trail
from app.db import get_sessionmaker
from app.main import create_app
from app.models import ApiClient, AuditEvent, AuditEventPatient, User
from app.settings import Settings

PASSWORD = "correct horse battery"


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def api_on(request: pytest.FixtureRequest) -> Iterator[Api]:
    name = "app_settings" if request.param == "sqlite" else "pg_settings"
    settings: Settings = request.getfixturevalue(name)
    sessions = get_sessionmaker(settings)
    app = create_app(settings)
    with TestClient(app) as client:
        yield Api(app, client, settings, sessions, make_api_key(sessions))


def _logged_in(api: Api, email: str, role: str) -> tuple[TestClient, int]:
    user_id = make_user(api.sessions, email, PASSWORD, role=role)
    client = TestClient(api.app)
    r = client.post("/api/v1/auth/login", json={"email": email, "password": PASSWORD})
    assert r.status_code == 200, r.text
    client.headers["X-CSRF-Token"] = r.json()["csrf_token"]
    return client, user_id


def _world(api: Api) -> dict[str, int]:
    """Patients A, B (notes changed by the API key) and C (notes changed by a clinician)."""
    ids = {
        name: api.client.post(
            "/api/v1/patients", json={"code": f"PD-{name}"}, headers=api.headers
        ).json()["id"]
        for name in "ABC"
    }
    doc, _ = _logged_in(api, "doc@example.org", "clinician")
    r = doc.patch(f"/api/v1/patients/{ids['C']}", json={"notes": "notes of C"})
    assert r.status_code == 200, r.text
    for name in "AB":
        r = api.client.patch(
            f"/api/v1/patients/{ids[name]}", json={"notes": f"notes of {name}"}, headers=api.headers
        )
        assert r.status_code == 200, r.text
    with api.sessions() as db:
        ids["key"] = int(db.scalars(select(ApiClient.id)).one())
    return ids


def _new_events(api: Api, after: int) -> list[AuditEvent]:
    with api.sessions() as db:
        return list(db.scalars(select(AuditEvent).where(AuditEvent.id > after).order_by("id")))


def _named(api: Api, event_id: int) -> set[int]:
    with api.sessions() as db:
        rows = db.scalars(
            select(AuditEventPatient.patient_id).where(AuditEventPatient.event_id == event_id)
        )
        return set(rows)


def _last_id(api: Api) -> int:
    return max(e.id for e in api.audit_events())


@pytest.mark.parametrize("where", ["api", "page"])
def test_a_read_of_kept_values_names_their_patients_and_only_them(api_on: Api, where: str) -> None:
    api = api_on
    ids = _world(api)
    admin, admin_id = _logged_in(api, "it@example.org", "admin")
    before = _last_id(api)
    # The API key's events: the creates of A, B and C, the updates of A and B.
    if where == "api":
        r = admin.get(f"/api/v1/audit?actor=api_client:{ids['key']}&limit=100")
        assert r.status_code == 200, r.text
        items = r.json()["items"]
        shown = {e["patient_id"] for e in items if e["changes"]}
        assert {e["patient_id"] for e in items} == {ids["A"], ids["B"], ids["C"]}
    else:
        r = admin.get(f"/admin/audit?actor=api_client:{ids['key']}")
        assert r.status_code == 200, r.text
        shown = {ids[n] for n in "ABC" if f"“notes of {n}”" in r.text}
        assert f">patient {ids['C']}<" in r.text  # C's create is on the page, its values are not
    assert shown == {ids["A"], ids["B"]}

    new = _new_events(api, before)
    assert [(e.action, e.resource_type) for e in new] == [
        ("list", "audit"),
        ("read", "field_changes"),
    ]
    values_read = new[1]
    assert values_read.actor_type == "user" and values_read.actor_id == str(admin_id)
    assert values_read.details == {"patient_ids": sorted([ids["A"], ids["B"]])}
    assert _named(api, values_read.id) == {ids["A"], ids["B"]}

    # Who saw A's data: the read is in A's trail (and B's), not in C's.
    for name, expected in (("A", True), ("B", True), ("C", False)):
        trail = api.client.get(
            f"/api/v1/audit?patient_id={ids[name]}&actor=user:{admin_id}", headers=api.headers
        ).json()["items"]
        found = [e for e in trail if e["resource_type"] == "field_changes"]
        assert [e["id"] for e in found] == ([values_read.id] if expected else []), name
    page = admin.get(f"/admin/audit?patient_id={ids['A']}&actor=user:{admin_id}").text
    assert "values of 2 patients shown</summary>" in page
    with api.sessions() as db:
        report = verify_trail(db)
    assert report.ok, report.problems


def test_reads_that_show_no_values_name_nobody(api_on: Api) -> None:
    """An auditor sees field names, not values; an admin's page of events without kept
    values shows none: neither read adds a ``read field_changes`` event."""
    api = api_on
    ids = _world(api)
    auditor, _ = _logged_in(api, "dpo@example.org", "auditor")
    admin, _ = _logged_in(api, "it@example.org", "admin")
    with api.sessions() as db:
        doc_id = db.scalars(select(User.id).where(User.email == "doc@example.org")).one()
    before = _last_id(api)
    r = auditor.get(f"/api/v1/audit?actor=api_client:{ids['key']}")
    assert r.status_code == 200 and all(e["changes"] is None for e in r.json()["items"])
    page = auditor.get(f"/admin/audit?actor=api_client:{ids['key']}")
    assert page.status_code == 200 and "changed notes" in page.text
    assert "notes of A" not in page.text
    r = admin.get(f"/api/v1/audit?actor=user:{doc_id}&until=2000-01-01")
    assert r.status_code == 200 and r.json()["items"] == []
    new = _new_events(api, before)
    assert [(e.action, e.resource_type) for e in new] == [("list", "audit")] * 3
    # The clinician's update of C only: the admin's read names C and nobody else.
    r = admin.get(f"/api/v1/audit?actor=user:{doc_id}")
    assert [e["changes"] for e in r.json()["items"] if e["action"] == "update"] == [
        {"notes": [None, "notes of C"]}
    ]
    values_read = _new_events(api, before)[-1]
    assert values_read.resource_type == "field_changes"
    assert _named(api, values_read.id) == {ids["C"]}

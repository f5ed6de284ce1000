# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""The audit trail you can read and trust (issue 18, finding 10), erasure and retention (11).

- ``GET /api/v1/audit`` (scope ``audit:read``), the admin page, ``export-audit``;
- the hash chain: ``verify-audit`` finds a deleted, an altered and an inserted row,
  on SQLite and on PostgreSQL (the tampering drops the append-only triggers first,
  as a database owner can);
- comparing two trials audits both; rejected uploads are audited;
- ``erase-patient`` and ``apply-retention`` remove the data, keep the audit trail.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from api_support import (
    Api,
    add_result,
    api,  # noqa: F401
    make_api_key,
    make_user,
    seed_recording_target,
    trial_files,
    video_pair,  # noqa: F401
)
from cli_support import admin_cli
from fastapi.testclient import TestClient
from sqlalchemy import func, select, text, update
from sqlalchemy.orm import Session, sessionmaker

from app.audit import audit
from app.chain import verify_chain
from app.db import get_sessionmaker
from app.models import (
    AuditEvent,
    FieldChange,
    Job,
    Patient,
    RecordingSession,
    Result,
    Trial,
    User,
    Video,
    utcnow,
)
from app.settings import Settings

PASSWORD = "correct horse battery"


def _login(client: TestClient, email: str) -> str:
    r = client.post("/api/v1/auth/login", json={"email": email, "password": PASSWORD})
    assert r.status_code == 200, r.text
    return str(r.json()["csrf_token"])


# --------------------------------------------------------------------------- hash chain


def _some_events(sessions: sessionmaker[Session], n: int = 6) -> None:
    with sessions() as db:
        for i in range(n):
            audit(db, None, "read", "patient", i + 1, i + 1)
            db.commit()


def _drop_guards(db: Session) -> None:
    """What a database owner can do: switch the append-only triggers off."""
    if db.get_bind().dialect.name == "postgresql":
        db.execute(text("ALTER TABLE audit_events DISABLE TRIGGER USER"))
    else:
        db.execute(text("DROP TRIGGER audit_events_no_update"))
        db.execute(text("DROP TRIGGER audit_events_no_delete"))


def _tamper(sessions: sessionmaker[Session], how: str) -> None:
    with sessions() as db:
        _drop_guards(db)
        if how == "delete":
            db.execute(text("DELETE FROM audit_events WHERE seq = 3"))
        elif how == "alter":
            db.execute(text("UPDATE audit_events SET patient_id = 99 WHERE seq = 4"))
        elif how == "insert":  # a forged event with a number and a hash that look right
            row = db.execute(text("SELECT * FROM audit_events WHERE seq = 2")).mappings().one()
            db.execute(text("UPDATE audit_events SET seq = seq + 100 WHERE seq >= 3"))
            db.execute(text("UPDATE audit_events SET seq = seq - 99 WHERE seq >= 103"))
            db.execute(
                text(
                    "INSERT INTO audit_events (at, actor_type, actor_id, action, resource_type,"
                    " resource_id, patient_id, outcome, seq, hash) VALUES (:at, 'system', NULL,"
                    " 'read', 'patient', '7', 7, 'success', 3, :hash)"
                ),
                {"at": row["at"], "hash": row["hash"]},
            )
        elif how == "truncate_tail":
            db.execute(
                text("DELETE FROM audit_events WHERE seq = (SELECT max(seq) FROM audit_events)")
            )
        db.commit()


@pytest.mark.parametrize("how", ["delete", "alter", "insert", "truncate_tail"])
def test_verify_audit_finds_tampering_sqlite(
    app_settings: Settings, how: str, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    sessions = get_sessionmaker(app_settings)
    _some_events(sessions)
    assert admin_cli(app_settings, monkeypatch, "verify-audit") == 0
    assert "intact: 6 chained events" in capsys.readouterr().out
    _tamper(sessions, how)
    assert admin_cli(app_settings, monkeypatch, "verify-audit") == 2
    err = capsys.readouterr().err
    assert "tampered with" in err, err


@pytest.mark.postgres
@pytest.mark.parametrize("how", ["delete", "alter", "insert"])
def test_verify_audit_finds_tampering_postgres(pg_settings: Settings, how: str) -> None:
    sessions = get_sessionmaker(pg_settings)
    _some_events(sessions)
    with sessions() as db:
        assert verify_chain(db).ok
    _tamper(sessions, how)
    with sessions() as db:
        report = verify_chain(db)
    assert not report.ok and report.problems, how


def test_concurrent_writers_keep_one_chain(app_settings: Settings) -> None:
    from concurrent.futures import ThreadPoolExecutor

    sessions = get_sessionmaker(app_settings)

    def write(i: int) -> None:
        with sessions() as db:
            audit(db, None, "read", "patient", i, i)
            db.commit()

    with ThreadPoolExecutor(max_workers=8) as pool:
        list(pool.map(write, range(40)))
    with sessions() as db:
        report = verify_chain(db)
        seqs = list(db.scalars(select(AuditEvent.seq).order_by(AuditEvent.seq)))
    assert report.ok, report.problems
    assert seqs == list(range(1, 41))


@pytest.mark.postgres
def test_concurrent_writers_keep_one_chain_postgres(pg_settings: Settings) -> None:
    from concurrent.futures import ThreadPoolExecutor

    sessions = get_sessionmaker(pg_settings)

    def write(i: int) -> None:
        with sessions() as db:
            audit(db, None, "read", "patient", i, i)
            db.commit()

    with ThreadPoolExecutor(max_workers=8) as pool:
        list(pool.map(write, range(40)))
    with sessions() as db:
        report = verify_chain(db)
    assert report.ok and report.chained == 40, report.problems


# --------------------------------------------------------------------------- reading it


def test_the_audit_api_needs_its_scope_and_filters(api: Api) -> None:
    h = api.headers
    p1 = api.client.post("/api/v1/patients", json={"code": "PD-1"}, headers=h).json()["id"]
    p2 = api.client.post("/api/v1/patients", json={"code": "PD-2"}, headers=h).json()["id"]
    api.client.get(f"/api/v1/patients/{p1}", headers=h)
    # a key with the data scopes (create-api-key's default) reads patient data but not the
    # audit trail (before: there was no route at all)
    from app.apikeys import DEFAULT_SCOPES

    data_key = make_api_key(api.sessions, name="data", scopes=DEFAULT_SCOPES)
    r = api.client.get("/api/v1/audit", headers={"Authorization": f"Bearer {data_key}"})
    assert r.status_code == 403 and "audit:read" in r.json()["detail"]
    auditor = {
        "Authorization": f"Bearer {make_api_key(api.sessions, name='auditor', scopes=('audit:read',))}"
    }
    r = api.client.get(f"/api/v1/audit?patient_id={p1}", headers=auditor)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["total"] == 2 and {e["action"] for e in body["items"]} == {"create", "read"}
    assert all(e["patient_id"] == p1 and len(e["hash"]) == 64 for e in body["items"])
    assert body["items"][0]["id"] > body["items"][1]["id"]  # newest first
    everything = api.client.get("/api/v1/audit?limit=2&offset=1", headers=auditor).json()
    assert everything["limit"] == 2 and len(everything["items"]) == 2
    mine = api.client.get("/api/v1/audit?actor=api_client:1", headers=auditor).json()
    assert mine["total"] >= 3 and all(e["actor_id"] == "1" for e in mine["items"])
    future = (utcnow() + timedelta(hours=1)).isoformat()
    assert (
        api.client.get("/api/v1/audit", params={"since": future}, headers=auditor).json()["total"]
        == 0
    )
    past = api.client.get(
        "/api/v1/audit", params={"until": "2000-01-01T00:00:00Z"}, headers=auditor
    )
    assert past.json()["total"] == 0
    assert api.client.get("/api/v1/audit?actor=root", headers=auditor).status_code == 422
    # reading the trail is on the trail
    reads = [e for e in api.audit_events() if e.resource_type == "audit"]
    assert reads and reads[0].patient_id == p1 and reads[0].actor_type == "api_client"
    assert p2


def test_a_list_of_patients_shows_in_each_patients_trail(api: Api) -> None:
    """A security review: GET /patients?limit=200 returned every patient's code, birth
    year, sex and notes, recorded as one "list patient" naming nobody, so no patient's
    trail showed it. The one event names the patients returned; the filter finds it."""
    make_user(api.sessions, "doc@example.org", PASSWORD)
    ids = [
        api.client.post("/api/v1/patients", json={"code": f"PD-{i}"}, headers=api.headers).json()[
            "id"
        ]
        for i in range(3)
    ]
    doc = TestClient(api.app)
    _login(doc, "doc@example.org")
    with api.sessions() as db:
        doc_id = db.scalar(select(User.id).where(User.email == "doc@example.org"))
    assert doc.get("/api/v1/patients?limit=200").status_code == 200
    assert doc.get("/api/v1/patients?q=PD-2").status_code == 200
    assert doc.get("/patients").status_code == 200  # the page, as the API
    listed = [e for e in api.audit_events() if e.action == "list"]
    assert [e.details for e in listed] == [
        {"patient_ids": ids},
        {"patient_ids": [ids[2]]},
        {"patient_ids": ids},
    ]
    for pid, expected in ((ids[0], 2), (ids[2], 3)):
        r = api.client.get(
            f"/api/v1/audit?patient_id={pid}&actor=user:{doc_id}", headers=api.headers
        )
        assert r.json()["total"] == expected, pid
        assert {e["action"] for e in r.json()["items"]} == {"list"}
    r = api.client.get(f"/api/v1/audit?patient_id={ids[0]}", headers=api.headers)
    assert [e["action"] for e in r.json()["items"]][-1] == "create"  # its own events too
    with api.sessions() as db:
        assert verify_chain(db).ok


def test_the_admin_page_shows_the_trail_to_admins_only(api: Api) -> None:
    make_user(api.sessions, "doc@example.org", PASSWORD)
    make_user(api.sessions, "it@example.org", PASSWORD, role="admin")
    api.client.post("/api/v1/patients", json={"code": "PD-7"}, headers=api.headers)
    clinician = TestClient(api.app)
    _login(clinician, "doc@example.org")
    assert clinician.get("/admin/audit").status_code == 403
    assert clinician.get("/api/v1/audit").status_code == 403
    admin = TestClient(api.app)
    _login(admin, "it@example.org")
    page = admin.get("/admin/audit?actor=api_client")
    assert page.status_code == 200
    assert "Audit trail" in page.text and ">create<" in page.text and ">patient 1<" in page.text
    assert admin.get("/api/v1/audit").status_code == 200
    assert 'href="/admin/audit"' in admin.get("/patients").text
    assert 'href="/admin/audit"' not in clinician.get("/patients").text
    # A UI review: the filter took the internal id only, and a bad value replaced the
    # page with an error page leading to the patient list. The code works as the id does;
    # a code or a date that cannot be used is said above the filter, which stays.
    by_code = admin.get("/admin/audit?patient_id=pd-7&actor=api_client")
    by_id = admin.get("/admin/audit?patient_id=1&actor=api_client")
    assert by_code.status_code == by_id.status_code == 200
    assert ">patient 1<" in by_code.text and "1 event," in by_code.text
    assert by_code.text.count("<tr>") == by_id.text.count("<tr>")
    unknown = admin.get("/admin/audit?patient_id=PD-NONE&since=2026-01-31")
    assert unknown.status_code == 422 and "No patient has the code “PD-NONE”" in unknown.text
    assert 'value="PD-NONE"' in unknown.text and 'value="2026-01-31"' in unknown.text
    bad_date = admin.get("/admin/audit?since=yesterday")
    assert bad_date.status_code == 422 and 'value="yesterday"' in bad_date.text


def test_an_auditor_cannot_test_whether_a_patient_code_exists(api: Api) -> None:
    """A security review: an auditor's filter by code answered 200 for a code in use and
    422 "No patient has the code" for one that is not, so an auditor could test codes.
    An auditor filters by id; a code from them gets one answer, held or not."""
    make_user(api.sessions, "dpo@example.org", PASSWORD, role="auditor")
    api.client.post("/api/v1/patients", json={"code": "PD-7"}, headers=api.headers)
    auditor = TestClient(api.app)
    _login(auditor, "dpo@example.org")
    held = auditor.get("/admin/audit?patient_id=PD-7")
    free = auditor.get("/admin/audit?patient_id=PD-NONE")
    assert held.status_code == free.status_code == 422
    assert held.text.replace("PD-7", "CODE") == free.text.replace("PD-NONE", "CODE")
    assert "No patient has the code" not in held.text and "patient&#39;s id" in held.text
    by_id = auditor.get("/admin/audit?patient_id=1")
    assert by_id.status_code == 200 and ">patient 1<" in by_id.text


def test_the_admin_page_shows_what_changed_and_whom_a_list_returned(api: Api) -> None:
    """The page said "update patient 1" and "list patient" where the API told the fields
    changed, their values (to readers of patients' data) and the patients a list returned.
    Each reader now sees on the page what the API shows them: the values to an admin,
    the field names only to an auditor, and every reader the patients of a list."""
    make_user(api.sessions, "it@example.org", PASSWORD, role="admin")
    make_user(api.sessions, "dpo@example.org", PASSWORD, role="auditor")
    h = api.headers
    ids = [api.client.post("/api/v1/patients", json={"code": f"PD-{i}"}, headers=h).json()["id"]
           for i in range(3)]  # fmt: skip
    r = api.client.patch(f"/api/v1/patients/{ids[1]}", json={"notes": "tremor worse at night"},
                         headers=h)  # fmt: skip
    assert r.status_code == 200, r.text
    assert api.client.get("/api/v1/patients?limit=200", headers=h).status_code == 200
    readers = {}
    for email in ("it@example.org", "dpo@example.org"):
        client = TestClient(api.app)
        _login(client, email)
        trail = client.get("/api/v1/audit?limit=100").json()["items"]
        shown = [e["changes"] for e in trail if e["action"] == "update"]
        page = client.get(f"/admin/audit?patient_id={ids[1]}")
        assert page.status_code == 200, page.text
        readers[email] = (shown, page.text, client)
    (api_admin, admin, admin_client), (api_auditor, auditor, _) = readers.values()
    assert api_admin == [{"notes": [None, "tremor worse at night"]}] and api_auditor == [None]
    # the values where the API gives them, and nowhere else
    assert 'notes: <span class="hint">(empty)</span> → “tremor worse at night”' in admin
    assert "tremor worse at night" not in auditor and "changed notes" in auditor
    listed = f"patients {', '.join(map(str, ids))}</span>"
    for html in (admin, auditor):  # the list found by its patient's filter, and whom it named
        assert "3 patients returned</summary>" in html and listed in html
    other = admin_client.get(f"/admin/audit?patient_id={ids[0]}").text
    assert "tremor" not in other and "3 patients returned" in other  # another patient's trail


def test_export_audit_writes_json_lines(api: Api, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    api.client.post("/api/v1/patients", json={"code": "PD-8"}, headers=api.headers)
    assert admin_cli(api.settings, monkeypatch, "export-audit") == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [e["action"] for e in lines][:1] == ["create"] and lines[0]["seq"] == 1
    assert set(lines[0]) >= {"at", "actor_type", "action", "resource_type", "patient_id", "hash"}
    later = (utcnow() + timedelta(minutes=5)).isoformat()
    assert admin_cli(api.settings, monkeypatch, "export-audit", "--since", later) == 0
    assert capsys.readouterr().out == ""
    assert admin_cli(api.settings, monkeypatch, "export-audit", "--since", "yesterday") == 2


def test_comparing_two_trials_audits_both(api: Api, video_pair) -> None:
    seeded = seed_recording_target(api)
    ids = []
    for hand in ("left", "right"):
        r = api.client.post(
            f"/api/v1/sessions/{seeded.session_id}/trials",
            data={"hand": hand},
            files=trial_files(*video_pair),
            headers=api.headers,
        )
        assert r.status_code == 201, r.text
        ids.append(r.json()["id"])
        add_result(api, ids[-1])
    make_user(api.sessions, "doc@example.org", PASSWORD)
    browser = TestClient(api.app)
    _login(browser, "doc@example.org")
    before = len(api.audit_events())
    assert browser.get(f"/trials/{ids[0]}?compare={ids[1]}").status_code == 200
    new = api.audit_events()[before:]
    reads = sorted((e.resource_type, e.resource_id) for e in new if e.action == "read")
    # before: only the first trial's result was audited
    assert reads == [("result", str(ids[0])), ("result", str(ids[1]))]


def test_rejected_uploads_are_audited(api: Api, video_pair) -> None:
    seeded = seed_recording_target(api)
    left, _ = video_pair
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "left"},
        files=trial_files(left, b"not a video at all" * 200),
        headers=api.headers,
    )
    assert r.status_code == 415
    event = api.audit_events()[-1]
    # before: nothing recorded the refused upload
    assert (event.action, event.resource_type, event.outcome, event.patient_id) == (
        "create",
        "trial",
        "invalid",
        seeded.patient_id,
    )
    r = api.client.post(
        f"/api/v1/rigs/{seeded.rig_id}/calibrations",
        files={"rig_json": ("rig.json", b"[" * 50_000, "application/json")},
        headers=api.headers,
    )
    assert r.status_code == 422
    event = api.audit_events()[-1]
    assert (event.resource_type, event.outcome) == ("calibration", "invalid")
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "left"},
        files=trial_files(left, left),
        headers=api.headers,
    )
    assert r.status_code == 422 and "same file" in r.json()["detail"]
    assert api.audit_events()[-1].outcome == "invalid"


# --------------------------------------------------------------------------- erasure, retention


def _patient_with_data(api: Api, video_pair, code: str = "PD-0042") -> tuple[int, list[Path]]:
    seeded = seed_recording_target(api)
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "left"},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    assert r.status_code == 201, r.text
    add_result(api, r.json()["id"])
    api.client.get(f"/api/v1/trials/{r.json()['id']}/result", headers=api.headers)
    rating = {"clinician_rating": 2, "comment": "slowing from the fifth tap"}
    assert api.client.patch(f"/api/v1/trials/{r.json()['id']}", json=rating,
                            headers=api.headers).status_code == 200  # fmt: skip
    with api.sessions() as db:
        paths = [p for p in db.scalars(select(Video.path))] + [
            p for p in db.scalars(select(Result.markers_path)) if p
        ]
    files = [api.settings.data_dir / p for p in paths]
    assert len(files) == 3 and all(f.is_file() for f in files)
    return seeded.patient_id, files


def test_delete_keeps_files_and_erasure_removes_them(
    api: Api, video_pair, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    patient_id, files = _patient_with_data(api, video_pair)
    # DELETE hides the patient and keeps every file (what docs/api.md says)
    assert (
        api.client.delete(f"/api/v1/patients/{patient_id}", headers=api.headers).status_code == 204
    )
    assert all(f.is_file() for f in files)
    events_before = api.audit_events()
    assert api.count(FieldChange) == 1

    assert admin_cli(api.settings, monkeypatch, "erase-patient", "PD-0042") == 0
    assert "erased" in capsys.readouterr().err
    assert not any(f.exists() for f in files)
    assert api.count(Trial) == api.count(Video) == api.count(Result) == api.count(Job) == 0
    assert api.count(RecordingSession) == 0
    assert api.count(FieldChange) == 0  # an update's values are the patient's: erased too
    with api.sessions() as db:
        tombstone = db.get(Patient, patient_id)
        assert tombstone is not None and tombstone.erased_at is not None
        assert "PD-0042" not in tombstone.code and tombstone.notes is None
        assert verify_chain(db).ok
    events = api.audit_events()
    # every earlier event is kept, and the erasure is one more
    assert [e.id for e in events[: len(events_before)]] == [e.id for e in events_before]
    erased = events[-1]
    assert (erased.action, erased.resource_type, erased.patient_id, erased.actor_type) == (
        "erase",
        "patient",
        patient_id,
        "system",
    )
    assert erased.actor_id is not None and erased.actor_id.startswith("cli:")
    # the code stays reserved, and nobody can read it back from the database
    r = api.client.post("/api/v1/patients", json={"code": "pd-0042"}, headers=api.headers)
    assert r.status_code == 409 and "erased" in r.json()["detail"]
    assert admin_cli(api.settings, monkeypatch, "erase-patient", "PD-0042") == 2
    assert "erased already" in capsys.readouterr().err


def test_docs_agree_on_what_deletion_keeps() -> None:
    root = Path(__file__).resolve().parents[2] / "docs"
    operations = (root / "operations.md").read_text(encoding="utf-8")
    api_doc = (root / "api.md").read_text(encoding="utf-8")
    # before: operations.md said files are removed when a record is deleted
    assert "removed when a record is deleted" not in operations
    for doc in (operations, api_doc):
        assert "erase-patient" in doc


def test_retention_erases_only_patients_past_the_period(
    api: Api, video_pair, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    patient_id, files = _patient_with_data(api, video_pair)
    recent = api.client.post("/api/v1/patients", json={"code": "PD-NEW"}, headers=api.headers)
    with api.sessions() as db:  # the old patient's last visit was 11 years ago
        long_ago = datetime(2015, 1, 1, tzinfo=UTC)
        db.execute(update(RecordingSession).values(recorded_at=long_ago))
        db.execute(update(Patient).where(Patient.id == patient_id).values(created_at=long_ago))
        db.commit()
    settings = api.settings.model_copy(update={"retention_days": 3650})
    assert admin_cli(settings, monkeypatch, "apply-retention", "--dry-run") == 0
    assert "1 patient(s) would be erased" in capsys.readouterr().err
    assert all(f.is_file() for f in files)
    assert admin_cli(settings, monkeypatch, "apply-retention") == 0
    assert not any(f.exists() for f in files)
    with api.sessions() as db:
        assert db.get(Patient, patient_id).erased_at is not None
        assert db.get(Patient, recent.json()["id"]).erased_at is None
        kinds = [e.action for e in db.scalars(select(AuditEvent).order_by(AuditEvent.id))]
    assert kinds[-1] == "erase_retention"
    assert admin_cli(api.settings, monkeypatch, "apply-retention") == 2  # no period configured


# --------------------------------------------------------------------------- migration


def test_the_chain_starts_on_a_database_of_the_previous_revision(tmp_path, make_settings) -> None:
    from app.db import dispose_engines, migrate

    settings = make_settings(tmp_path / "data")
    migrate(settings, revision="0009")
    engine = get_sessionmaker(settings).kw["bind"]
    with engine.begin() as conn:  # two events written by the previous version
        for i in (1, 2):
            conn.execute(
                text(
                    "INSERT INTO audit_events (at, actor_type, action, resource_type, outcome)"
                    " VALUES (:at, 'system', 'read', 'patient', 'success')"
                ),
                {"at": f"2026-01-0{i} 10:00:00.000000"},
            )
    dispose_engines()
    migrate(settings)
    sessions = get_sessionmaker(settings)
    _some_events(sessions, 3)
    with sessions() as db:
        report = verify_chain(db)
        assert db.scalar(select(func.count()).select_from(AuditEvent)) == 5
    assert report.ok and report.chained == 3 and report.unchained_before == 2
    dispose_engines()

# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Signed visit reports: re-authentication, unchanged bytes, amendments, roles, restart."""

from __future__ import annotations

import hashlib
import shutil
import subprocess

import pytest
import sqlalchemy as sa
from api_support import Api, api, make_user, video_pair  # noqa: F401 - pytest fixtures
from fastapi.testclient import TestClient
from sqlalchemy import select
from test_revisions import _trial

from app.main import create_app
from app.models import AuditEvent, RecordingSession, Signature, Trial

PASSWORD = "a long clinician passphrase 42"


def _login(client: TestClient, email: str) -> dict[str, str]:
    r = client.post("/api/v1/auth/login", json={"email": email, "password": PASSWORD})
    assert r.status_code == 200, r.text
    return {"X-CSRF-Token": r.json()["csrf_token"]}


def _session_of(api: Api, trial_id: int) -> int:
    with api.sessions() as db:
        return int(db.get(Trial, trial_id).session_id)


def _pdf_text(pdf: bytes, tmp_path) -> str:
    if not shutil.which("pdftotext"):
        pytest.skip("pdftotext (poppler-utils) is not installed")
    path = tmp_path / "signed.pdf"
    path.write_bytes(pdf)
    return subprocess.run(
        ["pdftotext", str(path), "-"], capture_output=True, text=True, check=True
    ).stdout


def test_sign_correct_amend_and_sign_again(api: Api, video_pair, tmp_path) -> None:
    trial_id = _trial(api, video_pair)
    session_id = _session_of(api, trial_id)
    make_user(api.sessions, "dr.sign@example.org", PASSWORD)
    client = TestClient(api.app)
    user = _login(client, "dr.sign@example.org")
    sign = f"/api/v1/sessions/{session_id}/sign"
    signed_pdf = f"/api/v1/sessions/{session_id}/report.pdf?signed=true"

    assert client.get(signed_pdf).status_code == 404  # nothing signed yet
    before = {e.id for e in api.audit_events()}
    wrong = client.post(sign, json={"password": "not it"}, headers=user)
    # 403, not 401: the login stands (a client reads 401 as an expired session)
    assert wrong.status_code == 403 and "password is wrong" in wrong.json()["detail"]
    assert api.count(Signature) == 0
    # An API key cannot sign: signing needs a person's password.
    key = api.client.post(sign, json={"password": PASSWORD}, headers=api.headers)
    assert key.status_code == 403
    first = client.post(sign, json={"password": PASSWORD}, headers=user)
    assert first.status_code == 201, first.text
    one = first.json()
    assert one["number"] == 1 and one["amends_number"] is None
    assert one["signed_by"] == "dr.sign@example.org"
    assert one["trial_revisions"] == {str(trial_id): 1}
    events = [
        (e.action, e.resource_type, e.outcome) for e in api.audit_events() if e.id not in before
    ]
    assert events == [
        ("reauthenticate", "user", "denied"),
        ("sign", "visit", "denied"),
        ("reauthenticate", "user", "success"),
        ("sign", "visit", "success"),
    ]

    pdf1 = client.get(signed_pdf)
    assert pdf1.status_code == 200 and pdf1.content.startswith(b"%PDF")
    assert (
        hashlib.sha256(pdf1.content).hexdigest()
        == one["sha256"]
        == pdf1.headers["x-content-sha256"]
    )
    text = _pdf_text(pdf1.content, tmp_path)
    assert "Electronically signed by dr.sign@example.org" in text
    state = client.get(f"/api/v1/sessions/{session_id}/signatures").json()
    assert state["status"] == "signed" and state["changes"] == []
    again = client.post(sign, json={"password": PASSWORD}, headers=user)
    assert again.status_code == 409 and "nothing changed" in again.json()["detail"]

    # A correction after signing: an amendment is pending; the signed bytes stay.
    r = api.client.post(
        f"/api/v1/trials/{trial_id}/revisions",
        json={"exclude_taps": [1], "reason": "tap 2 was a cough"},
        headers=api.headers,
    )
    assert r.status_code == 201
    state = client.get(f"/api/v1/sessions/{session_id}/signatures").json()
    assert state["status"] == "amendment_pending"
    assert state["changes"] == [f"trial {trial_id} is now at revision 2 (signed: 1)"]
    assert client.get(signed_pdf).content == pdf1.content

    second = client.post(sign, json={"password": PASSWORD}, headers=user)
    assert second.status_code == 201
    two = second.json()
    assert (two["number"], two["amends_number"]) == (2, 1)
    assert two["trial_revisions"] == {str(trial_id): 2} and two["sha256"] != one["sha256"]
    assert client.get(signed_pdf).content != pdf1.content  # the newest by default
    kept = client.get(f"{signed_pdf}&signature=1")
    assert kept.content == pdf1.content  # the first signed report, byte for byte
    assert "an amendment of signature 1" in _pdf_text(client.get(signed_pdf).content, tmp_path)
    assert client.get(f"/api/v1/sessions/{session_id}/signatures").json()["status"] == "signed"

    # Nobody can alter a signature, not even through the database.
    with api.sessions() as db:
        with pytest.raises(sa.exc.DBAPIError, match="signatures cannot be changed"):
            db.execute(sa.update(Signature).values(sha256="0" * 64))
            db.commit()
        db.rollback()

    # Signatures and revisions survive a restart (a new app on the same data).
    with TestClient(create_app(api.settings)) as fresh:
        r = fresh.get(f"{signed_pdf}&signature=1", headers=api.headers)
        assert r.status_code == 200 and r.content == pdf1.content
        doc = fresh.get(f"/api/v1/trials/{trial_id}/result?revision=1", headers=api.headers)
        assert doc.json()["revision"] == 1


def test_a_wrong_password_is_403_and_the_login_stands(api: Api, video_pair) -> None:
    """A 401 reads as an expired session to a client (it would log in again): the
    password typed again to sign is wrong, the login is not."""
    session_id = _session_of(api, _trial(api, video_pair))
    make_user(api.sessions, "dr.sign@example.org", PASSWORD)
    client = TestClient(api.app)
    user = _login(client, "dr.sign@example.org")
    wrong = client.post(
        f"/api/v1/sessions/{session_id}/sign", json={"password": "not it"}, headers=user
    )
    assert wrong.status_code == 403 and "password is wrong" in wrong.json()["detail"]
    assert client.get("/api/v1/auth/me").status_code == 200
    page = client.post(  # the session page's form: its error page says the same
        f"/sessions/{session_id}/sign",
        data={"password": "not it", "csrf_token": user["X-CSRF-Token"]},
        headers={"Accept": "text/html"},
    )
    assert page.status_code == 403 and "The password is wrong" in page.text
    assert api.count(Signature) == 0


def test_only_clinicians_sign(api: Api, video_pair) -> None:
    trial_id = _trial(api, video_pair)
    session_id = _session_of(api, trial_id)
    make_user(api.sessions, "admin@example.org", PASSWORD, role="admin")
    client = TestClient(api.app)
    admin = _login(client, "admin@example.org")
    r = client.post(
        f"/api/v1/sessions/{session_id}/sign", json={"password": PASSWORD}, headers=admin
    )
    assert r.status_code == 403 and "clinician" in r.json()["detail"]
    with api.sessions() as db:
        last = db.scalar(select(AuditEvent).order_by(AuditEvent.id.desc()))
        assert (last.action, last.outcome) == ("sign", "denied")
        assert db.get(RecordingSession, session_id) is not None


def test_a_stored_signed_report_that_was_damaged_is_refused(api: Api, video_pair) -> None:
    trial_id = _trial(api, video_pair)
    session_id = _session_of(api, trial_id)
    make_user(api.sessions, "dr.sign@example.org", PASSWORD)
    client = TestClient(api.app)
    user = _login(client, "dr.sign@example.org")
    r = client.post(
        f"/api/v1/sessions/{session_id}/sign", json={"password": PASSWORD}, headers=user
    )
    assert r.status_code == 201
    with api.sessions() as db:
        path = db.scalar(select(Signature.pdf_path))
    from app.storage import Storage

    stored = Storage.from_settings(api.settings).absolute(path)
    stored.write_bytes(stored.read_bytes() + b"%")
    damaged = client.get(f"/api/v1/sessions/{session_id}/report.pdf?signed=true")
    assert damaged.status_code == 409 and "SHA-256" in damaged.json()["detail"]


def test_revisions_and_signatures_survive_backup_and_restore(
    api: Api, video_pair, tmp_path, monkeypatch, capsys
) -> None:
    from cli_support import admin_cli

    from app.db import dispose_engines

    trial_id = _trial(api, video_pair)
    session_id = _session_of(api, trial_id)
    make_user(api.sessions, "dr.sign@example.org", PASSWORD)
    client = TestClient(api.app)
    user = _login(client, "dr.sign@example.org")
    sign = f"/api/v1/sessions/{session_id}/sign"
    assert client.post(sign, json={"password": PASSWORD}, headers=user).status_code == 201
    r = api.client.post(
        f"/api/v1/trials/{trial_id}/revisions",
        json={"exclude_taps": [3], "reason": "tap 4 was a sneeze"},
        headers=api.headers,
    )
    assert r.status_code == 201
    assert client.post(sign, json={"password": PASSWORD}, headers=user).status_code == 201
    pdf_url = f"/api/v1/sessions/{session_id}/report.pdf?signed=true&signature="
    signed = {n: api.client.get(f"{pdf_url}{n}", headers=api.headers).content for n in (1, 2)}
    results = {
        n: api.client.get(
            f"/api/v1/trials/{trial_id}/result?revision={n}", headers=api.headers
        ).json()
        for n in (1, 2)
    }
    assert admin_cli(api.settings, monkeypatch, "backup", str(tmp_path / "backup")) == 0
    dispose_engines()
    shutil.rmtree(api.settings.data_dir)
    assert admin_cli(api.settings, monkeypatch, "restore", str(tmp_path / "backup")) == 0
    with TestClient(create_app(api.settings)) as fresh:
        for n, body in signed.items():
            r = fresh.get(f"{pdf_url}{n}", headers=api.headers)
            assert r.status_code == 200 and r.content == body  # byte for byte
        for n, doc in results.items():
            r = fresh.get(f"/api/v1/trials/{trial_id}/result?revision={n}", headers=api.headers)
            assert r.json() == doc
        state = fresh.get(f"/api/v1/sessions/{session_id}/signatures", headers=api.headers).json()
        assert state["status"] == "signed" and [s["number"] for s in state["signatures"]] == [1, 2]
    dispose_engines()


def test_erasing_the_patient_removes_the_signed_reports(api: Api, video_pair) -> None:
    """A signature is never changed, but the patient's erasure (issue 18) removes it and its PDF."""
    from app.services.erasure import erase_patient
    from app.storage import Storage

    trial_id = _trial(api, video_pair)
    session_id = _session_of(api, trial_id)
    make_user(api.sessions, "dr.sign@example.org", PASSWORD)
    client = TestClient(api.app)
    user = _login(client, "dr.sign@example.org")
    sign = f"/api/v1/sessions/{session_id}/sign"
    assert client.post(sign, json={"password": PASSWORD}, headers=user).status_code == 201
    storage = Storage.from_settings(api.settings)
    with api.sessions() as db:
        path = db.scalar(select(Signature.pdf_path))
        code = db.get(RecordingSession, session_id).patient.code
        erase_patient(db, storage, None, code)
    with api.sessions() as db:
        assert db.scalar(select(Signature)) is None
    assert not storage.absolute(path).exists()

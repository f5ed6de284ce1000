"""A hidden trial is not a trial that "does not exist": its page, the session page, the
patient page and the visit report say it was hidden, by whom, when and why."""

from __future__ import annotations

import html as html_lib
import re

from sqlalchemy import select
from test_pages import _csrf, client, login, seeded  # noqa: F401 - fixtures

from app.models import AuditEvent, Trial, User
from app.passwords import hash_password

REASON = "recorded with the markers on the wrong fingers"


def _text(html: str) -> str:
    return re.sub(r"\s+", " ", html_lib.unescape(re.sub(r"<[^>]+>", " ", html)))


def _hide(client, db_sessionmaker, trial_id: int) -> tuple[int, int, int]:  # noqa: F811
    """Hide ``trial_id`` from the session page's form, as the clinician; (trial, session,
    patient) ids."""
    csrf = login(client)
    r = client.post(
        f"/trials/{trial_id}/hide",
        data={"csrf_token": csrf, "reason": REASON},
        follow_redirects=False,
    )
    assert r.status_code == 303
    with db_sessionmaker() as db:
        trial = db.get(Trial, trial_id)
        return trial.id, trial.session_id, trial.session.patient_id


def test_a_hidden_trial_says_who_hid_it_when_why_and_how_it_comes_back(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    trial_id, session_id, patient_id = _hide(client, db_sessionmaker, seeded["trials"][(1, "left")])
    with db_sessionmaker() as db:
        since = db.scalar(select(AuditEvent.id).order_by(AuditEvent.id.desc()))
    page = client.get(f"/trials/{trial_id}")
    assert page.status_code == 410  # gone on purpose, not "does not exist"
    text = _text(page.text)
    assert "does not exist" not in text
    assert f"Trial {trial_id} is hidden: finger tapping, left hand, medication on" in text
    assert f"by clinician@example.org. Reason: “{REASON}”" in text
    assert "ask an administrator" in text and 'action="/trials/' not in page.text
    with db_sessionmaker() as db:
        events = db.scalars(select(AuditEvent).where(AuditEvent.id > since)).all()
        assert [(e.action, e.resource_type, e.outcome) for e in events] == [
            ("read", "trial", "success")
        ]

    # The session page keeps the trial's row, struck through, with the reason; the side
    # reads "hidden", not "not recorded".
    session = client.get(f"/sessions/{session_id}").text
    row = re.search(
        rf'<tr class="trial-hidden" data-hidden-trial="{trial_id}">.*?</tr>', session, re.S
    )
    assert row, "no row for the hidden trial"
    assert "<del>left</del>" in row.group(0) and REASON in html_lib.unescape(row.group(0))
    grid = re.search(r'<table class="list task-grid".*?</table>', session, re.S).group(0)
    tapping = re.search(r"<tr>\s*<th scope=\"row\">Finger tapping.*?</tr>", grid, re.S).group(0)
    assert 'data-hidden-side="left"' in tapping and "not recorded" not in tapping
    assert 'action="/trials/' + str(trial_id) + '/restore"' not in session  # not an admin

    # The patient page: "hidden", not an invitation to upload that side.
    patient = client.get(f"/patients/{patient_id}").text
    cells = re.search(rf'<a href="/sessions/{session_id}">.*?</tr>', patient, re.S).group(0)
    assert f'data-hidden-trial="{trial_id}"' in cells and "#upload-left" not in cells

    # The visit report names it, with the reason.
    report = _text(client.get(f"/sessions/{session_id}/visit-report.html").text)
    assert "Hidden trials (not reported)" in report
    with db_sessionmaker() as db:  # the trial's own time (its upload), not the session's
        uploaded = db.get(Trial, trial_id).created_at
    assert (
        f"Trial #{trial_id}: finger tapping, left hand, medication on,"
        f" uploaded {uploaded:%Y-%m-%d %H:%M} UTC — hidden " in report
    )
    assert f"by clinician@example.org: “{REASON}”" in report


def test_an_administrator_restores_a_hidden_trial_from_its_page(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    trial_id, session_id, _ = _hide(client, db_sessionmaker, seeded["trials"][(1, "left")])
    with db_sessionmaker() as db:
        db.add(
            User(
                email="admin@example.org",
                password_hash=hash_password("an administrator's passphrase"),
                role="admin",
            )
        )
        db.commit()
    client.post("/logout", data={"csrf_token": _csrf(client.get("/patients").text)})
    form = client.get("/login").text
    client.post(
        "/login",
        data={
            "email": "admin@example.org",
            "password": "an administrator's passphrase",
            "csrf_token": _csrf(form),
            "next": "/patients",
        },
    )
    page = client.get(f"/trials/{trial_id}").text
    assert f'action="/trials/{trial_id}/restore"' in page
    assert f'action="/trials/{trial_id}/restore"' in client.get(f"/sessions/{session_id}").text
    r = client.post(
        f"/trials/{trial_id}/restore", data={"csrf_token": _csrf(page)}, follow_redirects=False
    )
    assert r.status_code == 303
    with db_sessionmaker() as db:
        assert db.get(Trial, trial_id).deleted_at is None

"""The review view and the record's pages: one audit event each, corrections, hide, edit."""

from __future__ import annotations

import json
import re

from sqlalchemy import select
from test_pages import _audit_count, client, login, seeded  # noqa: F401 - fixtures

from app.models import AuditEvent, RecordingSession, Result, Trial, Video


def _events(db_sessionmaker, since: int) -> list[tuple[str, str, str]]:
    with db_sessionmaker() as db:
        rows = db.scalars(select(AuditEvent).where(AuditEvent.id > since).order_by(AuditEvent.id))
        return [(e.action, e.resource_type, e.outcome) for e in rows]


def _last_event_id(db_sessionmaker) -> int:
    with db_sessionmaker() as db:
        return db.scalar(select(AuditEvent.id).order_by(AuditEvent.id.desc())) or 0


def test_review_view_is_one_audit_event_and_embeds_its_data(client, seeded, db_sessionmaker):  # noqa: F811
    login(client)
    t = seeded["trials"][(1, "right")]
    since = _last_event_id(db_sessionmaker)
    page = client.get(f"/trials/{t}/review")
    assert page.status_code == 200, page.text[:500]
    assert _events(db_sessionmaker, since) == [("read", "review", "success")]
    assert "<script>" not in page.text  # no inline script (CSP): the data block is JSON only
    block = re.search(
        r'<script type="application/json" id="review-data">(.*?)</script>', page.text, re.S
    )
    data = json.loads(block.group(1))
    assert data["revision"] == 1 and data["current"] is True
    assert len(data["signal"]) > 100 and data["taps"] and data["unit"] == "mm"
    assert 'src="/static/review.js"' in page.text
    # A trial without browser copies says so instead of showing a broken player.
    assert "no browser copy" in page.text
    assert client.get(f"/trials/{t}/video/left").status_code == 404
    assert client.get(f"/trials/{t}/review?revision=7").status_code == 404


def test_a_correction_from_the_page_is_a_revision_with_its_reason(client, seeded, db_sessionmaker):  # noqa: F811
    csrf = login(client)
    t = seeded["trials"][(1, "right")]
    form = {"csrf_token": csrf, "kind": "correct", "exclude_taps": ["1", "4"], "reason": ""}
    refused = client.post(f"/trials/{t}/revisions", data=form)
    assert refused.status_code == 422 and "reason" in refused.text.lower()
    since = _last_event_id(db_sessionmaker)
    form["reason"] = "taps 2 and 5 were the patient adjusting the marker"
    r = client.post(f"/trials/{t}/revisions", data=form, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"].startswith(f"/trials/{t}/review")
    assert _events(db_sessionmaker, since) == [("create", "revision", "success")]
    with db_sessionmaker() as db:
        rows = list(
            db.scalars(select(Result).where(Result.trial_id == t).order_by(Result.revision))
        )
        assert [r.revision for r in rows] == [1, 2]
        assert rows[1].document["corrections"]["exclude_taps"] == [1, 4]
        assert rows[1].created_by.startswith("Dr. Test")
    page = client.get(f"/trials/{t}/review").text
    assert "Revision 2</a> <strong>(current)</strong>" in page and "adjusting the marker" in page
    old = client.get(f"/trials/{t}/review?revision=1").text
    assert "not current" in old and 'name="exclude_taps"' not in old  # history is read-only
    trial_page = client.get(f"/trials/{t}").text
    assert "Result revision 2 (current), edited" in trial_page
    assert (
        client.post(f"/trials/{t}/revisions", data={**form, "csrf_token": "x"}).status_code == 403
    )


def test_hide_restore_and_edit_from_the_session_page(client, seeded, db_sessionmaker):  # noqa: F811
    csrf = login(client)
    t = seeded["trials"][(1, "left")]
    with db_sessionmaker() as db:
        session_id = db.get(Trial, t).session_id
    page = client.get(f"/sessions/{session_id}").text
    assert f'action="/trials/{t}/hide"' in page and "Hidden trials" not in page
    assert (
        client.post(f"/trials/{t}/hide", data={"csrf_token": csrf, "reason": ""}).status_code == 422
    )
    since = _last_event_id(db_sessionmaker)
    r = client.post(
        f"/trials/{t}/hide",
        data={"csrf_token": csrf, "reason": "duplicate upload"},
        follow_redirects=False,
    )
    assert r.status_code == 303
    assert _events(db_sessionmaker, since) == [("delete", "trial", "success")]
    assert client.get(f"/trials/{t}").status_code == 410  # says it was hidden, and why
    # A clinician cannot restore it; the refusal is audited.
    since = _last_event_id(db_sessionmaker)
    assert client.post(f"/trials/{t}/restore", data={"csrf_token": csrf}).status_code == 403
    assert _events(db_sessionmaker, since) == [("restore", "trial", "denied")]

    since = _last_event_id(db_sessionmaker)
    r = client.post(
        f"/sessions/{session_id}/edit",
        data={
            "csrf_token": csrf,
            "medication_state": "off",
            "dbs_state": "on",
            "time_since_levodopa_min": "90",
            "more_affected_side": "left",
            "notes": "re-rated after the video review",
        },
        follow_redirects=False,
    )
    assert r.status_code == 303
    assert _events(db_sessionmaker, since) == [("update", "session", "success")]
    with db_sessionmaker() as db:
        s = db.get(RecordingSession, session_id)
        assert (s.medication_state, s.dbs_state) == ("off", "on")
        assert (s.time_since_levodopa_min, s.more_affected_side) == (90, "left")
        assert s.notes == "re-rated after the video review"


def test_sign_from_the_session_page_then_an_amendment_is_pending(client, seeded, db_sessionmaker):  # noqa: F811
    import hashlib

    from test_pages import PASSWORD

    from app.models import Signature

    csrf = login(client)
    t = seeded["trials"][(1, "right")]
    with db_sessionmaker() as db:
        session_id = db.get(Trial, t).session_id
    page = client.get(f"/sessions/{session_id}").text
    assert 'data-signing="unsigned"' in page and f'action="/sessions/{session_id}/sign"' in page
    wrong = client.post(f"/sessions/{session_id}/sign", data={"csrf_token": csrf, "password": "x"})
    assert wrong.status_code == 403 and "The password is wrong" in wrong.text  # login stands
    r = client.post(
        f"/sessions/{session_id}/sign",
        data={"csrf_token": csrf, "password": PASSWORD},
        follow_redirects=False,
    )
    assert r.status_code == 303, r.text[:300]
    page = client.get(f"/sessions/{session_id}").text
    assert 'data-signing="signed"' in page and "Sign the visit report" not in page
    pdf = client.get(f"/sessions/{session_id}/signed/1.pdf")
    with db_sessionmaker() as db:
        sha = db.scalar(select(Signature.sha256))
    assert pdf.status_code == 200 and hashlib.sha256(pdf.content).hexdigest() == sha
    client.post(
        f"/trials/{t}/revisions",
        data={"csrf_token": csrf, "kind": "correct", "exclude_taps": ["0"], "reason": "a cough"},
    )
    page = client.get(f"/sessions/{session_id}").text
    assert 'data-signing="amendment_pending"' in page and "revision 2 (signed: 1)" in page
    assert client.get(f"/sessions/{session_id}/signed/1.pdf").content == pdf.content


def test_a_reanalysis_says_which_corrections_it_did_not_carry_over(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    from app.services import revisions

    csrf = login(client)
    t = seeded["trials"][(1, "right")]
    form = {
        "csrf_token": csrf,
        "kind": "correct",
        "exclude_taps": ["1", "4"],
        "window_start_s": "0.5",
        "window_end_s": "9",
        "reason": "taps 2 and 5 were the patient adjusting the marker",
    }
    r = client.post(f"/trials/{t}/revisions", data=form, follow_redirects=False)
    assert r.status_code == 303, r.text[:500]
    # The worker stores a re-analysis (here: the first analysis's document measured again).
    with db_sessionmaker() as db, db.begin():
        first = db.scalars(select(Result).where(Result.trial_id == t, Result.revision == 1)).one()
        number = revisions.store_analysis(
            db,
            trial_id=t,
            job_id=first.job_id,
            calibration_id=first.calibration_id,
            document=dict(first.document),
            markers_path=first.markers_path,
            overlay_path=first.overlay_path,
            request={"by": "dr", "reason": "a 3-frame offset", "change": {"offset_frames": 3}},
        )
    assert number == 3
    with db_sessionmaker() as db:
        doc = db.scalars(select(Result).where(Result.trial_id == t, Result.revision == 3)).one()
        assert doc.document["corrections_not_carried"] == {
            "exclude_taps": [1, 4],
            "dismiss_pauses": [],
            "window_s": [0.5, 9.0],
            "swap_labels": False,
        }
        assert "corrections" not in doc.document  # nothing of them is applied
    page = client.get(f"/trials/{t}/review")
    notice = re.search(r"<p [^>]*data-not-carried>(.*?)</p>", page.text, re.S)
    assert notice is not None, page.text[:2000]
    assert "taps 2, 5 excluded" in notice.group(1)  # 1-based, as the page numbers them
    assert "analysis window 0.5–9 s" in notice.group(1)
    # A re-analysis of an analysis (no correction in force) says nothing of the kind.
    with db_sessionmaker() as db, db.begin():
        again = revisions.store_analysis(
            db,
            trial_id=t,
            job_id=first.job_id,
            calibration_id=first.calibration_id,
            document=dict(first.document),
            markers_path=first.markers_path,
            overlay_path=first.overlay_path,
        )
    assert again == 4
    assert "data-not-carried" not in client.get(f"/trials/{t}/review").text


def test_the_session_edit_form_names_its_fields_by_their_labels(client, seeded, db_sessionmaker):  # noqa: F811
    """Errors of the edit form use the form's labels, as the new-session form does (issue 14)."""
    csrf = login(client)
    with db_sessionmaker() as db:
        session_id = db.get(Trial, seeded["trials"][(1, "right")]).session_id
    too_long = client.post(
        f"/sessions/{session_id}/edit",
        data={"csrf_token": csrf, "time_since_levodopa_min": "99999"},
    )
    assert too_long.status_code == 422
    assert "the time since the last levodopa dose must be 10080 or less" in too_long.text.lower()
    assert "Time since levodopa min" not in too_long.text  # not the field's internal name
    not_a_number = client.post(
        f"/sessions/{session_id}/edit",
        data={"csrf_token": csrf, "time_since_levodopa_min": "an hour"},
    )
    assert not_a_number.status_code == 422
    assert "Time since the last levodopa dose: give a whole number of minutes" in not_a_number.text


def test_a_video_read_from_its_first_byte_is_audited_once_per_viewing(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
    storage,
):
    """A security review downloaded every trial's videos without a trace: the address
    works without the review page. A request from byte 0 is one ``read video``; the
    player's later range requests of the same viewing are not recorded again."""
    login(client)
    t = seeded["trials"][(1, "right")]
    stored = storage.write_bytes("videos", ".mp4", b"\x00" * 4096)
    with db_sessionmaker() as db:
        trial = db.get(Trial, t)
        db.add(
            Video(trial_id=t, side="left", path=stored.path, size_bytes=4096, sha256="0" * 64,
                  fps=100.0, frame_count=1, width=640, height=512, proxy_path=stored.path)
        )  # fmt: skip
        patient_id = trial.session.patient_id
        db.commit()
    since = _last_event_id(db_sessionmaker)
    assert client.get(f"/trials/{t}/video/left").status_code == 200
    assert client.get(f"/trials/{t}/video/left", headers={"Range": "bytes=0-99"}).status_code == 206
    assert client.get(f"/trials/{t}/video/left", headers={"Range": "bytes=100-"}).status_code == 206
    with db_sessionmaker() as db:
        rows = db.scalars(select(AuditEvent).where(AuditEvent.id > since)).all()
        assert [(e.action, e.resource_type, e.resource_id, e.patient_id) for e in rows] == [
            ("read", "video", f"{t}/left", patient_id)
        ] * 2


HUGE = 9223372036854775808  # one past SQLite's largest integer


def test_page_addresses_with_ids_too_large_for_the_database_are_404_pages(client, seeded):  # noqa: F811
    """A security review found every page route answering 500 with two tracebacks in
    the log for an id past 64 bits (OverflowError in the database driver)."""
    login(client)
    t = seeded["trials"][(1, "right")]
    for url in (
        f"/patients/{HUGE}",
        f"/sessions/{HUGE}",
        f"/jobs/{HUGE}",
        f"/trials/{HUGE}",
        f"/trials/{HUGE}/video/left",
        f"/rigs/{HUGE}",
        f"/sessions/{HUGE}/capture",
        f"/sessions/1/signed/{HUGE}.pdf",
    ):
        r = client.get(url, headers={"Accept": "text/html"})
        assert r.status_code == 404 and "text/html" in r.headers["content-type"], (
            url,
            r.status_code,
        )
    assert client.get(f"/jobs/{HUGE}/status").status_code in (404, 422)
    r = client.get(f"/trials/{t}?compare={HUGE}")
    assert r.status_code == 200 and "choose a trial from the list" in r.text
    assert client.get(f"/patients?page={HUGE}").status_code == 200


def test_requests_refused_for_a_missing_csrf_token_are_audited(client, seeded, db_sessionmaker):  # noqa: F811
    """A forged request is refused (403); a security review found no trace of it in the
    trail. Pages' forms, their uploads and the API called with the cookie: one
    ``access route PATH denied`` each."""
    login(client)
    t = seeded["trials"][(1, "right")]
    since = _last_event_id(db_sessionmaker)
    posts = [
        (f"/trials/{t}/rating", {"data": {"clinician_rating": "2"}}),
        ("/patients", {"data": {"code": "FORGED-1"}}),
        ("/rigs/1/calibrations", {"files": {"left": ("l.mp4", b"x")}}),
        ("/api/v1/patients", {"json": {"code": "FORGED-2"}}),
    ]
    for url, body in posts:
        r = client.post(url, **body)
        assert r.status_code == 403, (url, r.status_code)
    with db_sessionmaker() as db:
        rows = db.scalars(
            select(AuditEvent).where(AuditEvent.id > since, AuditEvent.action == "access")
        ).all()
        assert [(e.resource_type, e.resource_id, e.outcome) for e in rows] == [
            ("route", url, "denied") for url, _ in posts
        ]


def test_every_download_from_the_trial_page_is_an_export(client, seeded, db_sessionmaker):  # noqa: F811
    """The JSON download was recorded as a read of the result, the other files as exports."""
    login(client)
    t = seeded["trials"][(1, "right")]
    for kind in ("json", "csv", "fhir"):
        since = _last_event_id(db_sessionmaker)
        assert client.get(f"/trials/{t}/download/{kind}").status_code == 200, kind
        assert [e[0] for e in _events(db_sessionmaker, since)] == ["export"], kind


def test_an_auditor_reads_the_audit_trail_and_nothing_of_the_patients(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    """A security review: an admin is the only one who reads the trail, and an admin reads
    every patient's data too; and the pages checked no scope at all. An auditor's login
    opens the trail only; every clinical page refuses it (403, audited)."""
    from api_support import make_user
    from test_pages import _csrf

    make_user(db_sessionmaker, "dpo@example.org", "tidal mirror lantern oak", role="auditor")
    page = client.get("/login")
    r = client.post(
        "/login",
        data={"email": "dpo@example.org", "password": "tidal mirror lantern oak",
              "csrf_token": _csrf(page.text), "next": "/patients"},
        follow_redirects=False,
    )  # fmt: skip
    assert r.status_code == 303 and r.headers["location"] == "/admin/audit"
    trail = client.get("/admin/audit")
    assert trail.status_code == 200 and 'href="/patients"' not in trail.text.split("<main")[0]
    t = seeded["trials"][(1, "right")]
    since = _last_event_id(db_sessionmaker)
    for url in ("/patients", f"/patients/{seeded['patient_id']}", f"/trials/{t}", "/rigs",
                f"/trials/{t}/download/csv", "/jobs/1/status"):  # fmt: skip
        r = client.get(url)
        assert r.status_code == 403, (url, r.status_code)
        assert "PD-0042" not in r.text, url
    token = _csrf(trail.text)
    with db_sessionmaker() as db:
        session_id = db.get(Trial, t).session_id
    r = client.post("/patients", data={"code": "AUD-1", "csrf_token": token})
    assert r.status_code == 403
    r = client.post(
        f"/sessions/{session_id}/trials",
        data={"csrf_token": token, "hand": "left"},
        files={"left_video": ("l.mp4", b"x"), "right_video": ("r.mp4", b"y")},
        headers={"Accept": "application/json"},
    )
    assert r.status_code == 403, r.text
    refused = [e for e in _events(db_sessionmaker, since) if e != ("list", "audit", "success")]
    assert refused == [("access", "route", "denied")] * 8
    assert client.get("/api/v1/patients").status_code == 403


def test_a_logged_in_auditors_home_is_the_audit_trail(client, seeded, db_sessionmaker):  # noqa: F811
    """A security review: a logged-in auditor going to / or /login was sent to /patients,
    a 403 page and a denial in the trail; their home is the audit trail."""
    from api_support import make_user
    from test_pages import _csrf

    make_user(db_sessionmaker, "dpo@example.org", "tidal mirror lantern oak", role="auditor")
    page = client.get("/login")
    r = client.post(
        "/login",
        data={"email": "dpo@example.org", "password": "tidal mirror lantern oak",
              "csrf_token": _csrf(page.text)},
        follow_redirects=False,
    )  # fmt: skip
    assert r.headers["location"] == "/admin/audit"
    since = _last_event_id(db_sessionmaker)
    for url in ("/", "/login", "/login?next=/patients/1"):
        r = client.get(url, follow_redirects=False)
        assert r.status_code == 303 and r.headers["location"] == "/admin/audit", url
    assert _events(db_sessionmaker, since) == []  # no refusal recorded
    client.cookies.clear()
    assert client.get("/", follow_redirects=False).headers["location"] == "/patients"
    login(client)
    assert client.get("/", follow_redirects=False).headers["location"] == "/patients"


def test_a_storage_fault_under_a_form_posted_without_script_is_the_error_page(
    client,  # noqa: F811
    seeded,  # noqa: F811
    monkeypatch,
):
    """An operations review: a form posted without JavaScript on a full disk got the
    507 as raw JSON, where every other refusal of a page is the site's error page."""
    import errno

    from app.services import patients

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(patients, "create_patient", full)
    token = login(client)
    r = client.post(
        "/patients", data={"code": "PD-9", "csrf_token": token}, headers={"Accept": "text/html"}
    )
    assert r.status_code == 507 and r.headers["content-type"].startswith("text/html")
    assert "storage is full" in r.text
    api = client.post(
        "/api/v1/patients", json={"code": "PD-9"},
        headers={"X-CSRF-Token": token, "Accept": "text/html"},
    )  # fmt: skip
    assert api.status_code == 507 and "storage is full" in api.json()["detail"]


def test_a_failed_trial_s_reason_and_retries_have_a_row_of_their_own(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    """A UI review: a failed trial's 17-line error sat in its Status cell and two retry
    forms, each with a field named only "Reason", in its Open cell (768 px)."""
    from app.models import Job

    login(client)
    t = seeded["trials"][(1, "left")]
    error = "The videos look swapped: check the frame offset or retry with them exchanged."
    with db_sessionmaker() as db:
        trial = db.get(Trial, t)
        db.add(Job(kind="analyze_trial", trial_id=t, status="failed", error=error))
        session_id = trial.session_id
        db.commit()
    page = client.get(f"/sessions/{session_id}").text
    row = re.search(rf'<tr class="trial-failure" data-failure="{t}">(.*?)</tr>', page, re.S)
    assert row is not None
    assert f"Why the last measurement failed: {error}" in row.group(1)  # it has a result
    assert 'data-retry="swap_cameras"' in row.group(1) and 'data-retry="offset"' in row.group(1)
    assert "Reason for the retry with swapped cameras</label>" in row.group(1)
    assert "Reason for the retry with offset K</label>" in row.group(1)


def test_a_failed_calibration_is_headed_as_failed_not_as_valid(client, seeded, db_sessionmaker):  # noqa: F811
    """A UI review: a failed calibration was headed "Version 2 — valid from ...", and its
    error was an alert announced at every visit of the rig page."""
    from datetime import UTC, datetime

    from app.models import Calibration, Job

    login(client)
    with db_sessionmaker() as db:
        cal = Calibration(rig_id=seeded["rig_id"], version=2, source="board_videos",
                          status="pending", valid_from=datetime(2026, 3, 1, tzinfo=UTC))  # fmt: skip
        db.add(cal)
        db.flush()
        db.add(Job(kind="calibrate", calibration_id=cal.id, status="failed",
                   error="The board was found in 0 of 40 left frames."))  # fmt: skip
        cal.status = "failed"
        db.commit()
    page = client.get(f"/rigs/{seeded['rig_id']}").text
    assert "Version 2 — failed: not used for any recording" in page
    assert "Version 2 — valid from" not in page
    assert 'role="alert">The board was found' not in page and "The board was found" in page


def test_the_review_heading_names_the_medication_state_dbs_and_time(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    """Two reviews of the same hand, off and on medication, are told apart by their heading."""
    login(client)
    off, on = seeded["trials"][(0, "right")], seeded["trials"][(1, "right")]
    with db_sessionmaker() as db:
        db.get(Trial, on).session.dbs_state = "on"
        db.commit()
    headings = {}
    for t, med in ((off, "off"), (on, "on")):
        page = client.get(f"/trials/{t}/review").text
        h1 = re.sub(r"<[^>]+>", "", re.search(r"<h1>(.*?)</h1>", page, re.S).group(1))
        crumbs = re.sub(r"<[^>]+>", "", re.search(r'<nav class="crumbs".*?</nav>', page).group(0))
        assert f"right hand, medication {med}" in h1, h1
        assert f"right hand, medication {med}" in crumbs, crumbs
        with db_sessionmaker() as db:  # the trial's own time (its upload), as the reports
            uploaded = db.get(Trial, t).created_at
        assert f"uploaded {uploaded:%Y-%m-%d %H:%M} UTC (trial #{t})" in h1, h1
        assert f"medication {med}" in re.search(r"<title>(.*?)</title>", page).group(1)
        headings[med] = h1
    assert "DBS on" in headings["on"] and "DBS" not in headings["off"]  # "none": not said
    assert headings["off"] != headings["on"]


def _text(html: str) -> str:
    return " ".join(re.sub(r"<[^>]+>", " ", html).split())


def test_two_trials_of_a_session_are_headed_by_their_own_time_on_their_pages(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
    monkeypatch,
):
    """The trial page said the session's start as "Recorded" and the review page headed
    the trial with it, while the reports name each trial by its upload: two takes of a
    visit read alike. Both pages now say the trial's own time (the reports' trial_time);
    the session's time stays, named as the session's."""
    import dataclasses
    from datetime import UTC, datetime

    from app.services import results as results_service
    from app.services import review as review_service

    login(client)
    left, right = seeded["trials"][(1, "left")], seeded["trials"][(1, "right")]
    session_at = datetime(2025, 3, 1, 9, tzinfo=UTC)  # the seeded session of both
    with db_sessionmaker() as db:
        db.get(Trial, left).created_at = datetime(2025, 3, 1, 9, 2, tzinfo=UTC)
        db.get(Trial, right).created_at = datetime(2025, 3, 1, 9, 7, tzinfo=UTC)
        db.commit()
        assert db.get(Trial, left).session_id == db.get(Trial, right).session_id

    def h1(page: str) -> str:
        return _text(re.search(r"<h1>(.*?)</h1>", page, re.S).group(1))

    for t, minute in ((left, 2), (right, 7)):
        own = f"uploaded 2025-03-01 09:{minute:02d} UTC"
        trial_page = _text(client.get(f"/trials/{t}").text)
        assert f"Trial #{t}, {own} Session {session_at:%Y-%m-%d %H:%M} UTC" in trial_page
        assert "Recorded" not in trial_page
        review = client.get(f"/trials/{t}/review").text
        assert f", {own} (trial #{t})" in h1(review), h1(review)
        crumbs = _text(re.search(r'<nav class="crumbs".*?</nav>', review).group(0))
        assert "Session 2025-03-01 09:00 UTC" in crumbs  # the session's time, as such

    # No stored trial lacks its upload time (trials.created_at is NOT NULL); a page given
    # none says the session's time, as the reports do, with no "uploaded".
    load, reviewed = results_service.load_report_data, review_service.review_page
    monkeypatch.setattr(
        results_service,
        "load_report_data",
        lambda *a, **k: dataclasses.replace(load(*a, **k), uploaded_at=None),
    )
    monkeypatch.setattr(
        review_service,
        "review_page",
        lambda *a, **k: dataclasses.replace(reviewed(*a, **k), uploaded_at=None),
    )
    trial_page = _text(client.get(f"/trials/{left}").text)
    assert f"Trial #{left}, 2025-03-01 09:00 UTC Session 2025-03-01 09:00 UTC" in trial_page
    review = h1(client.get(f"/trials/{left}/review").text)
    assert f", 2025-03-01 09:00 UTC (trial #{left})" in review and "uploaded" not in review


def test_the_review_form_swaps_the_cameras_and_undoes_it(client, seeded, db_sessionmaker):  # noqa: F811
    """The re-analysis form says how the newest analysis measured the two videos and
    measures them the chosen way: swapped, and back as uploaded (the form could only ask
    for a swap, so a swap made by mistake could not be undone in the browser)."""
    from app.models import Job

    csrf = login(client)
    t = seeded["trials"][(1, "right")]

    def form(how: str) -> dict[str, str]:
        return {"csrf_token": csrf, "kind": "reanalyse", "swap_cameras": how, "reason": "check"}

    page = client.get(f"/trials/{t}/review").text
    assert re.search(r'value="as-stored" checked', page) and 'value="swapped" checked' not in page
    r = client.post(f"/trials/{t}/revisions", data=form("swapped"), follow_redirects=False)
    assert r.status_code == 303, r.text[:500]
    with db_sessionmaker() as db, db.begin():
        job = db.scalars(select(Job).where(Job.trial_id == t).order_by(Job.id.desc())).first()
        assert job.payload["swap_cameras"] is True
        job.status = "succeeded"  # as if the worker had measured them swapped:
        newest = db.scalars(select(Result).where(Result.trial_id == t)).all()[-1]
        newest.document = {**newest.document, "cameras_swapped": True}
    page = client.get(f"/trials/{t}/review").text
    assert 'value="swapped" checked' in page  # the form starts where the analysis is
    r = client.post(f"/trials/{t}/revisions", data=form("as-stored"), follow_redirects=False)
    assert r.status_code == 303, r.text[:500]
    with db_sessionmaker() as db:
        job = db.scalars(select(Job).where(Job.trial_id == t).order_by(Job.id.desc())).first()
        assert "swap_cameras" not in job.payload  # measured as uploaded
        assert job.payload["revision_request"]["change"] == {"swap_cameras": False}


def _failed_trial(db_sessionmaker, session_of: int, error: str) -> int:
    """A trial of the session of trial ``session_of`` whose first analysis failed."""
    from app.models import Job

    with db_sessionmaker() as db, db.begin():
        trial = Trial(session_id=db.get(Trial, session_of).session_id, hand="left", status="failed")
        db.add(trial)
        db.flush()
        db.add(Job(kind="analyze_trial", trial_id=trial.id, status="failed", error=error))
        return trial.id


def test_a_failed_trial_is_measured_again_from_its_page(client, seeded, db_sessionmaker):  # noqa: F811
    """Finding 4 of the failure review: a trial whose analysis failed (cameras uploaded the
    wrong way round) offered only "upload it again", and its review page said to wait. Its
    page offers the review page's re-analysis form; the review page says it failed."""
    from app.models import Job

    csrf = login(client)
    error = "the two cameras do not agree; check that the videos are not swapped."
    t = _failed_trial(db_sessionmaker, seeded["trials"][(1, "right")], error)
    page = client.get(f"/trials/{t}").text
    assert "The analysis could not be completed." in page and error in page
    form = re.search(
        r'<form method="post" action="/trials/(\d+)/revisions">(.*?)</form>', page, re.S
    )
    assert form is not None and form.group(1) == str(t)
    fields = form.group(2)
    assert 'name="kind" value="reanalyse"' in fields and 'name="offset_frames"' in fields
    assert "Measure them with the cameras swapped" in fields
    assert re.search(r'<textarea id="reason-2" name="reason"[^>]* required', fields)
    assert " checked" not in fields  # nothing measured yet: the clinician chooses the way

    r = client.post(
        f"/trials/{t}/revisions",
        data={"csrf_token": csrf, "kind": "reanalyse", "swap_cameras": "swapped",
              "reason": "uploaded the wrong way round"},
        follow_redirects=False,
    )  # fmt: skip
    assert r.status_code == 303 and r.headers["location"].startswith("/jobs/"), r.text[:500]
    with db_sessionmaker() as db:
        job = db.scalars(select(Job).where(Job.trial_id == t).order_by(Job.id.desc())).first()
        assert (job.status, job.payload["swap_cameras"]) == ("queued", True)
        job.status, job.error = "failed", error  # as if it failed again
        db.get(Trial, t).status = "failed"
        db.commit()

    review = client.get(f"/trials/{t}/review")
    assert review.status_code == 409
    assert f"The analysis of trial {t} failed: {error.rstrip('.')}" in review.text
    assert "wait for its analysis" not in review.text and f"/trials/{t}" in review.text


def test_a_review_says_which_camera_s_video_is_unavailable_and_why(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
    storage,
):
    """Finding 9 of the failure review: the disk filled while the right video's browser copy
    was written; the review showed the left player alone, saying nothing."""
    login(client)
    t = seeded["trials"][(1, "right")]
    why = "cannot write a browser copy of 3f2a.mp4: No space left on device"
    with db_sessionmaker() as db, db.begin():
        for side in ("left", "right"):
            stored = storage.write_bytes("videos", ".mp4", b"original " + side.encode()).path
            proxy = (
                storage.write_bytes("proxies", ".mp4", b"proxy").path if side == "left" else None
            )
            db.add(
                Video(trial_id=t, side=side, path=stored, proxy_path=proxy,
                      size_bytes=10, sha256=side[0] * 64, fps=60.0, frame_count=600,
                      width=640, height=512)
            )  # fmt: skip
        result = db.get(Trial, t).result
        quality = dict(result.document.get("quality") or {})
        quality["warnings"] = [f"the right video cannot be shown in the review view: {why}"]
        result.document = {**result.document, "quality": quality}
    page = client.get(f"/trials/{t}/review").text
    assert 'data-video="left"' in page and 'data-video="right"' not in page
    notice = re.search(
        r'<p class="notice" role="status" data-missing-video="right">(.*?)</p>', page
    )
    assert notice is not None and 'data-missing-video="left"' not in page
    said = notice.group(1).replace("&#39;", "'")
    assert said.startswith(
        f"The right camera's video cannot be shown: its browser copy could not be written ({why})."
    )
    assert "“Measure again” below makes it again" in said

    with db_sessionmaker() as db, db.begin():  # the left proxy lost from the data directory
        left = db.scalars(select(Video).where(Video.trial_id == t, Video.side == "left")).one()
        storage.delete(left.proxy_path)
    page = client.get(f"/trials/{t}/review").text
    assert 'data-video="left"' not in page
    assert re.search(
        r'data-missing-video="left">The left camera.{1,6}s video cannot be shown: its browser copy'
        r" is missing from the data directory\.",
        page,
    )
    assert "measured before the review view existed" not in page

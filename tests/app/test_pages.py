"""Browser pages over a real migrated SQLite database, with a stored result.

The result here is the synthetic trial of ``sample_trial`` stored as the
worker would store it (a Result row and a markers.csv file), so that the pages
are tested without running the pipeline; ``tests/browser`` runs the real one.
"""

from __future__ import annotations

import re
from datetime import UTC, datetime

import pytest
from fastapi.testclient import TestClient
from sample_trial import synthetic_trial
from sqlalchemy import func, select

from app.models import (
    AuditEvent,
    Calibration,
    Job,
    Patient,
    RecordingSession,
    Result,
    Rig,
    Trial,
    User,
)
from app.passwords import hash_password
from core.markers_csv import markers_csv_text

EMAIL = "clinician@example.org"
PASSWORD = "correct horse battery staple"


def _rig_doc() -> dict:
    from core.camera import ImageSize, rig_to_dict
    from core.simulation.rig import default_rig

    return rig_to_dict(default_rig(image_size=ImageSize(640, 512)))


@pytest.fixture
def seeded(app_settings, db_sessionmaker, storage):
    """A clinician, a rig with a calibration, a patient with two sessions and three results."""
    with db_sessionmaker() as db:
        user = User(
            email=EMAIL,
            password_hash=hash_password(PASSWORD),
            role="clinician",
            display_name="Dr. Test",
        )
        rig = Rig(name="clinic-A")
        db.add_all([user, rig])
        db.flush()
        cal = Calibration(
            rig_id=rig.id,
            version=1,
            valid_from=datetime(2024, 1, 1, tzinfo=UTC),
            rig_json=_rig_doc(),
            rms_px=0.21,
            quality={"rms_px": 0.21},
            source="rig_file",
            status="ready",
        )
        patient = Patient(code="PD-0042")
        db.add_all([cal, patient])
        db.flush()
        trials = {}
        for i, (when, med) in enumerate(
            [
                (datetime(2024, 3, 1, 9, tzinfo=UTC), "off"),
                (datetime(2025, 3, 1, 9, tzinfo=UTC), "on"),
            ]
        ):
            s = RecordingSession(
                patient_id=patient.id,
                rig_id=rig.id,
                recorded_at=when,
                medication_state=med,
                dbs_state="none",
                clinician_user_id=user.id,
            )
            db.add(s)
            db.flush()
            for hand in ("left", "right") if i == 1 else ("right",):
                markers, result = synthetic_trial(amplitude0_mm=52.0 - 5 * i, seed=i)
                stored = storage.write_bytes("results", ".csv", markers_csv_text(markers).encode())
                trial = Trial(
                    session_id=s.id,
                    hand=hand,
                    status="succeeded",
                    clinician_rating=2 if hand == "right" else None,
                )
                db.add(trial)
                db.flush()
                job = Job(
                    kind="analyze_trial",
                    trial_id=trial.id,
                    status="succeeded",
                    progress=1.0,
                    stage="metrics",
                )
                db.add(job)
                db.flush()
                db.add(
                    Result(
                        trial_id=trial.id,
                        job_id=job.id,
                        calibration_id=cal.id,
                        document=result,
                        markers_path=stored.path,
                    )
                )
                trials[(i, hand)] = trial.id
        db.commit()
        return {"patient_id": patient.id, "rig_id": rig.id, "trials": trials}


@pytest.fixture
def client(app_settings):
    from app.main import create_app

    with TestClient(create_app(app_settings)) as c:
        yield c


def _csrf(html: str) -> str:
    match = re.search(r'name="csrf_token" value="([^"]+)"', html)
    assert match, "the page has no CSRF field"
    return match.group(1)


def login(client) -> str:
    page = client.get("/login")
    assert page.status_code == 200
    r = client.post(
        "/login",
        data={
            "email": EMAIL,
            "password": PASSWORD,
            "csrf_token": _csrf(page.text),
            "next": "/patients",
        },
        follow_redirects=False,
    )
    assert r.status_code == 303, r.text
    assert r.headers["location"] == "/patients"
    return _csrf(client.get("/patients").text)


def _audit_count(db_sessionmaker) -> int:
    with db_sessionmaker() as db:
        return db.scalar(select(func.count()).select_from(AuditEvent)) or 0


def _svg_count(html: str) -> int:
    return len(re.findall(r"<svg[^>]*data-plot=", html))


def test_every_page_needs_a_login(client, seeded):
    t = seeded["trials"][(1, "right")]
    for path in [
        "/patients",
        f"/patients/{seeded['patient_id']}",
        f"/patients/{seeded['patient_id']}/sessions/new",
        "/sessions/1",
        f"/trials/{t}",
        f"/trials/{t}/download/pdf",
        "/jobs/1",
        "/rigs",
        f"/rigs/{seeded['rig_id']}",
    ]:
        r = client.get(path, follow_redirects=False)
        assert r.status_code == 303, path
        assert r.headers["location"].startswith("/login?next="), path
        assert "PD-0042" not in r.text
    assert client.get("/jobs/1/status").status_code == 401
    r = client.post("/patients", data={"code": "X-1"}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"].startswith("/login")


def test_login_rejects_a_wrong_password_and_a_missing_form_token(client, seeded):
    page = client.get("/login")
    r = client.post(
        "/login", data={"email": EMAIL, "password": "wrong", "csrf_token": _csrf(page.text)}
    )
    assert r.status_code == 401
    assert "wrong" in r.text and 'type="password"' in r.text
    r = client.post("/login", data={"email": EMAIL, "password": PASSWORD, "csrf_token": "forged"})
    assert r.status_code == 403
    assert client.get("/patients", follow_redirects=False).status_code == 303  # still logged out


def test_login_next_is_kept_on_site(client, seeded):
    page = client.get("/login")
    r = client.post(
        "/login",
        data={
            "email": EMAIL,
            "password": PASSWORD,
            "csrf_token": _csrf(page.text),
            "next": "https://evil.example/",
        },
        follow_redirects=False,
    )
    assert r.headers["location"] == "/patients"


def test_patient_list_search_and_create(client, seeded, db_sessionmaker):
    token = login(client)
    before = _audit_count(db_sessionmaker)
    r = client.get("/patients?q=0042")
    assert r.status_code == 200 and "PD-0042" in r.text
    assert _audit_count(db_sessionmaker) == before + 1  # one event for the page
    empty = client.get("/patients?q=nobody").text
    assert 'href="/patients/' not in empty and "No patient code contains" in empty
    r = client.post(
        "/patients", data={"code": "PD-0100", "csrf_token": token}, follow_redirects=False
    )
    assert r.status_code == 303 and r.headers["location"].startswith("/patients/")
    page = client.get(r.headers["location"])
    assert "Patient PD-0100" in page.text and "No sessions yet" in page.text
    # Duplicate code: a clear message, status 409, nothing created.
    r = client.post("/patients", data={"code": "PD-0100", "csrf_token": token})
    assert r.status_code == 409 and "exists already" in r.text
    # A value out of range is said in words, named by the form's label, not pydantic's
    # "Input should be greater than or equal to 1900"; the same for every page form.
    for year, words in (("1850", "1900 or later"), ("2150", "2100 or earlier")):
        r = client.post("/patients", data={"code": "PD-7", "birth_year": year, "csrf_token": token})
        assert r.status_code == 422 and f"The birth year must be {words}." in r.text, year
        assert "Input should" not in r.text and "greater than or equal" not in r.text
    r = client.post("/patients", data={"code": "-x", "csrf_token": token})
    assert r.status_code == 422 and "The patient code must use letters, digits" in r.text
    # Without the CSRF token nothing is created.
    r = client.post("/patients", data={"code": "PD-0101"})
    assert r.status_code == 403
    with db_sessionmaker() as db:
        assert (
            db.scalar(select(func.count()).select_from(Patient).where(Patient.code == "PD-0101"))
            == 0
        )


def test_patient_page_shows_sessions_and_trend_plots(client, seeded, db_sessionmaker):
    login(client)
    before = _audit_count(db_sessionmaker)
    r = client.get(f"/patients/{seeded['patient_id']}")
    assert r.status_code == 200
    assert _audit_count(db_sessionmaker) == before + 1
    html = r.text
    assert (
        html.count('data-plot="trend"') == 5
    )  # amplitude, frequency, velocity, decrement, hesitations
    assert "right, off" in html and "right, on" in html and "left, on" in html
    assert "2024-03-01" in html and "2025-03-01" in html


def test_new_session_form_and_creation(client, seeded, db_sessionmaker):
    token = login(client)
    pid = seeded["patient_id"]
    form = client.get(f"/patients/{pid}/sessions/new").text
    for field in ("rig_id", "recorded_at", "time_since_levodopa_min", "notes"):
        assert f'for="{field}"' in form, field  # every field is labelled
    assert "<legend>Medication state</legend>" in form
    assert (
        "<legend>More affected side</legend>" in form and "<legend>Dominant hand</legend>" in form
    )
    assert "updrs_34_rating" not in form  # rated per trial (per hand), not per session
    r = client.post(
        f"/patients/{pid}/sessions",
        data={
            "rig_id": str(seeded["rig_id"]),
            "recorded_at": "2025-06-01T10:30",
            "medication_state": "off",
            "dbs_state": "on",
            "time_since_levodopa_min": "720",
            "more_affected_side": "right",
            "dominant_hand": "left",
            "notes": "Morning.",
            "csrf_token": token,
        },
        follow_redirects=False,
    )
    assert r.status_code == 303, r.text
    page = client.get(r.headers["location"]).text
    assert "Upload the left hand" in page and "Upload the right hand" in page
    assert page.count("<progress") >= 2  # an upload progress bar per hand
    assert "12 h 00 min before" in page
    with db_sessionmaker() as db:
        s = db.scalars(select(RecordingSession).order_by(RecordingSession.id.desc())).first()
        assert (s.medication_state, s.dbs_state) == ("off", "on")
        assert (s.time_since_levodopa_min, s.more_affected_side, s.dominant_hand) == (
            720,
            "right",
            "left",
        )
        assert s.recorded_at == datetime(2025, 6, 1, 10, 30, tzinfo=UTC)
    # A bad value is refused with a message in the form's own words; the values are kept.
    r = client.post(
        f"/patients/{pid}/sessions",
        data={
            "rig_id": str(seeded["rig_id"]),
            "recorded_at": "2025-06-01T10:30",
            "time_since_levodopa_min": "soon",
            "csrf_token": token,
        },
    )
    assert r.status_code == 422 and "Time since the last levodopa dose" in r.text
    assert 'value="soon"' in r.text


def test_trial_page_quality_panel_shows_the_camera_timing(client, seeded, db_sessionmaker):
    """A free-running pair's sync figures and core's warning on the trial page (issue 11)."""
    import html as html_lib

    from test_sync_panel import FREE_RUNNING

    t = seeded["trials"][(1, "left")]
    warning = "7 frames were lost during the recording (left after frames [3], right after ...)"
    with db_sessionmaker() as db, db.begin():
        result = db.scalars(select(Result).where(Result.trial_id == t)).one()
        doc = dict(result.document)
        doc["sync"] = FREE_RUNNING
        doc["quality"] = {**doc["quality"], "warnings": [warning]}
        result.document = doc
    login(client)
    page = html_lib.unescape(client.get(f"/trials/{t}").text)
    for text in (
        "Camera clock drift (right against left)",
        "+302 ppm",
        "Frame times from",
        "left: container timestamps; right: frame rate (frame number / fps)",
        "Lost frames found",
        "right 3 (1 frame lost after frame 150, 1 after frame 310 and 1 after frame 455)",
        "Rolling-shutter readout compensated",
        warning,
    ):
        assert text in page, text
    assert "+14.20 frames (" in page and " ms), estimated (confidence 0.83)" in page


def test_session_page_offers_the_left_right_comparison(client, seeded, db_sessionmaker):
    login(client)
    with db_sessionmaker() as db:
        session_id = db.get(Trial, seeded["trials"][(1, "right")]).session_id
    html = client.get(f"/sessions/{session_id}").text
    right, left = seeded["trials"][(1, "right")], seeded["trials"][(1, "left")]
    assert f'href="/trials/{right}?compare={left}#compare"' in html
    page = client.get(f"/trials/{right}?compare={left}")
    assert page.status_code == 200 and "Compared trial" in page.text
    # the visit report's right–left asymmetry over the first 10 taps, not B − A of all taps
    assert "Values over the first 10 taps of each trial" in page.text
    assert "This trial (A), first 10 taps" in page.text
    assert 'data-compare-kind="asymmetry"' in page.text and "Difference Right − left" in page.text
    assert "Right–left asymmetry: (right − left) / mean of both" in page.text


def _add_take(db, session_id: int, task: str, hand: str, status: str, *, hidden: bool = False):
    """A trial without a result: failed (with its job's error), queued or running."""
    trial = Trial(session_id=session_id, task=task, hand=hand, status=status)
    if hidden:
        trial.deleted_at, trial.deleted_reason = datetime(2025, 3, 1, 10, tzinfo=UTC), "x"
    db.add(trial)
    db.flush()
    error = "the cameras disagree" if status == "failed" else None
    db.add(Job(kind="analyze_trial", trial_id=trial.id, status=status, error=error))
    return trial.id


def _grid_cells(html: str) -> dict[tuple[str, str], str]:
    """The task grid's text per (task row, side), and "compare" per row with the link."""
    grid = re.search(r'<table class="list task-grid".*?</table>', html, re.S).group(0)
    cells = {}
    for row in re.findall(r"<tr>\s*<th scope=\"row\">.*?</tr>", grid, re.S):
        title = re.search(r'<th scope="row">([^<]+)</th>', row).group(1)
        for side, text in re.findall(r'<td data-side="(\w+)"[^>]*>(.*?)</td>', row, re.S):
            cells[(title, side)] = " ".join(re.sub(r"<[^>]+>", " ", text).split())
        cells[(title, "compare")] = "yes" if "data-compare-hands" in row else "no"
    return cells


def test_session_grid_says_measured_with_the_failed_retry_not_failed(
    client, seeded, db_sessionmaker
):
    """A right take that failed after a good one made the grid say Right = "failed", yet
    "Compare right and left" was offered (clinic review, item 6)."""
    right, left = seeded["trials"][(1, "right")], seeded["trials"][(1, "left")]
    with db_sessionmaker() as db, db.begin():
        sid = db.get(Trial, right).session_id
        _add_take(db, sid, "finger_tapping", "right", "failed")  # after the good one
        _add_take(db, sid, "finger_tapping", "left", "queued")
        _add_take(db, sid, "finger_tapping", "left", "failed", hidden=True)
        _add_take(db, sid, "hand_movements", "right", "failed")
        _add_take(db, sid, "hand_movements", "right", "running")
        _add_take(db, sid, "hand_movements", "left", "failed")
        _add_take(db, sid, "hand_movements", "left", "failed")
        _add_take(db, sid, "toe_tapping", "right", "failed", hidden=True)
        _add_take(db, sid, "toe_tapping", "left", "failed")
        _add_take(db, sid, "toe_tapping", "left", "failed", hidden=True)
    login(client)
    html = client.get(f"/sessions/{sid}").text
    cells = _grid_cells(html)
    tapping, hand, toe = (
        f"{t} (MDS-UPDRS 3.{n})"
        for t, n in (("Finger tapping", 4), ("Hand movements", 5), ("Toe tapping", 7))
    )
    assert cells[(tapping, "right")] == "measured (1 failed take)"
    assert cells[(tapping, "left")] == "measured (1 take being measured, 1 hidden take)"
    assert cells[(tapping, "compare")] == "yes"  # both sides measured, as the grid says
    assert f'href="/trials/{right}?compare={left}#compare"' in html
    assert cells[(hand, "right")] == "measuring (1 failed take)"
    assert cells[(hand, "left")] == "failed (1 other failed take)"
    assert cells[(hand, "compare")] == "no"
    assert cells[(toe, "right")] == "hidden"
    assert cells[(toe, "left")] == "failed (1 hidden take)"
    assert cells[("Leg agility (MDS-UPDRS 3.8)", "right")] == "not recorded"


def test_trial_page_has_every_plot_metrics_and_quality(client, seeded, db_sessionmaker):
    login(client)
    t = seeded["trials"][(1, "right")]
    before = _audit_count(db_sessionmaker)
    r = client.get(f"/trials/{t}")
    assert r.status_code == 200
    assert _audit_count(db_sessionmaker) == before + 1
    html = r.text
    for name in ("aperture", "amplitude", "velocity", "paths"):
        assert f'data-plot="{name}"' in html, name
    assert "Mean amplitude" in html and "mm/tap" in html
    assert "Calibration used" in html and "clinic-A, calibration v1" in html
    assert "Frames interpolated" in html and "Camera synchronisation offset" in html
    assert "The thumb marker was lost in the last frame." in html
    for kind in ("pdf", "html", "csv", "c3d", "trc", "json", "fhir"):
        assert f'/trials/{t}/download/{kind}"' in html
    # Comparison with the other hand of the same session, offered first.
    other = seeded["trials"][(1, "left")]
    assert re.search(rf'<option value="{other}"[^>]*>[^<]*other hand, same session', html)
    r = client.get(f"/trials/{t}?compare={other}")
    assert "Compared trial" in r.text and _svg_count(r.text) >= 4 + 4
    ids = re.findall(r'id="([^"]+)"', r.text)
    assert len(ids) == len(set(ids)), "duplicate element ids on the comparison page"
    # A trial of another patient cannot be compared, nor the trial with itself.
    assert "cannot be compared" in client.get(f"/trials/{t}?compare=99999").text
    same = client.get(f"/trials/{t}?compare={t}").text
    assert "That is this trial" in same and "Compared trial" not in same


def test_downloads_are_audited_once_each(client, seeded, db_sessionmaker):
    login(client)
    t = seeded["trials"][(1, "right")]
    expected = {
        "pdf": b"%PDF",
        "html": b"<!DOCTYPE html>",
        "csv": b"frame,time_s,marker",
        "trc": b"PathFileType",
        "json": b"{",
        "fhir": b"{",
    }
    for kind, start in expected.items():
        before = _audit_count(db_sessionmaker)
        r = client.get(f"/trials/{t}/download/{kind}")
        assert r.status_code == 200, (kind, r.text[:300])
        assert r.content.lstrip().startswith(start), kind
        assert "attachment" in r.headers["content-disposition"]
        assert _audit_count(db_sessionmaker) == before + 1, kind
    r = client.get(f"/trials/{t}/download/c3d")
    assert r.status_code == 200 and len(r.content) > 512
    assert client.get(f"/trials/{t}/download/exe").status_code == 404
    # The C3D residuals are the reprojection errors in mm, through the focal length of
    # the calibration that measured the trial.
    import io
    import warnings

    import c3d
    import numpy as np

    from app.models import Calibration, Result
    from core.camera import rig_from_dict
    from core.markers_csv import read_markers_csv

    with db_sessionmaker() as db:
        result = db.scalars(select(Result).where(Result.trial_id == t)).one()
        k = rig_from_dict(db.get(Calibration, result.calibration_id).rig_json).cameras[0].K
    markers = read_markers_csv(io.StringIO(client.get(f"/trials/{t}/download/csv").text))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "No analog data found"
        reader = c3d.Reader(io.BytesIO(r.content))
        pts = np.stack([p.copy() for _, p, _ in reader.read_frames()])
    measured = markers.status == "measured"
    expected = markers.reprojection_px * markers.positions_mm[:, :, 2] / (0.5 * (k[0, 0] + k[1, 1]))
    step = abs(reader.point_scale)
    np.testing.assert_allclose(pts[measured][:, 3], expected[measured], atol=0.5 * step)  # mm


def test_rig_pages_show_the_calibration_verdict(client, seeded):
    token = login(client)
    html = client.get("/rigs").text
    assert "clinic-A" in html and "verdict-" in html
    r = client.get(f"/rigs/{seeded['rig_id']}")
    assert r.status_code == 200 and "Version 1" in r.text
    assert re.search(r'class="verdict verdict-(good|acceptable|poor)"', r.text)
    r = client.post("/rigs", data={"name": "clinic-B", "csrf_token": token}, follow_redirects=False)
    assert r.status_code == 303
    rig_page = client.get(r.headers["location"]).text
    assert "No calibration yet" in rig_page
    # Upload a rig file through the page's form (plain multipart, CSRF in the form).
    import json

    rig_id = int(r.headers["location"].split("/")[2].split("?")[0])
    r = client.post(
        f"/rigs/{rig_id}/calibrations",
        data={"csrf_token": _csrf(rig_page)},
        files={"rig_json": ("rig.json", json.dumps(_rig_doc()).encode(), "application/json")},
        follow_redirects=False,
    )
    assert r.status_code == 303, r.text
    assert "Version 1" in client.get(f"/rigs/{rig_id}").text


def test_job_status_json_for_polling(client, seeded, db_sessionmaker):
    login(client)
    with db_sessionmaker() as db:
        job_id = db.scalar(select(Job.id).where(Job.trial_id == seeded["trials"][(0, "right")]))
    r = client.get(f"/jobs/{job_id}/status")
    assert r.status_code == 200
    body = r.json()
    assert body["status"] == "succeeded" and body["trial_url"].startswith("/trials/")
    page = client.get(f"/jobs/{job_id}")
    assert page.status_code == 200 and "data-job-status-url" in page.text
    assert client.get("/jobs/99999/status").status_code == 404


@pytest.fixture(scope="module")
def tiny_videos(tmp_path_factory):
    """Two short, real, decodable videos of the rig's size (640 x 512, 100 fps)."""
    import numpy as np

    from core.camera import ImageSize
    from core.video import VideoWriter

    out = tmp_path_factory.mktemp("videos")
    paths = []
    for k, side in enumerate(("left", "right")):
        path = out / f"{side}.mkv"
        with VideoWriter(path, fps=100.0, image_size=ImageSize(640, 512)) as w:
            for i in range(10):  # the two sides differ (an identical pair is refused)
                w.write(np.full((512, 640), 10 + i + 3 * k, dtype=np.uint8))
        paths.append(path)
    return paths


def _new_session(client, seeded, token) -> str:
    r = client.post(
        f"/patients/{seeded['patient_id']}/sessions",
        data={
            "rig_id": str(seeded["rig_id"]),
            "recorded_at": "2025-06-01T10:30",
            "csrf_token": token,
        },
        follow_redirects=False,
    )
    assert r.status_code == 303
    return r.headers["location"].split("?")[0]


def _stored_files(app_settings) -> list:
    return sorted(p for p in (app_settings.data_dir / "files").rglob("*") if p.is_file())


def test_trial_upload_plain_form_and_script(
    client, seeded, tiny_videos, db_sessionmaker, app_settings
):
    token = login(client)
    session_url = _new_session(client, seeded, token)
    left, right = tiny_videos
    files = {
        "left_video": ("left.mkv", left.read_bytes(), "video/x-matroska"),
        "right_video": ("right.mkv", right.read_bytes(), "video/x-matroska"),
    }
    # Without JavaScript: the form posts, the answer is the job page.
    r = client.post(
        f"{session_url}/trials",
        data={"hand": "left", "csrf_token": token},
        files=files,
        follow_redirects=False,
    )
    assert r.status_code == 303, r.text
    assert re.fullmatch(r"/jobs/\d+", r.headers["location"])
    job_page = client.get(r.headers["location"])
    assert "Waiting for a worker" in job_page.text and 'data-status="queued"' in job_page.text
    # With the script: CSRF in the header, JSON answer.
    r = client.post(
        f"{session_url}/trials",
        data={"hand": "right"},
        files=files,
        headers={"X-CSRF-Token": token, "Accept": "application/json"},
    )
    assert r.status_code == 201, r.text
    assert r.json()["job_url"] == f"/jobs/{r.json()['job_id']}"
    with db_sessionmaker() as db:
        hands = sorted(db.scalars(select(Trial.hand).where(Trial.status == "queued")))
        assert hands == ["left", "right"]


def test_rejected_uploads_leave_nothing(client, seeded, tiny_videos, db_sessionmaker, app_settings):
    token = login(client)
    session_url = _new_session(client, seeded, token)
    files_before = _stored_files(app_settings)
    with db_sessionmaker() as db:
        trials_before = db.scalar(select(func.count()).select_from(Trial))
    left, _ = tiny_videos
    not_a_video = ("right.mkv", b"this is not a video at all" * 100, "video/x-matroska")
    good = ("left.mkv", left.read_bytes(), "video/x-matroska")
    # A file that does not decode: a clear sentence, status 4xx, the session page again.
    r = client.post(
        f"{session_url}/trials",
        data={"hand": "left", "csrf_token": token},
        files={"left_video": good, "right_video": not_a_video},
    )
    assert 400 <= r.status_code < 500 and "right video" in r.text.lower()
    assert "Upload the left hand" in r.text
    # The script gets the same sentence as JSON.
    r = client.post(
        f"{session_url}/trials",
        data={"hand": "left"},
        files={"left_video": good, "right_video": not_a_video},
        headers={"X-CSRF-Token": token, "Accept": "application/json"},
    )
    assert 400 <= r.status_code < 500 and "right video" in r.json()["detail"].lower()
    # A forged token: refused before anything is stored.
    r = client.post(
        f"{session_url}/trials",
        data={"hand": "left", "csrf_token": "forged"},
        files={"left_video": good, "right_video": good},
    )
    assert r.status_code == 403
    with db_sessionmaker() as db:
        assert db.scalar(select(func.count()).select_from(Trial)) == trials_before
    assert _stored_files(app_settings) == files_before
    assert not [p for p in (app_settings.data_dir / "tmp").rglob("*") if p.is_file()]


def test_failed_job_is_explained_in_plain_words(client, seeded, db_sessionmaker):
    login(client)
    message = "The markers were found in 3 of 400 left frames; check the lighting and retry."
    with db_sessionmaker() as db:
        trial = db.get(Trial, seeded["trials"][(0, "right")])
        job = Job(
            kind="analyze_trial",
            trial_id=trial.id,
            status="failed",
            progress=0.3,
            stage="detection",
            error=message,
        )
        db.add(job)
        db.commit()
        job_id = job.id
    page = client.get(f"/jobs/{job_id}")
    assert page.status_code == 200
    assert message in page.text and "could not be completed" in page.text
    assert client.get(f"/jobs/{job_id}/status").json()["stage_label"] == "Stopped with an error"
    # A UI review found the failed job headed "Measuring ..." at "85 %", "updates by
    # itself", and no way on: the ended state has its heading and a way to the session.
    assert 'data-status="failed"' in page.text
    assert "The measurement of the right hand of PD-0042 failed" in page.text
    assert f'<a href="/sessions/{trial.session_id}">Go to the session</a>' in page.text
    css = client.get("/static/style.css").text
    assert '.job[data-status="failed"] .while-working' in css
    with db_sessionmaker() as db:
        db.get(Job, job_id).error = "the left video is 640x480; the rig's cameras are 640x512."
        db.commit()
    assert "The left video is 640x480" in client.get(f"/jobs/{job_id}").text


def test_calibration_upload_needs_one_kind_of_input(client, seeded):
    token = login(client)
    r = client.post(
        f"/rigs/{seeded['rig_id']}/calibrations",
        data={"csrf_token": token},
        # the form's file inputs left empty, as a browser sends them
        files={"rig_json": ("", b"", "application/octet-stream")},
    )
    assert r.status_code == 422 and "either a rig file" in r.text
    r = client.post(  # a part no form of the page has is refused, named
        f"/rigs/{seeded['rig_id']}/calibrations",
        data={"csrf_token": token},
        files={"x": ("x", b"", "text/plain")},
    )
    assert r.status_code == 422 and "this route does not take: &#39;x&#39;" in r.text
    r = client.post(
        f"/rigs/{seeded['rig_id']}/calibrations",
        data={"csrf_token": token},
        files={"rig_json": ("rig.json", b"{not json", "application/json")},
    )
    assert 400 <= r.status_code < 500 and 'class="alert"' in r.text


def test_board_recordings_become_a_calibration_job(client, seeded, tiny_videos):
    token = login(client)
    left, right = tiny_videos
    r = client.post(
        f"/rigs/{seeded['rig_id']}/calibrations",
        data={
            "csrf_token": token,
            "board": "charuco",
            "cols": "7",
            "rows": "5",
            "square_mm": "30",
            "marker_mm": "22",
            "dictionary": "DICT_4X4_1000",
            "valid_from": "",
        },
        files={
            "left_video": ("board-left.mkv", left.read_bytes(), "video/x-matroska"),
            "right_video": ("board-right.mkv", right.read_bytes(), "video/x-matroska"),
        },
        follow_redirects=False,
    )
    assert r.status_code == 303, r.text
    assert re.fullmatch(r"/jobs/\d+", r.headers["location"])
    page = client.get(r.headers["location"]).text
    assert "Computing a calibration" in page and "Waiting for a worker" in page
    rig_page = client.get(f"/rigs/{seeded['rig_id']}").text
    assert "Version 2" in rig_page and "follow the computation" in rig_page


@pytest.mark.parametrize(
    "target",
    [
        "https://evil.example/",
        "//evil.example/",
        "/\\evil.example/",
        "/\\/evil.example",
        "javascript:alert(1)",
        "/patients\r\nSet-Cookie: x=1",
    ],
)
def test_safe_next_stays_on_site(target):
    from app.web.common import safe_next

    assert safe_next(target) == "/patients"
    assert safe_next("/trials/3?compare=4") == "/trials/3?compare=4"


def test_legacy_charuco_board_is_stored_with_the_calibration(
    client, seeded, tiny_videos, db_sessionmaker
):
    """The form's "printed with OpenCV before 4.6" box reaches the board the worker reads."""
    from core.boards import BoardSpec

    token = login(client)
    left, right = tiny_videos
    r = client.post(
        f"/rigs/{seeded['rig_id']}/calibrations",
        data={
            "csrf_token": token,
            "board": "charuco",
            "cols": "8",
            "rows": "6",
            "square_mm": "30",
            "marker_mm": "22",
            "legacy": "on",
        },
        files={
            "left_video": ("board-left.mkv", left.read_bytes(), "video/x-matroska"),
            "right_video": ("board-right.mkv", right.read_bytes(), "video/x-matroska"),
        },
        follow_redirects=False,
    )
    assert r.status_code == 303, r.text
    with db_sessionmaker() as db:
        cal = db.scalars(select(Calibration).order_by(Calibration.id.desc())).first()
        assert cal is not None and cal.board is not None
        assert BoardSpec.from_dict(dict(cal.board)).legacy is True


def test_calibration_quality_shows_the_time_offset_and_warnings():
    """Free-running board videos: the rig page says how far apart the cameras started."""
    from app.web.rigs import _quality_items

    quality = {
        "rms_px": 0.05,
        "sync": {"method": "estimated", "offset_s": 0.29985, "offset_frames": 4.498},
        "warnings": ["the left video has 50 frames and the right 45; the frames past ..."],
    }
    items = dict(_quality_items(quality))
    assert items["Time offset between the cameras"] == (
        "the right video starts 0.300 s (4.50 frames) after the left; found from the board's motion"
    )
    assert items["Warning"].startswith("the left video has 50 frames")
    lab = dict(_quality_items({"sync": {"method": "synchronous", "offset_s": 0.0}}))
    assert lab["Time offset between the cameras"] == "none: the two videos are synchronous"
    assert "Time offset between the cameras" not in dict(
        _quality_items({"sync": {"method": "images"}})
    )


def test_upload_to_a_rig_without_calibration_is_refused_early(
    client, seeded, tiny_videos, db_sessionmaker
):
    token = login(client)
    with db_sessionmaker() as db:
        rig = Rig(name="uncalibrated")
        db.add(rig)
        db.commit()
        rig_id = rig.id
    r = client.post(
        f"/patients/{seeded['patient_id']}/sessions",
        data={"rig_id": str(rig_id), "recorded_at": "2025-06-01T10:30", "csrf_token": token},
        follow_redirects=False,
    )
    session_url = r.headers["location"].split("?")[0]
    assert "none usable" in client.get(session_url).text  # the page warns before any upload
    left, right = tiny_videos
    r = client.post(
        f"{session_url}/trials",
        data={"hand": "left"},
        files={
            "left_video": ("l.mkv", left.read_bytes()),
            "right_video": ("r.mkv", right.read_bytes()),
        },
        headers={"X-CSRF-Token": token, "Accept": "application/json"},
    )
    assert r.status_code == 409 and "calibration" in r.json()["detail"]


def test_a_single_visit_is_a_table_not_one_dot_plots(client, seeded, db_sessionmaker):
    login(client)
    with db_sessionmaker() as db:
        first = db.get(Trial, seeded["trials"][(0, "right")]).session
        first.deleted_at = datetime(2026, 1, 1, tzinfo=UTC)  # only the 2025 visit remains
        db.commit()
    html = client.get(f"/patients/{seeded['patient_id']}").text
    assert "data-trend-table" in html and 'data-plot="trend"' not in html
    assert "right hand, medication on" in html and "left hand, medication on" in html


def test_trends_follow_the_first_10_taps(client, seeded):
    login(client)
    html = client.get(f"/patients/{seeded['patient_id']}").text
    assert "First-10-tap values" in html
    # Hover text of a point: its date, hand, medication state and first-10 value.
    assert "2025-03-01 09:00, left hand, medication on:" in html
    # The same values in a table, for keyboard, touch and screen-reader users (a UI
    # review: with two visits or more the values were only in the plots' hover titles).
    values = re.search(r"<details[^>]*data-trend-values>(.*?)</details>", html, re.S)
    assert values is not None
    row = re.search(r"<tr><th scope=\"row\">2025-03-01 09:00 UTC</th><td>left</td><td>on</td>(.*?)</tr>",
                    values.group(1))  # fmt: skip
    assert row is not None and '<td class="num">' in row.group(1)
    assert "Tapping frequency (Hz)" in values.group(1)


def test_job_page_title_says_how_it_ended_and_the_queue_position(client, seeded, db_sessionmaker):
    login(client)
    with db_sessionmaker() as db:
        done = db.scalar(select(Job.id).where(Job.trial_id == seeded["trials"][(0, "right")]))
        waiting = [
            Job(kind="analyze_trial", trial_id=seeded["trials"][(1, hand)], status="queued")
            for hand in ("left", "right")
        ]
        db.add_all(waiting)
        db.commit()
        second = waiting[1].id
    page = client.get(f"/jobs/{done}").text
    assert f"<title>Analysis {done}: finished — bradyscope</title>" in page
    status = client.get(f"/jobs/{second}/status").json()
    assert status["queue_position"] == 2 and "number 2 in the queue" in status["stage_label"]
    assert status["title"] == f"Analysis {second}: queued"


def test_the_session_table_shows_the_first_10_taps_as_the_trends_do(
    client, seeded, db_sessionmaker
):
    """The item is about the first 10 taps: the session list must not show other numbers."""
    from app.reports.catalogue import format_metric

    login(client)
    with db_sessionmaker() as db:
        doc = db.scalar(
            select(Result.document).where(Result.trial_id == seeded["trials"][(0, "right")])
        )
    first10, whole = doc["metrics_first_10"], doc["metrics"]
    shown = (
        f"{format_metric('amplitude_mm_mean', first10['amplitude_mm_mean'])} mm,"
        f" {format_metric('frequency_hz', first10['frequency_hz'])} Hz"
    )
    recording = f"{format_metric('amplitude_mm_mean', whole['amplitude_mm_mean'])} mm"
    assert not shown.startswith(recording)  # the synthetic trial decrements: they differ
    html = client.get(f"/patients/{seeded['patient_id']}").text
    cells = re.findall(r"<a [^>]*data-session-values>([^<]*)</a>", html)
    assert shown in cells, cells
    assert 'Right hand <span class="unit">(first 10 taps)</span>' in html


def _number(text: str) -> tuple[float, float]:
    """A shown number and half a unit of its last shown digit (its rounding, at most)."""
    clean = text.replace("−", "-").replace("+", "").replace("%", "").replace(",", "").strip()
    decimals = len(clean.split(".")[1]) if "." in clean else 0
    return float(clean), 0.5 * 10.0**-decimals


def test_the_compare_table_says_which_minus_which_and_in_percent(client, seeded):
    """Issue 14, list 5: the difference is labelled (B − A) and given in % of A as well,
    in words (another visit: neither an asymmetry nor a medication response)."""
    login(client)
    a, b = seeded["trials"][(1, "right")], seeded["trials"][(0, "right")]
    html = client.get(f"/trials/{a}?compare={b}").text
    table = re.search(r'<table class="metrics compare-table"[^>]*>(.*?)</table>', html, re.S)
    table = table.group(1)
    assert "Differences are B minus A; the percentage is of A" in table
    assert "Difference B − A" in table and "B against A: (B − A) / A" in table
    checked = 0
    for row in re.findall(
        r"<tr data-compare-row=\"[^\"]+\"><th scope=\"row\">([^<]+)</th>(.*?)</tr>", table, re.S
    ):
        cells = re.findall(r'<td class="num"[^>]*>([^<]*)</td>', row[1])
        words = re.search(r"<td data-words>([^<]*)</td>", row[1]).group(1)
        found = re.fullmatch(r"B (\d+) % (above|below) A", words)
        if len(cells) != 3 or "–" in cells or found is None:
            continue
        (va, ha), (vb, hb), (diff, hd) = (_number(c) for c in cells)
        pct, hp = float(found.group(1)) * (1 if found.group(2) == "above" else -1), 0.5
        if abs(va) <= ha:
            continue
        # Every shown value is rounded: the checks allow exactly that rounding.
        assert diff == pytest.approx(vb - va, abs=ha + hb + hd), row
        pct_rounding = 100 * (hb / abs(va) + abs(vb) * ha / (abs(va) - ha) ** 2) + hp
        assert pct == pytest.approx(100 * (vb - va) / va, abs=pct_rounding), row
        checked += 1
    assert checked >= 2, table[:1500]  # mean amplitude, peak opening velocity


def test_the_aperture_caption_explains_the_closed_offset_and_the_grey_lines(client, seeded):
    """Issue 14, list 5: why the distance never reaches 0, and what the thin grey lines are."""
    login(client)
    html = client.get(f"/trials/{seeded['trials'][(1, 'right')]}").text
    caption = re.sub(r"\s+", " ", html)
    assert "does not reach 0 when the fingers touch" in caption
    assert "measured from that closed position" in caption
    assert "thin grey vertical lines: the start of each tap" in caption


def test_a_page_shows_only_the_notices_the_pages_themselves_send(client, seeded):
    """?msg= is how a redirect says what was done; a crafted link must not put its own
    sentence in a clinical page's status notice (found in a clinician-style review)."""
    login(client)
    t = seeded["trials"][(1, "right")]
    html = client.get(f"/trials/{t}?msg=Rating+saved.").text
    assert 'role="status"' in html and "Rating saved." in html
    html = client.get(f"/trials/{t}?msg=Result+verified+by+the+neurologist.").text
    assert "verified by the neurologist" not in html
    assert "Revision 12 stored." in client.get(f"/trials/{t}/review?msg=Revision+12+stored.").text


def test_every_notice_the_pages_send_is_one_they_show():
    """Each ``?msg=`` of the app's redirects passes app.web.common.NOTICES (a new notice
    must be added there, or it would not be shown)."""
    from pathlib import Path
    from urllib.parse import unquote_plus

    from app.web.common import notice_of

    root = Path(__file__).resolve().parents[2] / "app"
    sent = set()
    for path in root.rglob("*.py"):
        for raw in re.findall(r"\?msg=([^\s\"'#&`]+)", path.read_text(encoding="utf-8")):
            if raw.endswith("."):  # a redirect's notice, not prose about them
                sent.add(unquote_plus(re.sub(r"\{[^}]*\}", "7", raw)))
    assert len(sent) >= 12, sent
    assert [m for m in sorted(sent) if notice_of(m) is None] == []


def test_an_address_that_is_no_page_gets_the_error_page_not_json(client, seeded):
    """/trials/abc answered a browser with raw JSON (a 422 of the path's validation)."""
    login(client)
    html = {"Accept": "text/html,application/xhtml+xml"}
    for url in ("/trials/abc", "/patients/1x", "/no-such-page"):
        r = client.get(url, headers=html)
        assert r.status_code == 404, url
        assert r.headers["content-type"].startswith("text/html"), url
        assert "There is no page at this address" in r.text and url not in r.text
    # API clients keep their JSON answers
    r = client.get("/api/v1/trials/abc", headers=html)
    assert r.status_code == 422 and r.json()["detail"].startswith("The request is invalid")
    assert client.get("/no-such-page").headers["content-type"].startswith("application/json")


def test_the_interruptions_band_has_a_row_of_its_own(client, seeded):
    """The band of hesitations and halts together sat in the Hesitations row and read as
    that count's band ("Hesitations 2 — 3 · moderate: a freeze"; found in a review)."""
    login(client)
    html = client.get(f"/trials/{seeded['trials'][(1, 'right')]}").text
    rows = dict(re.findall(r'<tr data-summary-row="([^"]+)"[^>]*>(.*?)</tr>', html, re.S))
    assert "data-band" not in rows["hesitation_count"]
    assert "data-band" not in rows["halt_count"]
    assert 'data-band="interruptions"' in rows["interruptions-band"]
    assert "Band of both" in rows["interruptions-band"]
    # the single-measure aspects keep their band beside their value
    assert 'data-band="speed"' in rows["frequency_hz"]


def test_a_patient_code_refused_says_what_is_allowed_in_words(client, seeded):
    """A UI review found "String should match pattern '^[A-Za-z0-9]...'" on the form."""
    token = login(client)
    r = client.post("/patients", data={"code": "Jan Novák", "csrf_token": token})
    assert r.status_code == 422
    assert "The patient code must use letters, digits, dots, underscores and dashes only" in r.text
    assert "pattern" not in r.text.split("<main", 1)[1].split("</main>")[0].replace('pattern="', "")

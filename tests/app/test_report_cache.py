# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Trials' PDF reports made ahead by the worker, kept on disk, never stale.

The worker makes a trial's report whenever what it shows changes; the request
then serves it without making it; a request that finds none makes it and keeps
it; erasing the patient or restoring a backup removes the kept reports.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterator

import pytest
from api_support import (  # noqa: F401 - pytest fixtures
    Api,
    api,
    make_api_key,
    make_user,
    trial_files,
    video_pair,
)
from fastapi.testclient import TestClient
from sample_trial import synthetic_trial
from sqlalchemy import select
from test_revisions import _trial

import app.services.results as results_service
from app import job_views, jobs
from app.db import dispose_engines, get_sessionmaker
from app.main import create_app
from app.models import AuditEvent, Calibration, Job, Result, Trial, utcnow
from app.reports.pdf_cache import ReportPdfCache
from app.services import revisions
from app.storage import Storage
from app.worker import run_worker
from core.markers_csv import markers_csv_text, read_markers_csv

PASSWORD = "a long clinician passphrase 42"


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def db_api(request: pytest.FixtureRequest) -> Iterator[Api]:
    """The API over SQLite, and over PostgreSQL (``-m postgres``)."""
    settings = request.getfixturevalue(
        "app_settings" if request.param == "sqlite" else "pg_settings"
    )
    sessions = get_sessionmaker(settings)
    app = create_app(settings)
    with TestClient(app) as client:
        yield Api(app, client, settings, sessions, make_api_key(sessions))
    dispose_engines()


@pytest.fixture
def made(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The trial ids of the PDF reports made (by the worker or a request) during the test."""
    calls: list[int] = []
    render = results_service.render_report_pdf

    def counting(data):
        calls.append(data.trial_id)
        return render(data)

    monkeypatch.setattr(results_service, "render_report_pdf", counting)
    return calls


def _measured_trial(api: Api, video_pair) -> int:
    """A trial with a result and its stored plots, as the worker leaves an analysis."""
    trial_id = _trial(api, video_pair)
    storage = Storage.from_settings(api.settings)
    with api.sessions() as db:
        result = db.scalars(select(Result).where(Result.trial_id == trial_id)).one()
        table = read_markers_csv(storage.absolute(result.markers_path), fps=100.0)
        result.plots_path = revisions.store_plots(storage, result.document, table)
        db.commit()
    return trial_id


def _cache(api: Api) -> ReportPdfCache:
    return ReportPdfCache.of(Storage.from_settings(api.settings))


def _queued_reports(api: Api) -> list[int | None]:
    with api.sessions() as db:
        return list(
            db.scalars(
                select(Job.trial_id).where(Job.kind == jobs.REPORT_PDF, Job.status == "queued")
            )
        )


def _pdf(api: Api, trial_id: int, client: TestClient | None = None) -> bytes:
    r = (client or api.client).get(f"/api/v1/trials/{trial_id}/report.pdf", headers=api.headers)
    assert r.status_code == 200, r.text
    assert r.content.startswith(b"%PDF")
    return r.content


def _text(pdf: bytes, tmp_path) -> str:
    if shutil.which("pdftotext") is None:
        pytest.skip("pdftotext (poppler-utils) is not installed")
    path = tmp_path / "report.pdf"
    path.write_bytes(pdf)
    out = subprocess.run(["pdftotext", str(path), "-"], capture_output=True, text=True, check=True)
    return " ".join(out.stdout.split())


def _export_events(api: Api) -> int:
    with api.sessions() as db:
        return len(
            db.scalars(
                select(AuditEvent).where(
                    AuditEvent.action == "export", AuditEvent.resource_type == "report_pdf"
                )
            ).all()
        )


def test_the_worker_makes_the_pdf_and_the_request_serves_it(db_api: Api, video_pair, made):
    api = db_api
    trial_id = _measured_trial(api, video_pair)
    r = api.client.patch(
        f"/api/v1/trials/{trial_id}", json={"clinician_rating": 2}, headers=api.headers
    )
    assert r.status_code == 200, r.text
    assert _queued_reports(api) == [trial_id]
    # Its analysis stays the trial's job on the pages and in the API.
    assert api.client.get(f"/api/v1/trials/{trial_id}", headers=api.headers).json()["job_id"]
    with api.sessions() as db:
        assert db.get(Trial, trial_id).status == "succeeded"
        analysis = job_views.latest_job(db, trial_id=trial_id)
        assert analysis is not None and analysis.kind == "analyze_trial"

    assert run_worker(api.settings, once=True) == 1
    assert made == [trial_id] and _queued_reports(api) == []
    (kept,) = _cache(api).files()
    events = _export_events(api)
    assert _pdf(api, trial_id) == kept.read_bytes()
    assert _pdf(api, trial_id) == kept.read_bytes()
    assert made == [trial_id]  # the requests made none
    assert _export_events(api) == events + 2  # each download is still one export event
    with api.sessions() as db:
        assert db.get(Trial, trial_id).status == "succeeded"


def test_every_change_of_what_the_report_shows_makes_a_new_pdf(
    db_api: Api, video_pair, made, tmp_path
):
    """A rating, the session's notes, a correction and a re-analysis each give a new PDF,
    made by the worker and served as made; signing the visit changes nothing the trial's
    report shows, and the signed visit report stays as signed."""
    api = db_api
    h = api.headers
    trial_id = _measured_trial(api, video_pair)
    with api.sessions() as db:
        session_id = db.get(Trial, trial_id).session_id
    make_user(api.sessions, "dr.sign@example.org", PASSWORD)
    clinician = TestClient(api.app)
    login = clinician.post(
        "/api/v1/auth/login", json={"email": "dr.sign@example.org", "password": PASSWORD}
    )
    assert login.status_code == 200, login.text
    csrf = {"X-CSRF-Token": login.json()["csrf_token"]}
    seen = [_pdf(api, trial_id)]  # made by this request: nothing was queued yet
    assert made == [trial_id]

    def re_analysis() -> None:
        with api.sessions() as db, db.begin():
            current = db.scalars(
                select(Result).where(Result.trial_id == trial_id).order_by(Result.revision.desc())
            ).first()
            revisions.store_analysis(
                db,
                trial_id=trial_id,
                job_id=db.scalar(select(Job.id).where(Job.kind == "analyze_trial")),
                calibration_id=db.scalar(select(Calibration.id)),
                document={**current.document, "sync": {"offset_frames": 2.0, "method": "given"}},
                markers_path=current.markers_path,
                overlay_path=None,
                request={"by": "Dr Sign", "reason": "the offset was 2 frames", "change": {}},
                plots_path=current.plots_path,
            )

    changes = [
        (
            "rating",
            lambda: api.client.patch(
                f"/api/v1/trials/{trial_id}",
                json={"clinician_rating": 3, "comment": "Slower from the fifth tap"},
                headers=h,
            ),
            "Slower from the fifth tap",
        ),
        (
            "notes",
            lambda: api.client.patch(
                f"/api/v1/sessions/{session_id}", json={"notes": "Tremor at rest."}, headers=h
            ),
            "Tremor at rest.",
        ),
        (
            "correction",
            lambda: api.client.post(
                f"/api/v1/trials/{trial_id}/revisions",
                json={"exclude_taps": [2], "reason": "tap 3 was a cough"},
                headers=h,
            ),
            "tap 3 was a cough",
        ),
        ("re-analysis", re_analysis, "the offset was 2 frames"),
    ]
    sign = f"/api/v1/sessions/{session_id}/sign"
    signed_pdf = f"/api/v1/sessions/{session_id}/report.pdf?signed=true"
    for what, change, words in changes:
        response = change()
        assert response is None or response.status_code in (200, 201), (what, response.text)
        assert _queued_reports(api) == [trial_id], what
        assert run_worker(api.settings, once=True) == 1, what
        made_before = len(made)
        pdf = _pdf(api, trial_id)
        assert len(made) == made_before, what  # served as the worker made it
        assert pdf not in seen, what
        assert words in _text(pdf, tmp_path), what
        seen.append(pdf)
        if what == "notes":  # sign the visit between two changes
            signed = clinician.post(sign, json={"password": PASSWORD}, headers=csrf)
            assert signed.status_code == 201, signed.text
            signed_bytes = clinician.get(signed_pdf).content
            assert _queued_reports(api) == [] and _pdf(api, trial_id) == pdf, "signing"
    # The signed visit report is kept byte for byte after the corrections that followed.
    assert clinician.get(signed_pdf).content == signed_bytes
    text = _text(seen[-1], tmp_path)  # the header's row holds another key before the value
    assert "RESULT REVISION" in text and "3 — edited" in text


def _second_hand(api: Api, video_pair, first: int) -> int:
    """The other hand of ``first``'s session, uploaded: its analysis is queued."""
    with api.sessions() as db:
        session_id = db.get(Trial, first).session_id
    r = api.client.post(
        f"/api/v1/sessions/{session_id}/trials",
        data={"hand": "right"},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    assert r.status_code == 201, r.text
    return int(r.json()["id"])


def _measure_as_the_worker(api: Api, trial_id: int) -> None:
    """Store a result of ``trial_id`` and mark its analysis done, as the worker does after
    measuring it (the same transaction queues its report job)."""
    markers, document = synthetic_trial(amplitude0_mm=40.0)
    storage = Storage.from_settings(api.settings)
    stored = storage.write_bytes("results", ".csv", markers_csv_text(markers).encode())
    with api.sessions() as db, db.begin():
        job = db.scalars(select(Job).where(Job.trial_id == trial_id)).one()
        job.status = "succeeded"
        db.get(Trial, trial_id).status = "succeeded"
        revisions.store_analysis(
            db,
            trial_id=trial_id,
            job_id=job.id,
            calibration_id=db.scalar(select(Calibration.id)),
            document=document,
            markers_path=stored.path,
            overlay_path=None,
            plots_path=revisions.store_plots(storage, document, markers),
        )


def test_the_other_hand_measured_makes_the_first_hands_report_again(api: Api, video_pair, made):
    """A trial's report shows the other hand of its visit beside it: when that one is
    measured, the worker makes both reports, and the first hand's PDF is found made."""
    first = _measured_trial(api, video_pair)  # the left hand
    before = _pdf(api, first)
    assert made == [first]
    second = _second_hand(api, video_pair, first)
    _measure_as_the_worker(api, second)
    assert _queued_reports(api) == [second]
    assert run_worker(api.settings, once=True) == 1
    assert made == [first, second, first]  # its own report, then the left hand's again
    after = _pdf(api, first)
    assert after != before and len(made) == 3  # found made


def test_a_visits_reports_wait_for_its_pending_analysis(db_api: Api, video_pair, made):
    """While an analysis of the visit is queued or running, a report job makes nothing
    (the analysis would change the reports again); the analysis's own report job then
    makes the visit's reports, each once."""
    api = db_api
    first = _measured_trial(api, video_pair)
    second = _second_hand(api, video_pair, first)
    r = api.client.patch(
        f"/api/v1/trials/{first}", json={"clinician_rating": 2}, headers=api.headers
    )
    assert r.status_code == 200 and _queued_reports(api) == [first]
    assert run_worker(api.settings, max_jobs=1) == 1  # reports first: the rating's job
    assert made == [] and _queued_reports(api) == [] and _cache(api).files() == []
    _measure_as_the_worker(api, second)
    assert _queued_reports(api) == [second]
    assert run_worker(api.settings, once=True) == 1
    assert made == [second, first]  # its own first, then the rest of the visit
    first_pdf = _pdf(api, first)
    assert _pdf(api, second) != first_pdf and made == [second, first]  # both found made


def test_an_analysis_that_fails_for_good_lets_its_visits_reports_be_made(
    api: Api, video_pair, made
):
    first = _measured_trial(api, video_pair)
    second = _second_hand(api, video_pair, first)
    api.client.patch(f"/api/v1/trials/{first}", json={"comment": "x"}, headers=api.headers)
    assert run_worker(api.settings, max_jobs=1) == 1
    assert made == []  # waits for the second hand's analysis
    claimed = jobs.claim_next(api.sessions, worker_name="w", lease_s=60.0, kinds=("analyze_trial",))
    assert claimed is not None and claimed.trial_id == second
    assert jobs.fail(api.sessions, claimed, "No markers.", retryable=True) == "queued"
    assert _queued_reports(api) == []  # it will be tried again: still pending
    claimed = jobs.claim_next(api.sessions, worker_name="w", lease_s=60.0, kinds=("analyze_trial",))
    assert claimed is not None
    assert jobs.fail(api.sessions, claimed, "No markers.", retryable=False) == "failed"
    assert _queued_reports(api) == [second]
    assert run_worker(api.settings, once=True) == 1
    assert made == [first]  # the second hand has no result, so no report
    _pdf(api, first)
    assert made == [first]


def test_without_the_workers_copy_the_request_makes_the_pdf_and_keeps_it(
    api: Api, video_pair, made
):
    trial_id = _measured_trial(api, video_pair)
    r = api.client.patch(f"/api/v1/trials/{trial_id}", json={"comment": "x"}, headers=api.headers)
    assert r.status_code == 200 and _queued_reports(api) == [trial_id]
    # The PDF is asked for before the worker ran: the request makes it, and keeps it.
    first = _pdf(api, trial_id)
    assert _pdf(api, trial_id) == first and made == [trial_id]
    assert run_worker(api.settings, once=True) == 1  # it finds the report made
    assert made == [trial_id] and len(_cache(api).files()) == 1
    # A second change while one report job is queued queues no other.
    for comment in ("y", "z"):
        api.client.patch(
            f"/api/v1/trials/{trial_id}", json={"comment": comment}, headers=api.headers
        )
    assert _queued_reports(api) == [trial_id]


def test_a_report_in_another_time_zone_is_made_for_it(api: Api, video_pair, made, tmp_path):
    trial_id = _measured_trial(api, video_pair)
    api.client.patch(f"/api/v1/trials/{trial_id}", json={"comment": "x"}, headers=api.headers)
    assert run_worker(api.settings, once=True) == 1  # made in the settings' zone: UTC
    utc = _pdf(api, trial_id)
    assert made == [trial_id]
    elsewhere = api.settings.model_copy(update={"timezone": "America/New_York"})
    with TestClient(create_app(elsewhere)) as client:
        new_york = _pdf(api, trial_id, client)
    assert made == [trial_id, trial_id]  # not the UTC report
    assert "2026-03-01 04:30" in _text(new_york, tmp_path)  # recorded 09:30 UTC
    assert "2026-03-01 09:30" in _text(utc, tmp_path)
    assert _pdf(api, trial_id) == utc and len(made) == 2


def test_erasing_the_patient_removes_their_kept_reports(api: Api, video_pair, made):
    from app.services.erasure import erase_patient

    trial_id = _measured_trial(api, video_pair)
    cache = _cache(api)
    other = cache.put(999, 5, "a" * 64, b"%PDF-1.7 another patient's report")
    _pdf(api, trial_id)
    assert len(cache.files()) == 2
    storage = Storage.from_settings(api.settings)
    with api.sessions() as db:
        code = db.get(Trial, trial_id).session.patient.code
        erase_patient(db, storage, None, code)
    assert cache.files() == [other]


def test_a_report_made_while_its_patient_is_erased_removes_itself(
    api: Api, video_pair, monkeypatch
):
    """The erasure removes the kept files after its commit; a report being made at that
    moment is kept after that, then finds its trial gone and removes the patient's files."""
    from app.services.erasure import erase_patient

    trial_id = _measured_trial(api, video_pair)
    storage = Storage.from_settings(api.settings)
    with api.sessions() as db:
        code = db.get(Trial, trial_id).session.patient.code
    render = results_service.render_report_pdf

    def erased_meanwhile(data):
        pdf = render(data)
        with api.sessions() as db:
            erase_patient(db, storage, None, code)
        return pdf

    monkeypatch.setattr(results_service, "render_report_pdf", erased_meanwhile)
    made = results_service.make_report_pdfs(api.sessions, storage, trial_id, timezone="UTC")
    assert made == [trial_id] and _cache(api).files() == []
    # Once the trial is gone the job has nothing to make.
    assert results_service.make_report_pdfs(api.sessions, storage, trial_id, timezone="UTC") == []


def test_a_hidden_trials_report_job_makes_nothing(api: Api, video_pair, made):
    trial_id = _measured_trial(api, video_pair)
    with api.sessions() as db, db.begin():
        jobs.enqueue_report_pdf(db, trial_id)
        db.get(Trial, trial_id).deleted_at = utcnow()
    assert run_worker(api.settings, once=True) == 1
    assert made == [] and _cache(api).files() == []


def test_a_restore_empties_the_report_cache(api: Api, video_pair, tmp_path, monkeypatch):
    """And the trend plot cache (app.reports.trend_cache), derived the same way."""
    from cli_support import admin_cli

    from app.reports.trend_cache import TrendSvgCache

    trial_id = _measured_trial(api, video_pair)
    _pdf(api, trial_id)
    assert len(_cache(api).files()) == 1
    trends = TrendSvgCache.of(Storage.from_settings(api.settings))
    trends.put(1, "a" * 64, "<svg>a trend</svg>")
    assert admin_cli(api.settings, monkeypatch, "backup", str(tmp_path / "backup")) == 0
    manifest = (tmp_path / "backup" / "manifest.json").read_text()
    assert "cache/" not in manifest  # derived: never backed up
    dispose_engines()
    assert admin_cli(api.settings, monkeypatch, "restore", str(tmp_path / "backup"), "--force") == 0
    assert _cache(api).files() == [] and trends.files() == []
    dispose_engines()

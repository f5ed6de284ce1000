# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""The database gone or read-only is said as such (review of failures, 2026-11-28).

- 1: a database that cannot be reached (refused, not accepting connections, its
  connections terminated; a SQLite file that cannot be opened) answers 503 with the
  documented sentence, not 500;
- 5: a read-only database is named as the database, and ``/health`` fails while the
  database cannot be written;
- 6: a database unreachable for a moment while a job runs spends none of its attempts;
- 7: a file larger than the file system or the process's limits allow (EFBIG) is a
  507 with its own sentence;
- 10: a page's server error is an HTML page with the request id and a way back;
- 11: the worker's log names no uploaded file (clinics name them after patients).

The PostgreSQL tests put a TCP proxy (tests/app/tcp_proxy.py) between the application
and the server, and stop it: what a network outage or a database server that went
down does to the application.
"""

from __future__ import annotations

import json
import logging
import re
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import sqlalchemy as sa
from api_support import (
    api,  # noqa: F401
    make_api_key,
    make_user,
    seed_recording_target,
    video_pair,  # noqa: F401
)
from conftest import make_test_settings
from fastapi.testclient import TestClient
from sqlalchemy.exc import DBAPIError

from app import faults, jobs
from app.apikeys import generate_api_key
from app.db import dispose_engines, get_sessionmaker
from app.errors import InsufficientStorageError, ServiceUnavailableError
from app.faults import DATABASE_DOWN, DATABASE_FILE_UNOPENED, storage_fault
from app.job_context import JobContext, RetryableJobError
from app.main import create_app
from app.models import Job
from app.settings import Settings
from app.worker import run_worker
from core.errors import InputError

EMAIL, PASSWORD = "clinician@example.org", "a long enough password 1"


def _closed_port() -> int:
    """A local TCP port nobody listens on (just released by this process)."""
    with socket.create_server(("127.0.0.1", 0)) as sock:
        return int(sock.getsockname()[1])


def _connect_error(url: str) -> DBAPIError:
    engine = sa.create_engine(url)
    try:
        with pytest.raises(DBAPIError) as caught:
            engine.connect()
    finally:
        engine.dispose()
    return caught.value


# --------------------------------------------------------------------------- finding 1


def test_a_refused_postgresql_connection_is_the_database_unreachable() -> None:
    exc = _connect_error(f"postgresql+psycopg://postgres@127.0.0.1:{_closed_port()}/none")
    assert "refused" in str(exc.orig).lower()  # psycopg's own error, no SQLSTATE
    fault = storage_fault(exc)
    # before: None, so a 500 "Internal error"
    assert isinstance(fault, ServiceUnavailableError) and str(fault) == DATABASE_DOWN


def test_a_sqlite_file_that_cannot_be_opened_is_the_database_unreachable(tmp_path: Path) -> None:
    exc = _connect_error(f"sqlite:///{tmp_path / 'no-such-directory' / 'db.sqlite3'}")
    fault = storage_fault(exc)
    # before: "the server's storage reported an input/output error"
    assert isinstance(fault, ServiceUnavailableError) and str(fault) == DATABASE_FILE_UNOPENED


def test_an_error_in_sql_stays_an_internal_error(app_settings: Settings) -> None:
    engine = sa.create_engine(f"sqlite:///{app_settings.data_dir / 'bradyscope.sqlite3'}")
    try:
        with pytest.raises(DBAPIError) as caught, engine.connect() as conn:
            conn.execute(sa.text("SELECT * FROM no_such_table"))
    finally:
        engine.dispose()
    assert storage_fault(caught.value) is None  # a bug, not the service being down


def _login_form(client: TestClient, password: str) -> dict[str, str]:
    """The login form's fields, with the CSRF token of the login page (no database read)."""
    page = client.get("/login")
    token = re.search(r'name="csrf_token" value="([^"]+)"', page.text)
    assert token is not None, page.text
    return {"email": EMAIL, "password": password, "csrf_token": token.group(1)}


def _login(client: TestClient) -> None:
    r = client.post("/login", data=_login_form(client, PASSWORD), follow_redirects=False)
    assert r.status_code == 303, r.text


HTML = {"Accept": "text/html,application/xhtml+xml,*/*;q=0.8"}


def _assert_unreachable_answers(
    client: TestClient, anonymous: TestClient, key: str, form: dict[str, str]
) -> None:
    """The API, a page (``client`` is logged in) and the login form (``form``, of
    ``anonymous``), while the database cannot be reached."""
    r = client.get("/api/v1/patients", headers={"Authorization": f"Bearer {key}"})
    assert r.status_code == 503, r.text  # before: 500 "Internal error"
    assert r.json()["detail"] == DATABASE_DOWN
    for r in (
        client.get("/patients", headers=HTML),
        anonymous.post("/login", headers=HTML, data=form),
    ):
        url = r.request.url.path
        assert r.status_code == 503, (url, r.text)
        assert r.headers["content-type"].startswith("text/html"), (url, r.text)
        assert "cannot be reached" in r.text, r.text
        # before: no request id on the page, no way back but the (unreachable) patient list
        assert f"request id <code>{r.headers['x-request-id']}</code>" in r.text
        retry = 'href="/patients">Try this page again' in r.text
        assert retry == (r.request.method == "GET") and 'href="/patients"' in r.text


@pytest.mark.postgres
def test_an_unreachable_postgresql_answers_503_and_a_page(proxied, pg_admin_url: str) -> None:
    settings, proxy = proxied
    sessions = get_sessionmaker(settings)
    key = make_api_key(sessions)
    make_user(sessions, EMAIL, PASSWORD)
    app = create_app(settings)
    with (
        TestClient(app, raise_server_exceptions=False) as client,
        TestClient(app, raise_server_exceptions=False) as anonymous,
    ):
        _login(client)
        assert client.get("/patients", headers=HTML).status_code == 200
        form = _login_form(anonymous, "a wrong password")
        proxy.stop()  # the server gone: open connections cut, new ones refused
        _assert_unreachable_answers(client, anonymous, key, form)
        proxy.start()
        assert client.get("/patients", headers=HTML).status_code == 200
        name = sa.make_url(settings.database_url).database
        admin = sa.create_engine(pg_admin_url, isolation_level="AUTOCOMMIT")
        try:
            with admin.connect() as conn:  # "not currently accepting connections" (55000)
                conn.execute(sa.text(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS false'))
                conn.execute(
                    sa.text("SELECT pg_terminate_backend(pid) FROM pg_stat_activity"
                            " WHERE datname = :name AND pid <> pg_backend_pid()"),
                    {"name": name},
                )  # fmt: skip
            _assert_unreachable_answers(client, anonymous, key, form)
        finally:
            with admin.connect() as conn:
                conn.execute(sa.text(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS true'))
            admin.dispose()
        assert client.get("/api/v1/patients", headers={"Authorization": f"Bearer {key}"}).is_success


def test_a_missing_sqlite_database_answers_503_and_a_page(tmp_path: Path) -> None:
    settings = make_test_settings(tmp_path / "data")
    settings.data_dir.mkdir()
    gone = settings.model_copy(
        update={"database_url": f"sqlite:///{tmp_path / 'gone' / 'bradyscope.sqlite3'}"}
    )
    with TestClient(create_app(gone), raise_server_exceptions=False) as client:
        key, _ = generate_api_key()  # well formed: looked up in the database
        r = client.get("/api/v1/patients", headers={"Authorization": f"Bearer {key}"})
        assert r.status_code == 503 and r.json()["detail"] == DATABASE_FILE_UNOPENED, r.text
        r = client.post("/login", headers=HTML, data=_login_form(client, "a wrong password"))
        assert r.status_code == 503 and r.headers["content-type"].startswith("text/html")


# --------------------------------------------------------------------------- finding 10


def test_an_unexpected_error_on_a_page_is_an_html_page_with_the_request_id(
    app_settings: Settings,
) -> None:
    app = create_app(app_settings)

    def broken() -> None:
        raise RuntimeError("a bug")

    app.add_api_route("/broken", broken, methods=["GET", "POST"])
    with TestClient(app, raise_server_exceptions=False) as client:
        r = client.get("/broken?x=1", headers=HTML)
        assert r.status_code == 500
        # before: {"detail": "Internal error; quote request id ..."} shown raw
        assert r.headers["content-type"].startswith("text/html"), r.text
        request_id = r.headers["x-request-id"]
        assert f"request id <code>{request_id}</code>" in r.text
        assert 'href="/broken?x=1">Try this page again' in r.text and 'href="/patients"' in r.text
        assert "a bug" not in r.text and "Traceback" not in r.text
        assert "default-src 'self'" in r.headers["content-security-policy"]
        assert r.headers["cache-control"] == "no-store"
        r = client.post("/broken", headers=HTML, data={"a": "b"})  # a form: no retry link
        assert r.status_code == 500 and "Try this page again" not in r.text
        assert r.headers["x-request-id"] in r.text
        for accept in ("application/json", "*/*", "application/json, text/html;q=0.5"):
            r = client.get("/broken", headers={"Accept": accept})
            assert r.status_code == 500 and r.headers["x-request-id"] in r.json()["detail"]
        r = client.get("/api/v1/nothing-here-either", headers=HTML)
        assert r.headers["content-type"].startswith("application/json")  # the API keeps JSON


def test_the_error_page_links_back_on_this_site_only(app_settings: Settings) -> None:
    app = create_app(app_settings)

    def broken() -> None:
        raise RuntimeError("a bug")

    app.add_api_route("/{rest:path}", broken)
    with TestClient(app, raise_server_exceptions=False) as client:
        for path, back in (
            ("http://testserver//evil.example/x", "/evil.example/x"),  # not "//evil.example"
            ("/%5Cevil.example/x", "/%5Cevil.example/x"),  # stays encoded: a path here
        ):
            r = client.get(path, headers=HTML)
            assert r.status_code == 500
            assert f'href="{back}">Try this page again' in r.text, r.text


# --------------------------------------------------------------------------- finding 5


def _read_only_sqlite(settings: Settings) -> Settings:
    """``settings``' SQLite database opened read-only (what SQLite does with a file, or a
    ``-wal``, it may not write)."""
    path = settings.data_dir / "bradyscope.sqlite3"
    return settings.model_copy(update={"database_url": f"sqlite:///file:{path}?mode=ro&uri=true"})


def test_a_read_only_sqlite_database_is_named_and_fails_health(
    app_settings: Settings, db_sessionmaker, monkeypatch
) -> None:
    monkeypatch.setattr(faults, "WRITE_CHECK_INTERVAL_S", 0.0)
    key = make_api_key(db_sessionmaker)
    with TestClient(create_app(_read_only_sqlite(app_settings))) as client:
        r = client.get("/api/v1/patients", headers={"Authorization": f"Bearer {key}"})
        # before: "... check the data directory's disk"
        assert r.status_code == 503 and r.json()["detail"] == faults.READ_ONLY_DATABASE, r.text
        health = client.get("/health")
        # before: 200 {"status": "ok", "database": "ok", ...}
        assert health.status_code == 503, health.text
        assert health.json()["database"] == "failed" and health.json()["storage"] == "ok"
        assert faults.READ_ONLY_DATABASE in health.json()["detail"]
    with TestClient(create_app(app_settings)) as client:
        assert client.get("/health").status_code == 200


@pytest.mark.postgres
def test_a_read_only_postgresql_is_named_and_fails_health(
    pg_settings: Settings, pg_admin_url: str, monkeypatch
) -> None:
    monkeypatch.setattr(faults, "WRITE_CHECK_INTERVAL_S", 0.0)
    key = make_api_key(get_sessionmaker(pg_settings))
    name = sa.make_url(pg_settings.database_url).database
    admin = sa.create_engine(pg_admin_url, isolation_level="AUTOCOMMIT")
    app = create_app(pg_settings)
    try:
        with TestClient(app) as client:
            assert client.get("/health").status_code == 200
            with admin.connect() as conn:
                conn.execute(
                    sa.text(f'ALTER DATABASE "{name}" SET default_transaction_read_only = on')
                )
            app.state.engine.dispose()  # new sessions take the database's new default
            r = client.get("/api/v1/patients", headers={"Authorization": f"Bearer {key}"})
            assert r.status_code == 503, r.text
            assert (
                r.json()["detail"] == faults.READ_ONLY_DATABASE
            )  # before: "the data directory's disk"
            health = client.get("/health")
            assert health.status_code == 503, health.text  # before: 200, "database": "ok"
            assert faults.READ_ONLY_DATABASE in health.json()["detail"]
            with admin.connect() as conn:
                conn.execute(
                    sa.text(f'ALTER DATABASE "{name}" RESET default_transaction_read_only')
                )
            app.state.engine.dispose()
            assert client.get("/health").status_code == 200
    finally:
        admin.dispose()


def test_health_writes_to_the_database_at_most_every_few_seconds_and_keeps_nothing(
    app_settings: Settings, db_sessionmaker, monkeypatch
) -> None:
    clock = [1000.0]
    monkeypatch.setattr(faults, "monotonic", lambda: clock[0])
    app = create_app(app_settings)
    writes: list[str] = []

    @sa.event.listens_for(app.state.engine, "before_cursor_execute")
    def count(conn, cursor, statement, parameters, context, executemany) -> None:
        if statement.lstrip().upper().startswith("UPDATE"):
            writes.append(statement)

    with db_sessionmaker() as db:
        version = db.scalar(sa.text("SELECT version_num FROM alembic_version"))
    with TestClient(app) as client:
        for _ in range(10):
            assert client.get("/health").status_code == 200
        assert len(writes) == 1  # before: 0 (SELECT 1 only)
        clock[0] += faults.WRITE_CHECK_INTERVAL_S
        assert client.get("/health").status_code == 200
        assert len(writes) == 2
    with db_sessionmaker() as db:
        assert db.scalar(sa.text("SELECT version_num FROM alembic_version")) == version


# --------------------------------------------------------------------------- finding 7

_UPLOAD_UNDER_A_FILE_SIZE_LIMIT = r"""
import json, resource, sys
from pathlib import Path
from fastapi.testclient import TestClient
from app.job_context import JobContext, RetryableJobError
from app.main import create_app
from app.models import Job
from app.settings import Settings
from app.worker import run_worker
from core.errors import InputError

data_dir, key, session_id, left, right, limit = sys.argv[1:7]
resource.setrlimit(resource.RLIMIT_FSIZE, (int(limit), int(limit)))  # as `ulimit -f`, LimitFSIZE
settings = Settings(data_dir=data_dir, max_upload_bytes=64 * 1024 * 1024)
with TestClient(create_app(settings), raise_server_exceptions=False) as client:
    files = {
        "left_video": ("left.mp4", Path(left).read_bytes(), "video/mp4"),
        "right_video": ("right.mp4", Path(right).read_bytes(), "video/mp4"),
    }
    r = client.post(f"/api/v1/sessions/{session_id}/trials", data={"hand": "left"},
                    files=files, headers={"Authorization": f"Bearer {key}"})
    print(json.dumps({"status": r.status_code, "body": r.text}))
"""


def test_a_file_larger_than_the_file_system_allows_answers_507(api, video_pair, tmp_path) -> None:
    """EFBIG (a FAT/exFAT disk, systemd's LimitFSIZE, ``ulimit -f``) is a 507 with its
    sentence, not a 500 with a traceback; nothing is kept."""
    seeded = seed_recording_target(api)
    before, files_before = api.recording_rows(), api.stored_files()
    dispose_engines()
    database = api.settings.data_dir / "bradyscope.sqlite3"
    limit = database.stat().st_size + 4 * 1024 * 1024  # bytes: the database may still grow
    big_left = tmp_path / "left.mp4"  # a video followed by more bytes than the limit allows
    big_left.write_bytes(video_pair[0].read_bytes() + b"\0" * (limit + 1024 * 1024))
    script = tmp_path / "upload.py"
    script.write_text(_UPLOAD_UNDER_A_FILE_SIZE_LIMIT)
    args = [str(api.settings.data_dir), api.key, str(seeded.session_id), str(big_left)]
    proc = subprocess.run(
        [sys.executable, str(script), *args, str(video_pair[1]), str(limit)],
        capture_output=True, text=True, check=False, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    answer = json.loads(proc.stdout.strip().splitlines()[-1])
    assert answer["status"] == 507, answer  # before: 500 "Internal error"
    assert json.loads(answer["body"])["detail"] == faults.FILE_TOO_LARGE
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert api.recording_rows() == before and api.stored_files() == files_before


# --------------------------------------------------------------------------- finding 6


class _Records(logging.Handler):
    """Sets ``seen`` at the first warning (or worse) of the job queue or the worker."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.seen = threading.Event()

    def emit(self, record: logging.LogRecord) -> None:
        if record.name in ("app.jobs", "app.worker"):
            self.seen.set()


@pytest.mark.postgres
def test_a_short_database_outage_during_a_job_spends_no_attempt(proxied, wait_for) -> None:
    """The database goes away for a moment while a job reports its progress: the job
    keeps its work and finishes on its first attempt (before: "unexpected error", then
    "ended without its outcome recorded", and a second attempt)."""
    settings, proxy = proxied
    settings = settings.model_copy(update={"job_lease_s": 30.0, "job_heartbeat_s": 0.2})
    sessions = get_sessionmaker(settings)
    with sessions() as db, db.begin():
        job_id = jobs.enqueue(db, "outage_probe", max_attempts=3).id
    started, resume, runs = threading.Event(), threading.Event(), []

    def handler(ctx: JobContext) -> None:
        runs.append(ctx.job.attempts)
        started.set()
        while not resume.is_set():
            ctx.progress("measuring", len(runs), 2)  # writes every 0.5 s
            resume.wait(0.05)
        ctx.finish()

    records = _Records()
    logging.getLogger("app").addHandler(records)
    stop = threading.Event()
    worker = threading.Thread(
        target=run_worker,
        args=(settings,),
        kwargs={"stop_event": stop, "handlers": {"outage_probe": handler}},
    )
    worker.start()
    try:
        assert started.wait(30), "the worker did not start the job"
        proxy.stop()
        assert records.seen.wait(30), "no heartbeat met the outage"
        proxy.start()
        resume.set()
        wait_for(lambda: _job(sessions, job_id).status in ("succeeded", "failed"), timeout_s=60,
                 what="the job's end")  # fmt: skip
    finally:
        resume.set()
        stop.set()
        proxy.start()
        worker.join(60)
        logging.getLogger("app").removeHandler(records)
    job = _job(sessions, job_id)
    assert (job.status, job.attempts, runs) == ("succeeded", 1, [1]), (job.status, job.error)


def _job(sessions, job_id: int) -> Job:
    with sessions() as db:
        job = db.get(Job, job_id)
        assert job is not None
        return job


# --------------------------------------------------------------------------- finding 11

PATIENT_FILE = "pacient_Novak_Jan_left.mp4"


@pytest.mark.parametrize(
    "error",
    [
        InputError(f"the left video ({PATIENT_FILE}) ends after 199 of 600 frames"),
        RetryableJobError(f"the left video ({PATIENT_FILE}) is missing on this worker"),
        InsufficientStorageError(f"the left video ({PATIENT_FILE}) could not be written"),
    ],
    ids=["input", "retryable", "storage"],
)
def test_the_worker_log_names_no_uploaded_file(
    app_settings: Settings, db_sessionmaker, caplog, error: Exception
) -> None:
    """Clinics name files after patients: the worker's log says the error's kind and the
    job's trial, the job keeps the sentence (before: the sentence, file name and all)."""
    with db_sessionmaker() as db, db.begin():
        job_id = jobs.enqueue(db, "name_probe", max_attempts=3).id

    def handler(ctx: JobContext) -> None:
        raise error

    with caplog.at_level(logging.DEBUG):
        run_worker(app_settings, once=True, max_jobs=1, handlers={"name_probe": handler})
    assert PATIENT_FILE in (_job(db_sessionmaker, job_id).error or "")
    assert f"job {job_id} (name_probe)" in caplog.text
    assert type(error).__name__ in caplog.text
    assert "Novak" not in caplog.text, caplog.text


@pytest.mark.postgres
def test_a_job_stopped_by_the_database_going_away_is_given_back_without_an_attempt(
    proxied,
) -> None:
    """The database goes away just as a job stores its result: the worker gives the job
    back (postponed, its attempt not spent) once the database returns, within the lease
    (before: "ended without its outcome recorded"; its lease ran out and the next claim
    spent an attempt)."""
    settings, proxy = proxied
    settings = settings.model_copy(update={"job_lease_s": 3.0, "job_heartbeat_s": 0.2})
    sessions = get_sessionmaker(settings)
    with sessions() as db, db.begin():
        job_id = jobs.enqueue(db, "outage_probe", max_attempts=3).id

    class _Retrying(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if "not given back yet" in record.getMessage():
                proxy.start()  # the database returns once the worker has met its absence

    def handler(ctx: JobContext) -> None:
        proxy.stop()
        ctx.finish()

    retrying = _Retrying(logging.WARNING)
    logging.getLogger("app.worker").addHandler(retrying)
    try:
        run_worker(settings, once=True, max_jobs=1, handlers={"outage_probe": handler})
    finally:
        logging.getLogger("app.worker").removeHandler(retrying)
        proxy.start()
    job = _job(sessions, job_id)
    assert (job.status, job.attempts) == ("queued", 0), (job.status, job.attempts, job.error)
    assert "The job waits and retries by itself." in (job.error or "")

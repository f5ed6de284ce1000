"""Shared fixtures for the service tests (tests/app/). Stable: other test files rely on them.

Fixtures
--------
``make_settings`` : callable ``(data_dir, **overrides) -> Settings``
    Test settings (short lease, no retry delay) for a data directory of your
    own; nothing is migrated (call ``app.db.migrate``).
``app_settings`` : app.settings.Settings
    A fresh data directory (``tmp_path / "data"``) with an SQLite database
    already migrated to head **by Alembic** (copied from a once-per-run
    template, so each test costs a file copy, not a migration). Short job
    lease (5 s) and no retry delay so that retry tests do not wait.
``db_sessionmaker`` : sqlalchemy.orm.sessionmaker
    Bound to ``app_settings``' database (``expire_on_commit=False``).
``db_session`` : sqlalchemy.orm.Session
    One open session, closed (not committed) after the test.
``storage`` : app.storage.Storage
    Files under ``app_settings.data_dir``.
``pg_settings`` : app.settings.Settings
    Like ``app_settings`` but on a PostgreSQL database created for this test on
    127.0.0.1:5432 (dropped afterwards), migrated by Alembic. Mark tests using it
    ``@pytest.mark.postgres``. Skips when the server is unreachable, except when
    the ``CI`` environment variable is set: then it fails.
``pg_admin_url`` : str
    URL of the maintenance database ``test`` (for creating/dropping databases).
``pg_empty_url`` : str
    URL of a new, empty PostgreSQL database (dropped after the test).
``wait_for`` : callable ``(condition, *, timeout_s, what)``
    Poll ``condition()`` until truthy; fails with ``what`` after the deadline.
``worker_script`` : Path
    A worker process script whose ``analyze_trial`` handler blocks on a gate file.
``kill9_scenario`` : callable ``(settings, worker_script)``
    The kill -9 take-over scenario (used on SQLite and PostgreSQL).

Engines are cached per database URL by ``app.db.get_engine``; every fixture
disposes them at teardown.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker
from tcp_proxy import TcpProxy

from app.db import dispose_engines, get_sessionmaker, migrate
from app.settings import Settings
from app.storage import Storage

PG_SERVER = os.environ.get("BRADYSCOPE_TEST_PG", "postgresql+psycopg://postgres@127.0.0.1:5432")
SQLITE_NAME = "bradyscope.sqlite3"


def make_test_settings(data_dir: Path, **overrides: object) -> Settings:
    """Settings for tests: given data dir, short lease, no retry delay, fast polling."""
    values: dict[str, object] = {
        "data_dir": data_dir,
        "job_lease_s": 5.0,
        "job_retry_delay_s": 0.0,
        "worker_poll_s": 0.05,
        "max_upload_bytes": 50 * 1024 * 1024,
    }
    values.update(overrides)
    return Settings(**values)  # type: ignore[arg-type]


@pytest.fixture
def make_settings() -> object:
    return make_test_settings


@pytest.fixture(scope="session")
def _migrated_sqlite_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    data_dir = tmp_path_factory.mktemp("template-data")
    settings = make_test_settings(data_dir)
    migrate(settings)
    dispose_engines()  # checkpoints the WAL into the main file
    for extra in ("-wal", "-shm"):
        (data_dir / (SQLITE_NAME + extra)).unlink(missing_ok=True)
    return data_dir / SQLITE_NAME


@pytest.fixture
def app_settings(tmp_path: Path, _migrated_sqlite_template: Path) -> Iterator[Settings]:
    data_dir = tmp_path / "data"
    data_dir.mkdir()
    shutil.copyfile(_migrated_sqlite_template, data_dir / SQLITE_NAME)
    yield make_test_settings(data_dir)
    dispose_engines()


@pytest.fixture
def db_sessionmaker(app_settings: Settings) -> sessionmaker[Session]:
    return get_sessionmaker(app_settings)


@pytest.fixture
def db_session(db_sessionmaker: sessionmaker[Session]) -> Iterator[Session]:
    with db_sessionmaker() as session:
        yield session


@pytest.fixture
def storage(app_settings: Settings) -> Storage:
    return Storage.from_settings(app_settings)


# --------------------------------------------------------------------------- PostgreSQL


@pytest.fixture(scope="session")
def pg_admin_url() -> str:
    import sqlalchemy as sa

    url = f"{PG_SERVER}/test"
    try:
        engine = sa.create_engine(url)
        with engine.connect() as conn:
            conn.execute(sa.text("SELECT 1"))
        engine.dispose()
    except Exception as exc:  # unreachable server: skip locally, fail in CI
        if os.environ.get("CI"):
            pytest.fail(f"PostgreSQL at {url} is unreachable in CI: {exc}")
        pytest.skip(f"PostgreSQL at {url} is unreachable: {exc}")
    return url


def create_pg_database(admin_url: str) -> str:
    """Create a uniquely named database; returns its URL."""
    import sqlalchemy as sa

    name = f"bradyscope_test_{uuid.uuid4().hex[:12]}"
    engine = sa.create_engine(admin_url, isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.execute(sa.text(f'CREATE DATABASE "{name}"'))
    engine.dispose()
    return f"{PG_SERVER}/{name}"


def drop_pg_database(admin_url: str, url: str) -> None:
    import sqlalchemy as sa

    name = url.rsplit("/", 1)[1]
    engine = sa.create_engine(admin_url, isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    engine.dispose()


@pytest.fixture
def pg_empty_url(pg_admin_url: str) -> Iterator[str]:
    """URL of a new, empty PostgreSQL database (dropped after the test)."""
    url = create_pg_database(pg_admin_url)
    try:
        yield url
    finally:
        dispose_engines()
        drop_pg_database(pg_admin_url, url)


@pytest.fixture
def pg_settings(tmp_path: Path, pg_empty_url: str) -> Settings:
    data_dir = tmp_path / "data"
    data_dir.mkdir()
    settings = make_test_settings(data_dir, database_url=pg_empty_url)
    migrate(settings)
    return settings


@pytest.fixture
def proxied(pg_settings: Settings) -> Iterator[tuple[Settings, TcpProxy]]:
    """``pg_settings`` reaching the server through a proxy (started), which a test stops
    and starts to take the database away and give it back."""
    proxy = TcpProxy(("127.0.0.1", 5432))
    proxy.start()
    url = sa.make_url(pg_settings.database_url).set(host="127.0.0.1", port=proxy.port)
    settings = pg_settings.model_copy(
        update={"database_url": url.render_as_string(hide_password=False)}
    )
    try:
        yield settings, proxy
    finally:
        proxy.stop()
        dispose_engines()


# --------------------------------------------------------------------------- worker processes

WORKER_SCRIPT = r'''
"""A bradyscope worker process whose 'analyze_trial' handler blocks on a gate file."""
import os
import sys
import time
from pathlib import Path

from app.models import Result
from app.settings import Settings
from app.worker import run_worker

data_dir, db_url, lease_s, max_jobs = sys.argv[1], sys.argv[2] or None, float(sys.argv[3]), int(sys.argv[4])
settings = Settings(
    data_dir=data_dir, database_url=db_url, job_lease_s=lease_s, job_heartbeat_s=lease_s / 5,
    worker_poll_s=0.05, job_retry_delay_s=0.0,
)
gate = Path(data_dir) / "gate"
log = Path(data_dir) / "executions.log"


def note(ctx, what):
    with open(log, "a") as fh:  # O_APPEND: one short line per write is atomic
        fh.write(f"{ctx.job.id} {os.getpid()} {what}\n")


def handler(ctx):
    note(ctx, "start")
    while not gate.exists():
        ctx.progress("waiting for gate", 0, 1)  # extends the lease; raises if lost
        time.sleep(0.01)
    def write(db):
        if ctx.job.trial_id is not None:
            db.add(Result(trial_id=ctx.job.trial_id, job_id=ctx.job.id,
                          document={"pid": os.getpid()}))
    ctx.finish(write)
    note(ctx, "done")


run_worker(settings, handlers={"analyze_trial": handler}, once=max_jobs == 0,
           max_jobs=max_jobs or None, worker_name=f"test-{os.getpid()}")
'''


@pytest.fixture(scope="session")
def worker_script(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Path of a Python script running a worker whose ``analyze_trial`` handler waits for
    the file ``<data_dir>/gate``, logs ``"<job id> <pid> start|done"`` lines to
    ``<data_dir>/executions.log`` and stores a Result ``{"pid": pid}`` for the job's trial.

    Arguments: ``DATA_DIR DATABASE_URL('' = SQLite) LEASE_S MAX_JOBS(0 = drain the queue and exit)``.
    """
    path = tmp_path_factory.mktemp("worker") / "gated_worker.py"
    path.write_text(WORKER_SCRIPT)
    return path


def _wait_for(condition, *, timeout_s: float, what: str):  # type: ignore[no-untyped-def]
    """Poll ``condition()`` until it returns a truthy value (deadline, not a timing sleep)."""
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.02)


def kill9_takeover(settings: Settings, script: Path, *, lease_s: float = 3.0) -> None:
    """Kill -9 a worker mid-job; a second worker must complete the job with one Result."""
    import signal
    import subprocess
    import sys
    from datetime import UTC, datetime

    import sqlalchemy as sa

    from app import jobs
    from app.models import Job, Patient, RecordingSession, Result, Rig, Trial

    sm = get_sessionmaker(settings)
    with sm() as db, db.begin():
        rig, patient = Rig(name="kill-rig"), Patient(code="PD-KILL")
        db.add_all([rig, patient])
        db.flush()
        session = RecordingSession(
            patient_id=patient.id, rig_id=rig.id, recorded_at=datetime(2026, 2, 1, tzinfo=UTC)
        )
        db.add(session)
        db.flush()
        trial = Trial(session_id=session.id, hand="left")
        db.add(trial)
        db.flush()
        trial_id = trial.id
        job_id = jobs.enqueue(db, "analyze_trial", trial_id=trial_id).id

    def job() -> Job:
        with sm() as db:
            return db.get(Job, job_id)

    args = [
        sys.executable,
        str(script),
        str(settings.data_dir),
        settings.database_url or "",
        str(lease_s),
        "1",
    ]
    first = subprocess.Popen(args)
    try:
        running = _wait_for(
            lambda: (j := job()).status == "running" and j,
            timeout_s=60,
            what="the first worker to claim the job",
        )
        first_owner = running.lease_owner
        assert first_owner.startswith(f"test-{first.pid}:")
        # Its heartbeat keeps the lease alive beyond the lease period.
        _wait_for(
            lambda: job().heartbeat_at > running.heartbeat_at, timeout_s=30, what="a heartbeat"
        )
        assert jobs.claim_next(sm, worker_name="thief", lease_s=lease_s) is None
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=30)
    assert first.returncode == -signal.SIGKILL
    (settings.data_dir / "gate").touch()

    second = subprocess.Popen(args)
    try:
        assert second.wait(timeout=60) == 0
    finally:
        if second.poll() is None:
            second.kill()
    done = job()
    assert done.status == "succeeded", done.error
    assert done.attempts == 2
    assert done.lease_owner.startswith(f"test-{second.pid}:")
    with sm() as db:
        results = db.scalars(sa.select(Result).where(Result.trial_id == trial_id)).all()
        assert [r.document for r in results] == [{"pid": second.pid}]
        assert db.get(Trial, trial_id).status == "succeeded"
    lines = (settings.data_dir / "executions.log").read_text().split()
    assert lines == [
        str(job_id),
        str(first.pid),
        "start",
        str(job_id),
        str(second.pid),
        "start",
        str(job_id),
        str(second.pid),
        "done",
    ]


@pytest.fixture
def wait_for():  # type: ignore[no-untyped-def]
    """``wait_for(condition, *, timeout_s, what)``: poll a condition until true (or fail)."""
    return _wait_for


@pytest.fixture
def kill9_scenario():  # type: ignore[no-untyped-def]
    """``kill9_scenario(settings, worker_script)``: see :func:`kill9_takeover`."""
    return kill9_takeover

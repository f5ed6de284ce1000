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
from sqlalchemy.orm import Session, sessionmaker

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

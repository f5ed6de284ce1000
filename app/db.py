"""Database engine, sessions, and migrations run once under a start-up lock.

- :func:`make_engine` — an engine for the settings; on SQLite every connection
  gets ``journal_mode=WAL``, ``busy_timeout`` and ``foreign_keys=ON``.
- :func:`get_engine` / :func:`get_sessionmaker` — cached per database URL.
- :func:`migrate` — Alembic ``upgrade head`` under a lock (a file lock in the
  data directory for SQLite, ``pg_advisory_lock`` for PostgreSQL). Call it once
  per process start (``serve``, ``worker``, ``admin``), never per request or
  per web worker.
- :func:`alembic_config` — Alembic configured programmatically (no
  ``alembic.ini`` needed); ``migrations/`` sits at the repository root.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TextIO

from sqlalchemy import create_engine, event, text
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.orm import Session, sessionmaker

from app.chain import register_key_file
from app.errors import ServiceUnavailableError
from app.settings import Settings

log = logging.getLogger(__name__)

MIGRATIONS_DIR = Path(__file__).resolve().parents[1] / "migrations"
# An arbitrary constant identifying bradyscope's migration lock among advisory locks.
PG_MIGRATION_LOCK_KEY = 0x6272_6164_7973  # "bradys"

_engines: dict[str, Engine] = {}
_engines_lock = threading.Lock()


def _sqlite_pragmas(busy_timeout_ms: int) -> Callable[[Any, Any], None]:
    def on_connect(dbapi_connection: Any, connection_record: Any) -> None:
        cursor = dbapi_connection.cursor()
        try:
            cursor.execute(f"PRAGMA busy_timeout = {int(busy_timeout_ms)}")
            cursor.execute("PRAGMA journal_mode = WAL")
            cursor.execute("PRAGMA synchronous = NORMAL")
            cursor.execute("PRAGMA foreign_keys = ON")
        finally:
            cursor.close()

    return on_connect


def make_engine(settings: Settings, **kwargs: Any) -> Engine:
    """A new engine for ``settings.effective_database_url``.

    SQLite: the data directory is created; the pysqlite driver keeps its
    default transaction handling (BEGIN just before the first write), so a
    read-then-write unit of work waits on ``busy_timeout`` instead of failing.
    The audit chain's key file (``settings.audit_key_path``) is registered for
    the engine (read or created at the first audit event). The statements' values
    are left out of SQLAlchemy's error texts (``hide_parameters``): they hold
    patient codes, notes and file names, and a failed write's error is logged.
    """
    url = settings.effective_database_url
    kwargs.setdefault("hide_parameters", True)
    if url.startswith("sqlite"):
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        connect_args = {
            "timeout": settings.sqlite_busy_timeout_ms / 1000,
            "check_same_thread": False,
        }
        engine = create_engine(url, connect_args=connect_args, **kwargs)
        event.listen(engine, "connect", _sqlite_pragmas(settings.sqlite_busy_timeout_ms))
    else:
        engine = create_engine(url, pool_pre_ping=True, **kwargs)
    # The audit trail of this database is sealed with the key kept beside its files.
    register_key_file(engine, settings.audit_key_path)
    return engine


def get_engine(settings: Settings) -> Engine:
    """The process-wide engine for the settings' database URL (created once)."""
    url = settings.effective_database_url
    with _engines_lock:
        engine = _engines.get(url)
        if engine is None:
            engine = make_engine(settings)
            _engines[url] = engine
        return engine


def dispose_engines() -> None:
    """Close every cached engine (tests, and after ``fork``)."""
    with _engines_lock:
        for engine in _engines.values():
            engine.dispose()
        _engines.clear()


def get_sessionmaker(settings: Settings) -> sessionmaker[Session]:
    """A session factory bound to :func:`get_engine` (``expire_on_commit=False``)."""
    return sessionmaker(bind=get_engine(settings), expire_on_commit=False)


@contextlib.contextmanager
def session_scope(settings: Settings) -> Iterator[Session]:
    """One unit of work: commit on success, roll back on any exception."""
    factory = get_sessionmaker(settings)
    with factory() as db, db.begin():
        yield db


# --------------------------------------------------------------------------- migrations


def alembic_config(
    url: str, *, connection: Connection | None = None, stdout: TextIO | None = None
) -> Any:
    """An Alembic ``Config`` for ``url`` pointing at ``migrations/``.

    With ``connection``, ``env.py`` runs the migration on that connection
    (used to hold the PostgreSQL advisory lock on the same connection).
    Alembic's messages go to ``stdout`` (default: the current ``sys.stdout``).
    """
    from alembic.config import Config

    cfg = Config(stdout=stdout if stdout is not None else sys.stdout)
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    # ConfigParser interpolation: a literal '%' in a URL (encoded password) must be doubled.
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    if connection is not None:
        cfg.attributes["connection"] = connection
    return cfg


@contextlib.contextmanager
def _file_lock(path: Path, timeout_s: float) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise ServiceUnavailableError(
                        f"another bradyscope process has held the migration lock {path} for "
                        f"more than {timeout_s:.0f} s; check that no migration is stuck."
                    ) from None
                time.sleep(0.05)
        yield
    finally:
        os.close(fd)  # closing releases the lock


def head_revision() -> str:
    """The newest revision in ``migrations/versions``."""
    from alembic.script import ScriptDirectory

    script = ScriptDirectory.from_config(alembic_config("sqlite://"))
    head = script.get_current_head()
    if head is None:
        raise RuntimeError("migrations/versions holds no revision")
    return head


def current_revision(settings: Settings) -> str | None:
    """The revision the database is at (None for an empty database)."""
    from alembic.runtime.migration import MigrationContext

    with get_engine(settings).connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def migrate(settings: Settings, *, revision: str = "head") -> None:
    """Bring the database to ``revision`` (default: the newest) under the start-up lock.

    Safe to call from several processes at once: one migrates, the others wait
    for it and then find nothing to do.

    Raises
    ------
    ServiceUnavailableError
        When the database cannot be reached or the lock is not obtained in time.
    """
    from alembic import command
    from sqlalchemy.exc import OperationalError

    url = settings.effective_database_url
    try:
        if settings.is_sqlite:
            settings.data_dir.mkdir(parents=True, exist_ok=True)
            with _file_lock(settings.data_dir / ".migrate.lock", settings.migration_lock_timeout_s):
                engine = get_engine(settings)
                with engine.begin() as conn:
                    command.upgrade(alembic_config(url, connection=conn), revision)
        else:
            engine = get_engine(settings)
            with engine.connect() as conn:
                timeout_ms = int(settings.migration_lock_timeout_s * 1000)
                conn.execute(text(f"SET lock_timeout = {timeout_ms}"))
                conn.execute(text("SELECT pg_advisory_lock(:k)"), {"k": PG_MIGRATION_LOCK_KEY})
                conn.commit()
                try:
                    with conn.begin():
                        command.upgrade(alembic_config(url, connection=conn), revision)
                finally:
                    conn.execute(
                        text("SELECT pg_advisory_unlock(:k)"), {"k": PG_MIGRATION_LOCK_KEY}
                    )
                    conn.execute(text("RESET lock_timeout"))
                    conn.commit()
    except OperationalError as exc:
        reason = " ".join(str(exc.orig).split())[:300]
        raise ServiceUnavailableError(
            f"the database at {_redacted(url)} cannot be reached ({reason}); check "
            "BRADYSCOPE_DATABASE_URL and that the database server is running."
        ) from exc
    log.info("database %s is at revision %s", _redacted(url), revision)


def _redacted(url: str) -> str:
    from sqlalchemy.engine import make_url

    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # a malformed URL is reported as given, minus nothing to hide
        return url

"""Storage faults in plain words, and the health check that looks for them.

A full disk or a read-only data directory used to surface as a bare 500.
:func:`storage_fault` recognises the operating system's and the databases'
ways of saying so and turns them into the service's errors:

- disk full (``ENOSPC``, ``EDQUOT``, SQLite ``SQLITE_FULL``, PostgreSQL
  ``53100 disk_full``) -> :class:`InsufficientStorageError` (507); a file larger
  than the file system (FAT, exFAT) or the process's limit (``RLIMIT_FSIZE``)
  allows (``EFBIG``) too, with its own sentence;
- read-only (``EROFS``; the database: SQLite ``SQLITE_READONLY``, PostgreSQL
  ``25006``, each named as such), a storage I/O error, or an unreachable
  database -> 503. Unreachable: a
  connection refused or cut, a database not accepting connections (psycopg's
  errors without a SQLSTATE, ``08xxx``, ``57P0x``), a SQLite file that cannot be
  opened (missing, or on a read-only disk where its ``-wal`` cannot be made).

Nothing is half-written when they happen: an upload's files are removed
(``app.uploads.run_upload``) and the request's transaction is rolled back, so
no row points at a missing file. Reads fail too while the database cannot be
written, because every read writes its audit event: failing closed is right,
and the answer says why.

:func:`check_health` is what ``GET /health`` answers: the database answers a
query and takes a write (rolled back), and a file can be written, fsynced and
removed in the data directory (both writes at most every
:data:`WRITE_CHECK_INTERVAL_S` seconds; their verdicts are kept in between).
The answer names no path, and tells the data directory's free space only to an
authenticated caller.
"""

from __future__ import annotations

import contextlib
import errno
import os
import threading
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from time import monotonic
from typing import Any

from sqlalchemy import text
from sqlalchemy.engine import Engine
from sqlalchemy.exc import DBAPIError, OperationalError

from app.errors import (
    AppError,
    InsufficientStorageError,
    ServiceUnavailableError,
    StorageReadOnlyError,
)

FULL = (
    "The server's storage is full, so nothing was saved; ask the administrator to free disk"
    " space, then retry."
)
READ_ONLY = (
    "The server's storage refuses writes (read-only), so nothing was saved; ask the"
    " administrator to check the data directory's disk, then retry."
)
READ_ONLY_DATABASE = (
    "The database refuses writes (read-only), so nothing was saved; ask the administrator to"
    " check the database (a standby server, default_transaction_read_only, or the database"
    " file's permissions), then retry."
)
FILE_TOO_LARGE = (
    "The file is larger than the data directory's file system or limits allow, so nothing was"
    " saved; ask the administrator to check the disk's format (FAT and exFAT take files"
    " under 4 GB) or the service's file size limit (LimitFSIZE, ulimit -f), then retry."
)
IO_ERROR = (
    "The server's storage reported an input/output error, so nothing was saved; ask the"
    " administrator to check the disk, then retry."
)
DATABASE_DOWN = (
    "The database cannot be reached right now, so nothing was done; retry in a moment or ask"
    " the administrator."
)
DATABASE_FILE_UNOPENED = (
    "The database file cannot be opened (it is missing, or its disk refuses writes), so"
    " nothing was saved; ask the administrator to check it, then retry."
)

_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
_READ_ONLY_ERRNOS = frozenset({errno.EROFS})
_IO_ERRNOS = frozenset({errno.EIO})


def _sqlite_fault(orig: Any) -> AppError | None:
    name = str(getattr(orig, "sqlite_errorname", "") or "")
    message = str(orig).lower()
    if name == "SQLITE_FULL" or "database or disk is full" in message:
        return InsufficientStorageError(FULL)
    if name.startswith("SQLITE_READONLY") or "readonly database" in message:
        return StorageReadOnlyError(READ_ONLY_DATABASE)
    if name.startswith("SQLITE_CANTOPEN") or "unable to open database file" in message:
        return ServiceUnavailableError(DATABASE_FILE_UNOPENED)  # gone, or no -wal/-shm made
    if name.startswith("SQLITE_IOERR") or "disk i/o error" in message:
        return StorageReadOnlyError(IO_ERROR)
    return None


def _postgres_fault(orig: Any, *, operational: bool) -> AppError | None:
    if not hasattr(orig, "sqlstate"):  # not psycopg's
        return None
    sqlstate = str(orig.sqlstate or "")
    if sqlstate == "53100":  # disk_full
        return InsufficientStorageError(FULL)
    if (
        sqlstate == "25006"
    ):  # read_only_sql_transaction (a standby, or default_transaction_read_only)
        return StorageReadOnlyError(READ_ONLY_DATABASE)
    if sqlstate.startswith("08") or sqlstate in ("57P01", "57P02", "57P03"):
        return ServiceUnavailableError(DATABASE_DOWN)
    if sqlstate == "55000" and "accepting connections" in str(orig):  # ALLOW_CONNECTIONS false
        return ServiceUnavailableError(DATABASE_DOWN)
    if operational and not sqlstate:
        # The server said nothing: psycopg could not connect (refused, timed out, the
        # database not accepting connections) or the connection broke. Errors of SQL
        # itself always carry a SQLSTATE.
        return ServiceUnavailableError(DATABASE_DOWN)
    return None


def storage_fault(exc: BaseException) -> AppError | None:
    """The service error for a storage or database fault, or None if ``exc`` is something else."""
    if isinstance(exc, DBAPIError):
        orig = exc.orig
        operational = isinstance(exc, OperationalError)
        fault = _sqlite_fault(orig) or _postgres_fault(orig, operational=operational)
        if fault is None and exc.connection_invalidated:
            fault = ServiceUnavailableError(DATABASE_DOWN)
        return fault
    if isinstance(exc, OSError):
        if exc.errno in _FULL_ERRNOS:
            return InsufficientStorageError(FULL)
        if exc.errno == errno.EFBIG:
            return InsufficientStorageError(FILE_TOO_LARGE)
        if exc.errno in _READ_ONLY_ERRNOS:
            return StorageReadOnlyError(READ_ONLY)
        if exc.errno in _IO_ERRNOS:
            return StorageReadOnlyError(IO_ERROR)
    cause = exc.__cause__ or exc.__context__
    if cause is not None and cause is not exc and isinstance(cause, OSError | DBAPIError):
        return storage_fault(cause)
    return None


# --------------------------------------------------------------------------- health


@dataclass
class Health:
    """The answer of ``GET /health``: ``ok`` and each check's verdict."""

    checks: dict[str, str] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    free_bytes: int | None = None

    @property
    def ok(self) -> bool:
        return not self.problems

    def as_document(self, *, free_bytes: bool = False) -> dict[str, Any]:
        """The JSON answer; ``free_bytes``: with ``data_dir_free_bytes`` (for an
        authenticated caller: it tells how fast recordings arrive, nobody else's business)."""
        doc: dict[str, Any] = {"status": "ok" if self.ok else "unavailable", **self.checks}
        if free_bytes and self.free_bytes is not None:
            doc["data_dir_free_bytes"] = self.free_bytes
        if self.problems:
            doc["detail"] = " ".join(self.problems)
        return doc


def _check_database(engine: Engine) -> str | None:
    """The database answers a query (each call), and takes a write (every few seconds)."""
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1")).scalar_one()
    except Exception as exc:  # any failure is the answer: the database does not answer
        fault = storage_fault(exc)
        reason = str(fault) if fault is not None else DATABASE_DOWN
        return f"Database: {reason}"
    key = ("database", engine.url.render_as_string(hide_password=True))
    return _cached(key, lambda: _probe_database_write(engine))


def _probe_database_write(engine: Engine) -> str | None:
    """Write to the database and roll back: None, or why it cannot be written.

    Every request writes (its audit event): a database that answers queries but refuses
    writes (a standby, ``default_transaction_read_only``, a read-only SQLite file) fails
    them all. The write changes nothing (alembic's one row set to itself) and is rolled
    back; another writer holding SQLite's lock shows that it can be written.
    """
    try:
        with engine.connect() as conn:
            transaction = conn.begin()
            try:
                conn.execute(text("UPDATE alembic_version SET version_num = version_num"))
            finally:
                transaction.rollback()
    except Exception as exc:
        if "database is locked" in str(exc):  # SQLite: another writer, so it takes writes
            return None
        fault = storage_fault(exc)
        reason = (
            str(fault) if fault is not None else f"it cannot be written ({type(exc).__name__})."
        )
        return f"Database: {reason}"
    return None


WRITE_CHECK_INTERVAL_S = 5.0
"""The write checks (data directory, database) run at most this often; calls in between
answer their last verdict, so unauthenticated callers of ``/health`` cannot make the server
write (and fsync) in a loop."""

_write_checks: dict[object, tuple[float, str | None]] = {}
_write_checks_lock = threading.Lock()


def _cached(key: object, probe: Callable[[], str | None]) -> str | None:
    """``probe()``'s verdict, made at most every :data:`WRITE_CHECK_INTERVAL_S` seconds per
    ``key`` (concurrent callers wait for one probe)."""
    with _write_checks_lock:
        now = monotonic()
        last = _write_checks.get(key)
        if last is not None and now - last[0] < WRITE_CHECK_INTERVAL_S:
            return last[1]
        problem = probe()
        _write_checks[key] = (monotonic(), problem)
        return problem


def _probe_write(data_dir: Path) -> str | None:
    """Write, fsync and remove a file in the data directory: None, or what failed.

    The answer names no path: ``/health`` is public, and the data directory's location
    is the operator's business (the server's log and ``BRADYSCOPE_DATA_DIR`` tell them).
    """
    probe = data_dir / "tmp" / f".health-{uuid.uuid4().hex}"
    try:
        probe.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.write(fd, b"bradyscope health check\n" * 64)  # 1.5 KB: a page must be found
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        fault = storage_fault(exc)
        return (
            f"Data directory: {fault}"
            if fault is not None
            else f"Data directory: it cannot be written ({exc.strerror})."
        )
    finally:
        with contextlib.suppress(OSError):  # absent when it could not be made
            probe.unlink()
    return None


def _check_writable(data_dir: Path) -> str | None:
    """:func:`_probe_write`'s verdict, made at most every :data:`WRITE_CHECK_INTERVAL_S`
    seconds per data directory (concurrent callers wait for one probe)."""
    return _cached(("storage", data_dir), lambda: _probe_write(data_dir))


def check_health(engine: Engine, data_dir: Path) -> Health:
    """Whether the database answers and takes a write, and the data directory a file."""
    health = Health()
    for name, problem in (
        ("database", _check_database(engine)),
        ("storage", _check_writable(data_dir)),
    ):
        health.checks[name] = "ok" if problem is None else "failed"
        if problem is not None:
            health.problems.append(problem)
    try:
        stat = os.statvfs(data_dir)
        health.free_bytes = int(stat.f_bavail * stat.f_frsize)
    except OSError:
        health.free_bytes = None
    return health

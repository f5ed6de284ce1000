"""Backups: the database and every stored file, with a manifest of checksums; and restore.

``bradyscope admin backup DIR`` writes::

    DIR/
      manifest.json         format, time, database kind and migration revision,
                            and every file below with its size and SHA-256
      database.sqlite3      SQLite: a consistent copy made with SQLite's online
                            backup API (safe while the service runs)
      database.pgdump       PostgreSQL: pg_dump's custom format (pg_dump must be at
                            least the server's major version; checked first)
      files/...             a copy of <data dir>/files
      audit.key             the audit chain's secret key (keep the backup as safe as
                            the data directory itself)

A backup is made only of an audit trail that verifies whole
(:func:`app.audit_check.verify_trail`: the hash chain, an update's kept values
in ``field_changes`` and the patients in ``audit_event_patients`` against what
their events sealed): a backup is a restore point, and one holding a tampered
trail would pass the tampering on as the record. The database is copied first,
then the files: stored files are only ever added
(or removed by an erasure), so the copy holds every file the database copy
refers to, at worst a few more. ``restore DIR`` checks every checksum before
it changes anything, refuses to overwrite a database or data directory that
holds data (unless ``force``), puts the database and the files back, empties
the PDF report cache (``<data dir>/cache/reports``: derived from the database,
never backed up; reports of another database must not be served), brings
the database to the newest migration, and verifies the restored audit trail
whole: a restored trail that does not verify (a backup made by an older
version, or altered since) fails the restore, after the fact, with what to do.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import sqlite3
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import create_engine, inspect, text
from sqlalchemy.engine import make_url
from sqlalchemy.pool import NullPool

from app.audit_check import verify_trail
from app.chain import forget_key
from app.db import current_revision, dispose_engines, get_engine, get_sessionmaker, migrate
from app.errors import AppError, ConflictError, InvalidRequestError, ServiceUnavailableError
from app.models import Base, utcnow
from app.reports.pdf_cache import ReportPdfCache
from app.reports.trend_cache import TrendSvgCache
from app.settings import Settings
from app.storage import Storage, service_running
from app.storage import file_sha256 as _sha256
from app.storage import fsync_path as _fsync

MANIFEST = "manifest.json"
FORMAT = "bradyscope.backup/1"
SQLITE_FILE = "database.sqlite3"
PG_FILE = "database.pgdump"
AUDIT_KEY_FILE = "audit.key"
_CHUNK = 1024 * 1024
_TRAIL_PROBLEMS = 20
"""The problems of the audit trail counted before a backup or a restore says it fails."""


class BackupError(AppError):
    """A backup cannot be made or restored; the sentence says why and what to do."""

    http_status = 500


@dataclass(frozen=True)
class BackupSummary:
    """What a backup holds (or what a restore put back)."""

    directory: Path
    database: str
    revision: str | None
    files: int
    size_bytes: int


def _copy(src: Path, dst: Path) -> tuple[int, str]:
    """Copy one file (fsynced); returns its size and SHA-256."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    sha = hashlib.sha256()
    size = 0
    with open(src, "rb") as fin, open(dst, "wb") as fout:
        while block := fin.read(_CHUNK):
            sha.update(block)
            fout.write(block)
            size += len(block)
        fout.flush()
        os.fsync(fout.fileno())
    shutil.copystat(src, dst)
    return size, sha.hexdigest()


def trail_problems(settings: Settings) -> str | None:
    """How many problems the configured database's audit trail has, as words ("3 problems",
    "at least 20 problems"); None when it verifies whole (:func:`verify_trail`).

    Only the count leaves here: the problems name events and patients' ids, and
    ``bradyscope admin verify-audit`` lists them to whoever investigates.
    """
    with get_sessionmaker(settings)() as db:
        report = verify_trail(db, max_problems=_TRAIL_PROBLEMS)
    n = len(report.problems)
    if not n:
        return None
    return f"{'at least ' if n >= _TRAIL_PROBLEMS else ''}{n} problem{'' if n == 1 else 's'}"


def _sqlite_path(settings: Settings) -> Path:
    database = make_url(settings.effective_database_url).database
    if not database or database == ":memory:":
        raise BackupError("an in-memory SQLite database cannot be backed up.")
    return Path(database)


# --------------------------------------------------------------------------- PostgreSQL tools


def _pg_env(settings: Settings) -> dict[str, str]:
    """libpq's environment for the configured database (the password never on a command line)."""
    url = make_url(settings.effective_database_url)
    env = dict(os.environ)
    for name, value in (
        ("PGHOST", url.host),
        ("PGPORT", url.port),
        ("PGUSER", url.username),
        ("PGPASSWORD", url.password),
        ("PGDATABASE", url.database),
    ):
        if value is not None:
            env[name] = str(value)
    sslmode = url.query.get("sslmode")
    if isinstance(sslmode, str):
        env["PGSSLMODE"] = sslmode
    return env


def _tool_major(tool: str) -> int:
    try:
        out = subprocess.run(
            [tool, "--version"], capture_output=True, text=True, check=True, timeout=30
        ).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        raise BackupError(
            f"{tool} is needed to back up or restore PostgreSQL but cannot be run ({exc});"
            " install the PostgreSQL client tools (Debian: postgresql-client)."
        ) from exc
    match = re.search(r"(\d+)(?:\.\d+)?", out)
    if match is None:
        raise BackupError(f"cannot read the version of {tool} from {out.strip()!r}.")
    return int(match.group(1))


def _server_major(settings: Settings) -> int:
    with get_engine(settings).connect() as conn:
        number = int(conn.execute(text("SHOW server_version_num")).scalar_one())
    return number // 10000


def check_pg_tools(settings: Settings, tool: str) -> tuple[int, int]:
    """``(client major, server major)``; refuses a client older than the server."""
    client, server = _tool_major(tool), _server_major(settings)
    if client < server:
        raise BackupError(
            f"{tool} is version {client} but the database server is PostgreSQL {server}; an older"
            f" {tool} cannot read a newer server. Install postgresql-client-{server}."
        )
    return client, server


def _run(tool: str, args: list[str], env: dict[str, str]) -> None:
    proc = subprocess.run([tool, *args], env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        reason = " ".join(proc.stderr.split())[:500] or f"exit status {proc.returncode}"
        raise BackupError(f"{tool} failed: {reason}")


# --------------------------------------------------------------------------- backup


def _empty_target(target: Path) -> None:
    if target.exists() and (not target.is_dir() or any(target.iterdir())):
        raise ConflictError(
            f"{target} is not an empty directory; give a new directory for the backup."
        )
    target.mkdir(parents=True, exist_ok=True)
    target.chmod(0o700)  # patient data and the audit key


def backup(settings: Settings, target: Path) -> BackupSummary:
    """Back up the database, the stored files and the audit key into ``target`` (new or empty).

    Raises
    ------
    ConflictError
        ``target`` holds something already.
    BackupError
        The audit trail does not verify (nothing is written then), or the database could
        not be copied (``pg_dump`` missing or too old...).
    """
    target = target.expanduser().resolve()
    if target.is_relative_to(settings.data_dir):
        raise InvalidRequestError("put the backup outside the data directory it backs up.")
    problems = trail_problems(settings)
    if problems is not None:
        raise BackupError(
            f"no backup was made: the audit trail does not verify ({problems}), and a backup"
            " would keep the tampering as a restore point. Run 'bradyscope admin"
            " verify-audit' to see which events, investigate, and keep the last backup made"
            f" before them; nothing was written to {target}."
        )
    _empty_target(target)
    try:
        return _write_backup(settings, target)
    except (OSError, sqlite3.Error) as exc:
        # a half-written backup is no backup: leave the directory empty, as it was given
        for child in list(target.iterdir()):
            if child.is_dir():
                shutil.rmtree(child)
            else:
                child.unlink()
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise BackupError(
            f"the backup could not be written to {target} ({reason}); nothing was kept there:"
            " free space or choose another place, and back up again."
        ) from exc


def _write_backup(settings: Settings, target: Path) -> BackupSummary:
    """:func:`backup` into the empty directory ``target``."""
    revision = current_revision(settings)
    entries: list[dict[str, Any]] = []
    if settings.is_sqlite:
        kind, db_file = "sqlite", target / SQLITE_FILE
        source = sqlite3.connect(_sqlite_path(settings))
        try:
            copy = sqlite3.connect(db_file)
            try:
                source.backup(copy)  # online: a consistent snapshot while others write
            finally:
                copy.close()
        finally:
            source.close()
    else:
        kind, db_file = "postgresql", target / PG_FILE
        check_pg_tools(settings, "pg_dump")
        _run(
            "pg_dump",
            ["--format=custom", "--no-owner", "--no-privileges", f"--file={db_file}"],
            _pg_env(settings),
        )
    _fsync(db_file)
    entries.append(
        {"path": db_file.name, "size_bytes": db_file.stat().st_size, "sha256": _sha256(db_file)}
    )

    files_dir = settings.data_dir / "files"
    if files_dir.is_dir():
        for src in sorted(p for p in files_dir.rglob("*") if p.is_file()):
            rel = src.relative_to(settings.data_dir).as_posix()
            size, digest = _copy(src, target / rel)
            entries.append({"path": rel, "size_bytes": size, "sha256": digest})
    key = settings.audit_key_path
    if key.is_file():
        size, digest = _copy(key, target / AUDIT_KEY_FILE)
        (target / AUDIT_KEY_FILE).chmod(0o600)
        entries.append({"path": AUDIT_KEY_FILE, "size_bytes": size, "sha256": digest})

    manifest = {
        "format": FORMAT,
        "created_at": utcnow().isoformat().replace("+00:00", "Z"),
        "database": {"kind": kind, "file": db_file.name, "revision": revision},
        "files": entries,
    }
    partial = target / (MANIFEST + ".part")
    partial.write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    _fsync(partial)
    os.replace(partial, target / MANIFEST)  # the manifest last: its presence means complete
    _fsync(target)
    return BackupSummary(
        directory=target,
        database=kind,
        revision=revision,
        files=len(entries),
        size_bytes=sum(int(e["size_bytes"]) for e in entries),
    )


# --------------------------------------------------------------------------- restore


def read_manifest(source: Path) -> dict[str, Any]:
    """The backup's manifest, after checking that every file it lists is intact."""
    path = source / MANIFEST
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InvalidRequestError(
            f"{source} holds no {MANIFEST}; it is not a complete bradyscope backup."
        ) from None
    except (OSError, ValueError, RecursionError) as exc:
        raise InvalidRequestError(f"{path} cannot be read ({exc}).") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise InvalidRequestError(f"{path} is not a {FORMAT} manifest.")
    for entry in manifest.get("files", []):
        rel = str(entry.get("path", ""))
        file = (source / rel).resolve()
        if not rel or not file.is_relative_to(source.resolve()):
            raise InvalidRequestError(f"{path} lists a path outside the backup: {rel!r}.")
        if not file.is_file():
            raise InvalidRequestError(f"the backup is incomplete: {rel} is missing.")
        if file.stat().st_size != entry.get("size_bytes") or _sha256(file) != entry.get("sha256"):
            raise InvalidRequestError(
                f"the backup is damaged: {rel} differs from its checksum in the manifest;"
                " restore from another backup."
            )
    return manifest


def _refuse_while_running(settings: Settings) -> None:
    """A restore under a running service loses what it writes and fails the jobs it takes
    meanwhile (an operations review: a worker failed a trial on a file not yet copied
    back). Refused while a ``serve`` or ``worker`` runs on the data directory, or, on
    PostgreSQL, while anything else is connected to the database (workers elsewhere)."""
    stop = "stop every 'bradyscope serve' and 'bradyscope worker' first, then restore."
    if service_running(settings.data_dir):
        raise ConflictError(f"bradyscope is running on {settings.data_dir}; {stop}")
    if settings.is_sqlite:
        return
    dispose_engines()  # this process's own pooled connections are not others'
    engine = create_engine(settings.effective_database_url, poolclass=NullPool)
    try:
        with engine.connect() as conn:
            others = conn.execute(
                text(
                    "SELECT count(*) FROM pg_stat_activity"
                    " WHERE datname = current_database() AND pid <> pg_backend_pid()"
                )
            ).scalar_one()
    finally:
        engine.dispose()
    if others:
        raise ConflictError(f"{others} other connection(s) to the database are open; {stop}")


def _database_holds_data(settings: Settings) -> bool:
    engine = get_engine(settings)
    with engine.connect() as conn:
        present = set(inspect(conn).get_table_names())
        for table in Base.metadata.sorted_tables:
            if (
                table.name in present
                and conn.execute(text(f'SELECT 1 FROM "{table.name}" LIMIT 1')).first()
            ):
                return True
    return False


def _restore_database(settings: Settings, kind: str, db_file: Path) -> None:
    """Replace the configured database with the backup's copy ``db_file``."""
    if kind == "sqlite":
        dispose_engines()
        path = _sqlite_path(settings)
        path.parent.mkdir(parents=True, exist_ok=True)
        copy = sqlite3.connect(db_file)
        try:
            live = sqlite3.connect(path)
            try:
                copy.backup(live)  # page by page, in one transaction of the live file
            finally:
                live.close()
        finally:
            copy.close()
    else:
        check_pg_tools(settings, "pg_restore")
        dispose_engines()
        _run(
            "pg_restore",
            [
                "--clean",
                "--if-exists",
                "--no-owner",
                "--no-privileges",
                "--single-transaction",
                "--exit-on-error",
                f"--dbname={make_url(settings.effective_database_url).database}",
                str(db_file),
            ],
            _pg_env(settings),
        )


def _restore_files(
    settings: Settings, source: Path, manifest: dict[str, Any], *, skip: str, force: bool
) -> tuple[int, int]:
    """Copy the backup's files (all but ``skip``) back, each checked; (count, bytes) copied."""
    count, total = 0, 0
    for entry in manifest.get("files", []):
        rel = str(entry["path"])
        if rel == skip:
            continue
        dst = settings.audit_key_path if rel == AUDIT_KEY_FILE else settings.data_dir / rel
        if rel == AUDIT_KEY_FILE and dst.exists() and not force:
            if _sha256(dst) != entry["sha256"]:
                raise ConflictError(f"{dst} holds another audit key; move it away or pass --force.")
            continue
        size, digest = _copy(source / rel, dst)
        if digest != entry["sha256"]:
            raise BackupError(f"{rel} changed while it was restored; check the disk and retry.")
        if rel == AUDIT_KEY_FILE:
            dst.chmod(0o600)
            forget_key(dst)
        count += 1
        total += size
    return count, total


def restore(settings: Settings, source: Path, *, force: bool = False) -> BackupSummary:
    """Put a backup back into the configured database and data directory, then migrate.

    Every checksum is verified before anything changes. Without ``force`` the
    database and ``<data dir>/files`` must hold no data yet.

    Raises
    ------
    InvalidRequestError
        The backup is incomplete, damaged, or of another database kind.
    ConflictError
        The target holds data and ``force`` is not given.
    BackupError
        The restored audit trail does not verify: the backup is in place, and the
        sentence says so and what to do.
    """
    source = source.expanduser().resolve()
    manifest = read_manifest(source)
    database = manifest.get("database") or {}
    kind = "sqlite" if settings.is_sqlite else "postgresql"
    if database.get("kind") != kind:
        raise InvalidRequestError(
            f"this backup holds a {database.get('kind')} database but bradyscope is configured"
            f" for {kind}; set BRADYSCOPE_DATABASE_URL accordingly."
        )
    _refuse_while_running(settings)
    files_dir = settings.data_dir / "files"
    has_files = files_dir.is_dir() and any(p.is_file() for p in files_dir.rglob("*"))
    if not force and (has_files or _database_holds_data(settings)):
        raise ConflictError(
            "the database or the data directory already holds data; restore into an empty"
            " one, or pass --force to replace it (stop the service first)."
        )
    db_file = source / str(database.get("file"))
    _restore_database(settings, kind, db_file)
    if force and files_dir.is_dir():
        shutil.rmtree(files_dir)
    count, total = _restore_files(settings, source, manifest, skip=db_file.name, force=force)
    storage = Storage.from_settings(settings)
    ReportPdfCache.of(storage).clear()
    TrendSvgCache.of(storage).clear()
    count, total = count + 1, total + int(db_file.stat().st_size)
    (settings.data_dir / "tmp").mkdir(parents=True, exist_ok=True)
    migrate(settings)  # a backup of an older version is brought forward
    try:
        revision = current_revision(settings)
    except Exception as exc:  # pragma: no cover - the migration just succeeded
        raise ServiceUnavailableError(f"the restored database cannot be read ({exc}).") from exc
    problems = trail_problems(settings)
    if problems is not None:
        raise BackupError(
            f"the backup was restored, but its audit trail does not verify ({problems}):"
            " it was tampered with before the backup was made, or the backup was altered"
            " since. Do not start bradyscope on it: run 'bradyscope admin verify-audit' to see"
            " which events, then restore an earlier backup with --force, or investigate."
        )
    return BackupSummary(
        directory=source, database=kind, revision=revision, files=count, size_bytes=total
    )

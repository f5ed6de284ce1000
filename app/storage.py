"""Files under the data directory: server-generated paths and atomic writes.

Layout (``data_dir`` from the settings)::

    data_dir/
      bradyscope.sqlite3        (SQLite only)
      files/<category>/<2 hex>/<32 hex><suffix>   stored files (videos, results, rigs)
      tmp/                      partial uploads and writes; never referenced by the DB
      cache/reports/            trials' PDF reports made ahead (app.reports.pdf_cache):
                                derived, bounded, never backed up, emptied by a restore
      cache/trends/             patients' trend plots drawn once (app.reports.trend_cache):
                                the same

Paths stored in the database are **relative to data_dir** and always produced
here (never from a client's file name), e.g.
``files/videos/3f/3f2a...9c.mp4``. :meth:`Storage.absolute` refuses any path
that leaves ``data_dir/files``.

A file appears at its final path only complete and fsynced (write to ``tmp/``,
``os.replace``); a failed or rejected write leaves nothing behind.

Upload pattern (REST API)::

    with storage.receive("videos", ".mp4", max_bytes=settings.max_upload_bytes) as incoming:
        for chunk in chunks:
            incoming.write(chunk)           # PayloadTooLargeError past the limit
        info = probe_video(incoming.temp_path)  # rejects by real decoding
        stored = incoming.commit()          # StoredFile(path, size_bytes, sha256)
    # any exception inside the block removes the temporary file (and a committed one)
    try:
        ...insert Video(path=stored.path, ...) and commit...
    except BaseException:
        storage.delete(stored.path)        # the DB does not know it: remove it
        raise
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

from app.errors import PayloadTooLargeError, StorageError
from app.settings import Settings

_CATEGORY_RE = re.compile(r"^[a-z][a-z0-9_-]{0,31}$")
_SUFFIX_RE = re.compile(r"^(\.[a-z0-9]{1,8}){0,2}$")


SERVICE_LOCK = ".service.lock"
"""Held shared by every ``serve`` and ``worker`` on the data directory while it runs."""


def hold_service_lock(data_dir: Path) -> BinaryIO:
    """Mark this process as running on ``data_dir`` until it exits (a shared ``flock``,
    which the kernel drops with the process, also after ``kill -9``); ``admin restore``
    refuses while anyone holds it. Returns the open file: keep it."""
    import fcntl

    handle = open(data_dir / SERVICE_LOCK, "a+b")
    fcntl.flock(handle.fileno(), fcntl.LOCK_SH)
    return handle


def service_running(data_dir: Path) -> bool:
    """Whether a ``serve`` or ``worker`` holds :func:`hold_service_lock` on ``data_dir``."""
    import fcntl

    path = data_dir / SERVICE_LOCK
    if not path.exists():
        return False
    with open(path, "a+b") as handle:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(handle.fileno(), fcntl.LOCK_UN)
    return False


def close_to_others(data_dir: Path, *, umask: bool) -> None:
    """Close the data directory to other users of the machine (mode 0700).

    The directory holds the database, the videos and the reports: health data.
    With a common umask (022) everything in it would be readable by every
    local account; closing the directory itself shuts them out of all of it,
    also of files made before. ``umask``: also create every later file of this
    process for its user only (the long-running ``serve`` and ``worker``).
    """
    if umask:
        os.umask(0o077)
    data_dir.mkdir(parents=True, exist_ok=True)
    if data_dir.stat().st_mode & 0o077:
        try:
            data_dir.chmod(0o700)
        except PermissionError as exc:
            raise StorageError(
                f"the data directory {data_dir} is open to other users and cannot be closed "
                f"({exc.strerror}); run as its owner, or 'chmod 700' it."
            ) from exc


@dataclass(frozen=True)
class StoredFile:
    """A file stored under the data directory."""

    path: str
    """Relative to the data directory (store this in the database)."""
    size_bytes: int
    sha256: str


def fsync_path(path: Path) -> None:
    """fsync a file or a directory (a directory: so that a rename in it is durable)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class Storage:
    """Stored files of one data directory.

    Parameters
    ----------
    data_dir
        The service's data directory (``Settings.data_dir``); created if missing.
    report_cache_bytes
        The most the PDF report cache (:attr:`report_cache_dir`) may hold
        (``Settings.report_cache_mb``), and apart from it the trend plot cache
        (:attr:`trend_cache_dir`).
    """

    def __init__(self, data_dir: Path | str, *, report_cache_bytes: int) -> None:
        self.data_dir = Path(data_dir).resolve()
        self.files_dir = self.data_dir / "files"
        self.tmp_dir = self.data_dir / "tmp"
        self.report_cache_dir = self.data_dir / "cache" / "reports"
        self.trend_cache_dir = self.data_dir / "cache" / "trends"
        self.report_cache_bytes = int(report_cache_bytes)
        self.files_dir.mkdir(parents=True, exist_ok=True)
        self.tmp_dir.mkdir(parents=True, exist_ok=True)

    @classmethod
    def from_settings(cls, settings: Settings) -> Storage:
        return cls(settings.data_dir, report_cache_bytes=settings.report_cache_mb * 1024**2)

    # ------------------------------------------------------------------ paths

    def new_path(self, category: str, suffix: str = "") -> str:
        """A fresh, unused relative path ``files/<category>/<xx>/<uuid><suffix>``.

        ``category`` is a short lower-case word (``videos``, ``results``, ``rigs``);
        ``suffix`` such as ``.mp4`` or ``.csv`` (lower-case letters and digits).
        """
        if not _CATEGORY_RE.match(category):
            raise ValueError(f"category must be a short lower-case word, got {category!r}")
        suffix = suffix.lower()
        if not _SUFFIX_RE.match(suffix):
            raise ValueError(f"suffix must look like '.mp4', got {suffix!r}")
        name = uuid.uuid4().hex
        return f"files/{category}/{name[:2]}/{name}{suffix}"

    def absolute(self, path: str) -> Path:
        """The absolute path of a stored file's relative ``path``.

        Raises ``ValueError`` if ``path`` is absolute or leaves ``data_dir/files``.
        """
        if not isinstance(path, str) or not path or os.path.isabs(path):
            raise ValueError(f"stored paths are relative to the data directory, got {path!r}")
        full = (self.data_dir / path).resolve()
        if not full.is_relative_to(self.files_dir):
            raise ValueError(f"stored path {path!r} points outside {self.files_dir}")
        return full

    def exists(self, path: str) -> bool:
        return self.absolute(path).is_file()

    def delete(self, path: str | None) -> None:
        """Remove a stored file if it exists (idempotent; ``None`` is ignored)."""
        if path is None:
            return
        with contextlib.suppress(FileNotFoundError):
            self.absolute(path).unlink()

    # ------------------------------------------------------------------ writing

    def _temp_path(self, suffix: str) -> Path:
        return self.tmp_dir / f"{uuid.uuid4().hex}{suffix}.part"

    def _publish(self, temp: Path, path: str) -> None:
        final = self.absolute(path)
        final.parent.mkdir(parents=True, exist_ok=True)
        if final.exists():
            raise StorageError(f"stored file {path} already exists; refusing to overwrite it.")
        os.replace(temp, final)
        fsync_path(final.parent)

    def write_bytes(self, category: str, suffix: str, data: bytes) -> StoredFile:
        """Store ``data`` atomically under a new path."""
        with self.receive(category, suffix) as incoming:
            incoming.write(data)
            return incoming.commit()

    @contextlib.contextmanager
    def writing(self, category: str, suffix: str = "") -> Iterator[tuple[Path, str]]:
        """Write a file with any function that takes a path, then publish it atomically.

        Yields ``(temp_path, final_relative_path)``; write to ``temp_path`` inside
        the block. On success the file is fsynced and moved to its final path; on
        an exception the temporary file is removed and nothing is published::

            with storage.writing("results", ".csv") as (tmp, path):
                write_markers_csv(analysis, tmp)
            result.markers_path = path
        """
        path = self.new_path(category, suffix)
        temp = self._temp_path(suffix)
        try:
            yield temp, path
            if not temp.is_file():
                raise StorageError(f"nothing was written for {path}.")
            with open(temp, "rb+") as fh:
                os.fsync(fh.fileno())
            self._publish(temp, path)
        finally:
            with contextlib.suppress(FileNotFoundError):
                temp.unlink()

    def receive(
        self, category: str, suffix: str = "", *, max_bytes: int | None = None
    ) -> IncomingFile:
        """Start receiving a file in chunks (see :class:`IncomingFile`)."""
        return IncomingFile(self, category, suffix, max_bytes=max_bytes)

    def cleanup_tmp(self, *, older_than_s: float = 3600.0) -> int:
        """Remove temporary files left by crashed processes; returns how many.

        A file being received or written changes at least every minute (an upload silent
        for ``app.uploads.UPLOAD_STALL_S`` is dropped), so one unchanged for an hour is
        left by a process that died: a crash loop cannot fill the disk with them for a day.
        """
        cutoff = time.time() - older_than_s
        removed = 0
        for entry in self.tmp_dir.iterdir():
            with contextlib.suppress(FileNotFoundError):
                if entry.is_file() and entry.stat().st_mtime < cutoff:
                    entry.unlink()
                    removed += 1
        return removed


class IncomingFile:
    """A file being received in chunks into ``tmp/``, hashed on the fly.

    Use as a context manager: leaving the block by an exception removes the
    temporary file, and also the published file if :meth:`commit` already ran.
    """

    def __init__(
        self, storage: Storage, category: str, suffix: str, *, max_bytes: int | None
    ) -> None:
        self.storage = storage
        self.path = storage.new_path(category, suffix)  # validates category and suffix
        self.temp_path = storage._temp_path(suffix.lower())
        self.max_bytes = max_bytes
        self.size_bytes = 0
        self._sha = hashlib.sha256()
        self._fh = open(self.temp_path, "wb")
        self._committed: StoredFile | None = None

    def __enter__(self) -> IncomingFile:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is not None:
            self.abort()
            if self._committed is not None:
                self.storage.delete(self._committed.path)
        elif self._committed is None:
            self.abort()

    @property
    def sha256(self) -> str:
        """SHA-256 (hex) of the bytes received so far."""
        return self._sha.hexdigest()

    def write(self, chunk: bytes) -> None:
        """Append ``chunk``; raises :class:`PayloadTooLargeError` past ``max_bytes``."""
        if self._fh.closed:
            raise ValueError("this incoming file is already committed or aborted")
        self.size_bytes += len(chunk)
        if self.max_bytes is not None and self.size_bytes > self.max_bytes:
            self.abort()
            raise PayloadTooLargeError(
                f"the file is larger than the limit of {self.max_bytes / 1e6:.1f} MB; "
                "record a shorter clip or ask the administrator to raise "
                "BRADYSCOPE_MAX_UPLOAD_BYTES."
            )
        self._sha.update(chunk)
        self._fh.write(chunk)

    def flush(self) -> None:
        """Make the bytes written so far readable at ``temp_path`` (no-op once closed).

        For checks that read the received file before :meth:`commit` publishes it.
        """
        if not self._fh.closed:
            self._fh.flush()

    def commit(self) -> StoredFile:
        """fsync and move the file to its final path; returns what to store in the database."""
        if self._committed is not None:
            return self._committed
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()
        self.storage._publish(self.temp_path, self.path)
        self._committed = StoredFile(self.path, self.size_bytes, self._sha.hexdigest())
        return self._committed

    def abort(self) -> None:
        """Discard the temporary file (idempotent), also when the disk is full or failing."""
        try:
            if not self._fh.closed:
                self._fh.close()  # flushes: raises again on a full disk, after closing
        except OSError:
            pass  # the bytes are being thrown away; what matters is that the file goes
        finally:
            with contextlib.suppress(FileNotFoundError):
                self.temp_path.unlink()


def file_sha256(path: Path, *, chunk_bytes: int = 1024 * 1024) -> str:
    """SHA-256 (hex) of a file, read in chunks."""
    sha = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk_bytes):
            sha.update(block)
    return sha.hexdigest()

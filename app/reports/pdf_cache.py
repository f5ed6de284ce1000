"""Trials' PDF reports made ahead of time, kept on disk in ``<data dir>/cache/reports/``.

WeasyPrint takes about a second of CPU for a trial's report, too long to wait
for on a request; so the worker makes it as soon as what the report shows
changes (a ``report_pdf`` job, :mod:`app.handlers`) and the request reads it
from here (:func:`app.services.results.report_pdf`). A file is named after the
report's content::

    <patient id>-<trial id>-<key>.pdf

``key`` is the SHA-256 of the report's HTML rendered at a fixed "generated on"
time (:func:`app.reports.rendering.report_key`): a change of anything the
report shows (a result revision, a rating, the session's notes, the visit's
other trials, the time zone, the template, the software) gives another name,
so a stale report is never found; a report found keeps the "generated on" time
of when it was made.

- **Bounded**: a trial keeps its :data:`KEEP_PER_TRIAL` most recently used
  files (its current report and a few older revisions or time zones), the
  whole cache at most ``max_bytes`` (``BRADYSCOPE_REPORT_CACHE_MB``), the least
  recently used going first; both are enforced at every :meth:`ReportPdfCache.put`.
- **Erasure and restore**: erasing a patient removes their files
  (:meth:`ReportPdfCache.forget_patient`); restoring a backup empties the cache
  (:meth:`ReportPdfCache.clear`). The cache is derived data and never backed up.
- **Several processes**: a file appears complete or not at all (written to a
  temporary name, fsynced, renamed); a file removed by another process
  meanwhile is a miss, not an error.
"""

from __future__ import annotations

import contextlib
import os
import re
import time
import uuid
from collections.abc import Iterable
from pathlib import Path

from app.storage import Storage

KEEP_PER_TRIAL = 3
"""Files a trial keeps: its current report and a few older revisions or time zones."""

_KEY = re.compile(r"^[0-9a-f]{64}$")
_STALE_PART_S = 3600.0  # a temporary file this old was left by a crashed process


def _check_id(name: str, value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return value


class ReportPdfCache:
    """The PDF reports kept in ``directory`` (created on the first write).

    Parameters
    ----------
    directory
        ``<data dir>/cache/reports`` (:attr:`app.storage.Storage.report_cache_dir`).
    max_bytes
        The most the cache may hold; the least recently used files go first.
    """

    def __init__(self, directory: Path | str, *, max_bytes: int) -> None:
        if max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1, got {max_bytes}")
        self.directory = Path(directory)
        self.max_bytes = int(max_bytes)

    @classmethod
    def of(cls, storage: Storage) -> ReportPdfCache:
        """The cache of ``storage``'s data directory, with its bound."""
        return cls(storage.report_cache_dir, max_bytes=storage.report_cache_bytes)

    def path(self, patient_id: int, trial_id: int, key: str) -> Path:
        """Where the report of ``trial_id`` with content ``key`` is kept."""
        _check_id("patient_id", patient_id)
        _check_id("trial_id", trial_id)
        if not isinstance(key, str) or not _KEY.match(key):
            raise ValueError(f"key must be a SHA-256 in lower-case hex, got {key!r}")
        return self.directory / f"{patient_id}-{trial_id}-{key}.pdf"

    def get(self, patient_id: int, trial_id: int, key: str) -> bytes | None:
        """The kept PDF, or None; a file found counts as just used (kept longest)."""
        path = self.path(patient_id, trial_id, key)
        try:
            body = path.read_bytes()
        except FileNotFoundError:
            return None
        with contextlib.suppress(FileNotFoundError):
            os.utime(path)
        return body

    def put(self, patient_id: int, trial_id: int, key: str, pdf: bytes) -> Path:
        """Keep ``pdf`` as the report of ``trial_id`` with content ``key``; returns its path.

        Then the trial's older files beyond :data:`KEEP_PER_TRIAL` and, past
        ``max_bytes``, the least recently used files of the cache are removed.
        """
        if not pdf.startswith(b"%PDF"):
            raise ValueError("only a PDF is kept in the report cache")
        final = self.path(patient_id, trial_id, key)
        self.directory.mkdir(parents=True, exist_ok=True)
        # The temporary name starts like the final one, so that forget_patient finds it too.
        temp = final.with_name(f"{final.name}.{uuid.uuid4().hex}.part")
        try:
            with open(temp, "wb") as fh:
                fh.write(pdf)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(temp, final)
        finally:
            with contextlib.suppress(FileNotFoundError):
                temp.unlink()
        self._prune_trial(patient_id, trial_id)
        self._trim()
        return final

    def forget_patient(self, patient_id: int) -> int:
        """Remove every file of the patient (an erasure); returns how many."""
        _check_id("patient_id", patient_id)
        return self._remove(self.directory.glob(f"{patient_id}-*"))

    def clear(self) -> int:
        """Remove every file (a restored backup: the reports are another database's)."""
        if not self.directory.is_dir():
            return 0
        return self._remove(p for p in self.directory.iterdir() if p.is_file())

    def files(self) -> list[Path]:
        """The kept PDF files, in no particular order."""
        if not self.directory.is_dir():
            return []
        return [p for p in self.directory.glob("*.pdf") if p.is_file()]

    # ------------------------------------------------------------------ bounds

    @staticmethod
    def _remove(paths: Iterable[Path]) -> int:
        removed = 0
        for path in paths:
            try:
                path.unlink()
            except FileNotFoundError:
                continue
            removed += 1
        return removed

    @staticmethod
    def _mtimes(paths: list[Path]) -> list[tuple[float, int, Path]]:
        """(mtime, size, path) of each path still there."""
        out = []
        for path in paths:
            try:
                stat = path.stat()
            except FileNotFoundError:
                continue
            out.append((stat.st_mtime, stat.st_size, path))
        return out

    def _prune_trial(self, patient_id: int, trial_id: int) -> None:
        kept = sorted(
            self._mtimes(list(self.directory.glob(f"{patient_id}-{trial_id}-*.pdf"))),
            key=lambda entry: entry[0],
            reverse=True,
        )
        self._remove(path for _, _, path in kept[KEEP_PER_TRIAL:])

    def _trim(self) -> None:
        now = time.time()
        parts = self._mtimes(list(self.directory.glob("*.part")))
        self._remove(path for mtime, _, path in parts if now - mtime > _STALE_PART_S)
        entries = sorted(self._mtimes(self.files()), key=lambda entry: entry[0])
        total = sum(size for _, size, _ in entries)
        doomed = []
        for _, size, path in entries:
            if total <= self.max_bytes:
                break
            doomed.append(path)
            total -= size
        self._remove(doomed)


__all__ = ["KEEP_PER_TRIAL", "ReportPdfCache"]

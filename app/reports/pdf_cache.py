"""Trials' PDF reports made ahead of time, kept on disk in ``<data dir>/cache/reports/``.

WeasyPrint takes about a second of CPU for a trial's report, too long to wait
for on a request; so the worker makes it as soon as what the report shows
changes (a ``report_pdf`` job, :mod:`app.handlers`) and the request reads it
from here (:func:`app.services.results.report_pdf`). A file is named after the
report's content::

    <patient id>-<trial id>-<key>.pdf
    <patient id>-visit-<session id>-<key>.pdf     (a visit report, made on request)

``key`` is the SHA-256 of the report's HTML rendered at a fixed "generated on"
time (:func:`app.reports.rendering.report_key`): a change of anything the
report shows (a result revision, a rating, the session's notes, the visit's
other trials, the time zone, the template, the software) gives another name,
so a stale report is never found; a report found keeps the "generated on" time
of when it was made.

Bounds, erasure, restore and several processes as in :mod:`app.reports.file_cache`:
a trial keeps its :data:`KEEP_PER_TRIAL` most recently used files (its current
report and a few older revisions or time zones), the whole cache at most
``BRADYSCOPE_REPORT_CACHE_MB``; never backed up.
"""

from __future__ import annotations

from pathlib import Path

from app.reports.file_cache import PatientFileCache
from app.storage import Storage

KEEP_PER_TRIAL = 3
"""Files a trial keeps: its current report and a few older revisions or time zones."""


class ReportPdfCache(PatientFileCache):
    """The PDF reports kept in ``directory`` (created on the first write).

    Parameters
    ----------
    directory
        ``<data dir>/cache/reports`` (:attr:`app.storage.Storage.report_cache_dir`).
    max_bytes
        The most the cache may hold; the least recently used files go first.
    """

    suffix = ".pdf"

    @classmethod
    def of(cls, storage: Storage) -> ReportPdfCache:
        """The cache of ``storage``'s data directory, with its bound."""
        return cls(storage.report_cache_dir, max_bytes=storage.report_cache_bytes)

    def path(self, patient_id: int, trial_id: int, key: str) -> Path:
        """Where the report of ``trial_id`` with content ``key`` is kept."""
        return self._named(patient_id, str(self.check_id("trial_id", trial_id)), key)

    def get(self, patient_id: int, trial_id: int, key: str) -> bytes | None:
        """The kept PDF, or None; a file found counts as just used (kept longest)."""
        return self.read(self.path(patient_id, trial_id, key))

    def put(self, patient_id: int, trial_id: int, key: str, pdf: bytes) -> Path:
        """Keep ``pdf`` as the report of ``trial_id`` with content ``key``; returns its path.

        Then the trial's older files beyond :data:`KEEP_PER_TRIAL` and, past
        ``max_bytes``, the least recently used files of the cache are removed.
        """
        final = self.path(patient_id, trial_id, key)
        return self._keep(final, f"{patient_id}-{trial_id}-*.pdf", pdf)

    # A visit report (every trial of a visit day; app.services.visits), by the session it
    # was asked for: ``<patient id>-visit-<session id>-<key>.pdf``.

    def visit_path(self, patient_id: int, session_id: int, key: str) -> Path:
        """Where the visit report of ``session_id``'s visit with content ``key`` is kept."""
        stem = f"visit-{self.check_id('session_id', session_id)}"
        return self._named(patient_id, stem, key)

    def get_visit(self, patient_id: int, session_id: int, key: str) -> bytes | None:
        """The kept visit report, or None (a file found counts as just used)."""
        return self.read(self.visit_path(patient_id, session_id, key))

    def put_visit(self, patient_id: int, session_id: int, key: str, pdf: bytes) -> Path:
        """Keep ``pdf`` as the visit report of ``session_id``; as :meth:`put`."""
        final = self.visit_path(patient_id, session_id, key)
        return self._keep(final, f"{patient_id}-visit-{session_id}-*.pdf", pdf)

    def _named(self, patient_id: int, stem: str, key: str) -> Path:
        self.check_id("patient_id", patient_id)
        self.check_key(key)
        return self.directory / f"{patient_id}-{stem}-{key}.pdf"

    def _keep(self, final: Path, siblings: str, pdf: bytes) -> Path:
        """Write ``pdf`` to ``final``; keep the newest :data:`KEEP_PER_TRIAL` of the files
        matching ``siblings`` and the cache within its bound."""
        if not pdf.startswith(b"%PDF"):
            raise ValueError("only a PDF is kept in the report cache")
        self.write(final, pdf)
        self.keep_newest(siblings, KEEP_PER_TRIAL)
        self.trim()
        return final


__all__ = ["KEEP_PER_TRIAL", "ReportPdfCache"]

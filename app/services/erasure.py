"""Erasure of a patient's data, by hand (``admin erase-patient``) or after the retention period.

Deleting a patient through the API only hides it (``deleted_at``): rows,
files and audit events stay. **Erasure** removes the patient's health data
for good: every row that depends on the patient (sessions, trials, videos,
jobs, results, and whatever later tables refer to them by foreign key) and
every stored file those rows name (columns ``path`` and ``*_path``). What is
kept is what the audit trail needs, pseudonymised: the patient's row becomes
a tombstone with its id (which the audit events refer to), the time of
erasure, and instead of the code a keyed hash of it, so the code stays
reserved (never given to another person by mistake) without being readable.
Audit events hold ids and verbs only, no codes and no clinical values; they
are all kept. The erasure itself is audited.

Rows go first, in one transaction; the files are removed after its commit
(a file whose row is gone is unreachable, so a crash between the two leaves
only unreferenced bytes, which the next erasure of anything does not need),
and with them the patient's PDF reports in the report cache
(:meth:`app.reports.pdf_cache.ReportPdfCache.forget_patient`; a report being
made at that moment removes itself when it finds its trial gone) and their trend
plots (:mod:`app.reports.trend_cache`; the same).
"""

from __future__ import annotations

import hashlib
import hmac
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Table, delete, func, select
from sqlalchemy.orm import Session

from app import chain
from app.audit import AnyActor, audit
from app.errors import NotFoundError
from app.models import Base, Patient, RecordingSession, utcnow
from app.reports.pdf_cache import ReportPdfCache
from app.reports.trend_cache import TrendSvgCache
from app.storage import Storage

log = logging.getLogger(__name__)

TOMBSTONE_PREFIX = "ERASED-"


def tombstone_code(db: Session, code: str) -> str:
    """The code an erased patient keeps: a keyed hash of its real code (any case; not reversible)."""
    key = chain.key_for(db)
    digest = hmac.new(key, b"patient-code\n" + code.lower().encode(), hashlib.sha256).hexdigest()
    return f"{TOMBSTONE_PREFIX}{digest[:40]}"


def code_was_erased(db: Session, code: str) -> bool:
    """Whether ``code`` belonged to an erased patient (it stays reserved)."""
    stone = tombstone_code(db, code)
    return db.scalar(select(Patient.id).where(Patient.code == stone)) is not None


@dataclass(frozen=True)
class ErasureReport:
    """What an erasure removed."""

    patient_id: int
    rows: dict[str, int]
    files_removed: int
    files_missing: int


def _path_columns(table: Table) -> list[Any]:
    return [c for c in table.columns if c.name == "path" or c.name.endswith("_path")]


def _dependent_rows(db: Session, patient_id: int) -> dict[str, set[Any]]:
    """Primary keys, per table, of every row that depends on the patient (by foreign key)."""
    doomed: dict[str, set[Any]] = {"patients": {patient_id}}
    # Parents come before children in sorted_tables: one pass collects the closure.
    for table in Base.metadata.sorted_tables:
        if table.name == "patients" or len(table.primary_key.columns) != 1:
            continue
        pk = next(iter(table.primary_key.columns))
        found: set[Any] = set()
        for fk in table.foreign_keys:
            parents = doomed.get(fk.column.table.name)
            if parents:
                found.update(db.scalars(select(pk).where(fk.parent.in_(parents))))
        if found:
            doomed[table.name] = found
    return doomed


def erase_patient(db: Session, storage: Storage, actor: AnyActor, code: str) -> ErasureReport:
    """Erase the patient with ``code`` (also a deleted one); commits, then removes the files.

    Raises
    ------
    NotFoundError
        No patient has this code (or it was erased already).
    """
    patient = db.scalars(select(Patient).where(Patient.code == code)).first()
    if patient is None:
        erased = code_was_erased(db, code)
        raise NotFoundError(
            f"the patient {code} was erased already." if erased else f"there is no patient {code}."
        )
    return _erase(db, storage, actor, patient, reason="erase")


def _erase(
    db: Session, storage: Storage, actor: AnyActor, patient: Patient, *, reason: str
) -> ErasureReport:
    from app.models import Trial
    from app.services.common import cancel_trial_jobs

    patient_id = patient.id
    # A worker still measuring a trial of this patient loses its lease and stores nothing.
    cancel_trial_jobs(
        db,
        select(Trial.id)
        .join(RecordingSession, Trial.session_id == RecordingSession.id)
        .where(RecordingSession.patient_id == patient_id),
    )
    doomed = _dependent_rows(db, patient_id)
    files: list[str] = []
    counts: dict[str, int] = {}
    for table in reversed(Base.metadata.sorted_tables):
        ids = doomed.get(table.name)
        if not ids or table.name == "patients":
            continue
        pk = next(iter(table.primary_key.columns))
        for column in _path_columns(table):
            files.extend(p for p in db.scalars(select(column).where(pk.in_(ids))) if p)
        # Children before parents; a row may refer to another of the same erasure
        # (results -> jobs), so each table goes whole before its parents.
        db.execute(delete(table).where(pk.in_(ids)).execution_options(synchronize_session=False))
        counts[table.name] = len(ids)
    db.expire_all()
    patient = db.get(Patient, patient_id) or patient
    now = utcnow()
    patient.code = tombstone_code(db, patient.code)
    patient.notes = None
    patient.birth_year = None
    patient.sex = None
    patient.deleted_at = patient.deleted_at or now
    patient.erased_at = now
    audit(db, actor, reason, "patient", patient_id, patient_id)
    db.commit()
    removed = missing = 0
    for path in files:
        try:
            absolute = storage.absolute(path)
        except ValueError:
            log.warning(
                "erasure of patient %s: stored path %r is not a data file", patient_id, path
            )
            continue
        if absolute.is_file():
            absolute.unlink()
            removed += 1
        else:
            missing += 1
    ReportPdfCache.of(storage).forget_patient(patient_id)
    TrendSvgCache.of(storage).forget_patient(patient_id)
    return ErasureReport(patient_id, counts, removed, missing)


def due_for_retention(
    db: Session, retention_days: int, *, now: datetime | None = None
) -> list[Patient]:
    """Patients (not yet erased) whose newest recording, creation or deletion is older than the period."""
    cutoff = (now or utcnow()) - timedelta(days=retention_days)
    newest_session = (
        select(RecordingSession.patient_id, func.max(RecordingSession.recorded_at).label("last"))
        .group_by(RecordingSession.patient_id)
        .subquery()
    )
    rows = db.execute(
        select(Patient, newest_session.c.last)
        .outerjoin(newest_session, newest_session.c.patient_id == Patient.id)
        .where(Patient.erased_at.is_(None))
        .order_by(Patient.id)
    ).all()
    due = []
    for patient, last in rows:
        moments: Iterable[datetime | None] = (last, patient.created_at, patient.deleted_at)
        newest = max(m for m in moments if m is not None)
        if newest < cutoff:
            due.append(patient)
    return due


def apply_retention(
    db: Session, storage: Storage, actor: AnyActor, retention_days: int, *, dry_run: bool = False
) -> list[ErasureReport | int]:
    """Erase every patient past the retention period; with ``dry_run`` only list their ids."""
    due = due_for_retention(db, retention_days)
    if dry_run:
        return [p.id for p in due]
    return [_erase(db, storage, actor, patient, reason="erase_retention") for patient in due]


__all__ = [
    "ErasureReport",
    "apply_retention",
    "code_was_erased",
    "due_for_retention",
    "erase_patient",
    "tombstone_code",
]

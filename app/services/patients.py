"""Patients: create, list (search + pagination), read, update, soft delete.

Deletion rule: a patient is never removed from the database. ``DELETE`` sets
``deleted_at`` (the patient, its sessions and trials then answer 404 and
disappear from lists), the audit trail keeps referring to its id, and its
code stays reserved so that it cannot be given to somebody else by mistake.
"""

from __future__ import annotations

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.actors import Actor
from app.audit import audit, audit_failure
from app.errors import ConflictError
from app.models import Patient, RecordingSession, Trial, utcnow
from app.schemas import PatientCreate, PatientUpdate
from app.services.common import cancel_trial_jobs, load_patient, paginate


def _code_taken(db: Session, code: str, *, exclude_id: int | None = None) -> Patient | None:
    query = select(Patient).where(func.lower(Patient.code) == code.lower())
    if exclude_id is not None:
        query = query.where(Patient.id != exclude_id)
    return db.scalars(query.limit(1)).first()


def _conflict(existing: Patient) -> ConflictError:
    if existing.deleted_at is not None:
        return ConflictError(
            f"The code {existing.code} belonged to a deleted patient and stays reserved;"
            " choose another code."
        )
    return ConflictError(f"A patient with the code {existing.code} exists already.")


def _refused(
    db: Session, actor: Actor, action: str, patient_id: int | None, error: ConflictError
) -> ConflictError:
    """Audit a change refused for a taken code (outcome ``denied``); returns ``error`` to raise.

    ``patient_id`` is the patient being changed, or the one holding the code (``None``
    when a concurrent request took it).
    """
    audit_failure(db, actor, action, "patient", patient_id, patient_id, outcome="denied")
    return error


def create_patient(db: Session, actor: Actor, data: PatientCreate) -> Patient:
    """Create a patient (409 if the code exists, case-insensitively)."""
    existing = _code_taken(db, data.code)
    if existing is not None:
        raise _refused(db, actor, "create", existing.id, _conflict(existing))
    patient = Patient(**data.model_dump())
    db.add(patient)
    try:
        db.flush()
    except IntegrityError as exc:  # a concurrent request took the code
        error = ConflictError(f"A patient with the code {data.code} exists already.")
        raise _refused(db, actor, "create", None, error) from exc
    audit(db, actor, "create", "patient", patient.id, patient.id)
    db.commit()
    return patient


def search_patients(
    db: Session, *, q: str | None, limit: int, offset: int
) -> tuple[list[Patient], int]:
    """Patients whose code contains ``q`` (case-insensitive), ordered by code; and the total.

    A query only: the caller audits the listing (API and patient list page).
    """
    query = select(Patient).where(Patient.deleted_at.is_(None))
    if q:
        escaped = q.strip().lower().replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
        query = query.where(func.lower(Patient.code).like(f"%{escaped}%", escape="\\"))
    return paginate(db, query, Patient.code, Patient.id, limit=limit, offset=offset)


def list_patients(
    db: Session, actor: Actor, *, q: str | None, limit: int, offset: int
) -> tuple[list[Patient], int]:
    """Patients whose code contains ``q`` (case-insensitive), ordered by code; and the total."""
    items, total = search_patients(db, q=q, limit=limit, offset=offset)
    audit(db, actor, "list", "patient")
    db.commit()
    return items, int(total)


def get_patient(db: Session, actor: Actor, patient_id: int) -> Patient:
    patient = load_patient(db, actor, patient_id, "read")
    audit(db, actor, "read", "patient", patient.id, patient.id)
    db.commit()
    return patient


def update_patient(db: Session, actor: Actor, patient_id: int, data: PatientUpdate) -> Patient:
    """Change the given fields; ``code`` cannot be cleared, other fields can (``null``)."""
    patient = load_patient(db, actor, patient_id, "update")
    changes = data.model_dump(exclude_unset=True)
    if changes.get("code") is None:
        changes.pop("code", None)
    if "code" in changes:
        existing = _code_taken(db, changes["code"], exclude_id=patient.id)
        if existing is not None:
            raise _refused(db, actor, "update", patient_id, _conflict(existing))
    for name, value in changes.items():
        setattr(patient, name, value)
    try:
        db.flush()
    except IntegrityError as exc:
        error = ConflictError("Another patient took this code meanwhile; choose another.")
        raise _refused(db, actor, "update", patient_id, error) from exc
    audit(db, actor, "update", "patient", patient.id, patient.id)
    db.commit()
    return patient


def delete_patient(db: Session, actor: Actor, patient_id: int) -> None:
    """Soft-delete a patient (see the module's deletion rule); jobs of its trials are cancelled."""
    patient = load_patient(db, actor, patient_id, "delete")
    patient.deleted_at = utcnow()
    cancel_trial_jobs(
        db,
        select(Trial.id)
        .join(RecordingSession, Trial.session_id == RecordingSession.id)
        .where(RecordingSession.patient_id == patient.id),
    )
    audit(db, actor, "delete", "patient", patient.id, patient.id)
    db.commit()

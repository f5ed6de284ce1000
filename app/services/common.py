"""Lookups shared by the use cases: load a visible row or audit the miss and raise 404."""

from __future__ import annotations

from typing import Any, TypeVar

from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session

from app import job_views, jobs
from app.actors import Actor
from app.audit import audit_failure
from app.errors import ConflictError, NotFoundError
from app.models import Job, Patient, RecordingSession, Rig, Trial
from app.timezones import local_date

T = TypeVar("T")


def not_found(
    db: Session, actor: Actor, action: str, resource_type: str, resource_id: Any, what: str
) -> NotFoundError:
    """Audit a miss (outcome ``not_found``) and return the error to raise."""
    audit_failure(db, actor, action, resource_type, resource_id, outcome="not_found")
    return NotFoundError(f"{what} {resource_id} does not exist; check the id.")


def paginate(
    db: Session, query: Select[Any], *order_by: Any, limit: int, offset: int
) -> tuple[list[Any], int]:
    """One page of ``query``'s rows in the order ``order_by``, and how many match in all."""
    total = db.scalar(select(func.count()).select_from(query.subquery())) or 0
    items = list(db.scalars(query.order_by(*order_by).limit(limit).offset(offset)))
    return items, int(total)


def visible_patient(db: Session, patient_id: int) -> Patient | None:
    """The patient, or None if it does not exist or was deleted (not audited)."""
    patient = db.get(Patient, patient_id)
    return None if patient is None or patient.deleted_at is not None else patient


def visible_session(db: Session, session_id: int) -> RecordingSession | None:
    """The session, or None if it, or its patient, does not exist or was deleted."""
    row = db.get(RecordingSession, session_id)
    if row is None or row.deleted_at is not None or row.patient.deleted_at is not None:
        return None
    return row


def trial_is_visible(trial: Trial) -> bool:
    """Neither the trial nor its session nor its patient was deleted."""
    return (
        trial.deleted_at is None
        and trial.session.deleted_at is None
        and trial.session.patient.deleted_at is None
    )


def visible_trial(db: Session, trial_id: int) -> Trial | None:
    """The trial, or None if it, its session or its patient does not exist or was deleted."""
    row = db.get(Trial, trial_id)
    return row if row is not None and trial_is_visible(row) else None


def load_patient(db: Session, actor: Actor, patient_id: int, action: str) -> Patient:
    patient = visible_patient(db, patient_id)
    if patient is None:
        raise not_found(db, actor, action, "patient", patient_id, "The patient")
    return patient


def load_session(db: Session, actor: Actor, session_id: int, action: str) -> RecordingSession:
    row = visible_session(db, session_id)
    if row is None:
        raise not_found(db, actor, action, "session", session_id, "The session")
    return row


def load_trial(db: Session, actor: Actor, trial_id: int, action: str) -> Trial:
    row = visible_trial(db, trial_id)
    if row is None:
        raise not_found(db, actor, action, "trial", trial_id, "The trial")
    return row


def no_result(db: Session, trial: Trial) -> ConflictError:
    """Why ``trial`` has no result to serve or correct, and what to do: its analysis failed
    (waiting will not help: measure it again), or it has not finished yet (wait)."""
    if trial.status == "failed":
        job = job_views.latest_job(db, trial_id=trial.id)
        error = (job.error or "").strip().rstrip(".") if job is not None else ""
        return ConflictError(
            f"The analysis of trial {trial.id} failed{': ' + error if error else ''}, so it has"
            " no result. Measure it again once the cause is fixed: a re-analysis with the"
            " cameras' offset (offset_frames) or with the two videos swapped (swap_cameras:"
            f" true), POST /api/v1/trials/{trial.id}/revisions or the session page's retry;"
            " or record the take again."
        )
    return ConflictError(
        f"The trial {trial.id} has no result yet (status {trial.status}); poll its job and"
        " retry when it has succeeded."
    )


def load_rig(db: Session, actor: Actor, rig_id: int, action: str) -> Rig:
    rig = db.get(Rig, rig_id)
    if rig is None:
        raise not_found(db, actor, action, "rig", rig_id, "The rig")
    return rig


DELETED_MESSAGE = "the recording was deleted before its measurement finished."


def cancel_trial_jobs(db: Session, trial_ids: Select[Any]) -> int:
    """Cancel the queued or running jobs of the trials ``trial_ids`` selects (being deleted).

    In the caller's transaction; a worker still measuring one of them loses its
    lease and stores nothing. Returns how many jobs were cancelled.
    """
    job_ids = db.scalars(
        select(Job.id).where(Job.trial_id.in_(trial_ids), Job.status.in_(("queued", "running")))
    ).all()
    return sum(jobs.cancel(db, job_id, DELETED_MESSAGE) for job_id in job_ids)


def visit_sessions(session: RecordingSession, timezone: str) -> list[RecordingSession]:
    """The visible sessions of ``session``'s visit, oldest first.

    A visit is the patient's sessions on one calendar day in the clinic's time
    zone ``timezone`` (``Settings.timezone``), e.g. off medication and, an hour
    later, on medication.
    """
    day = local_date(session.recorded_at, timezone)
    same_day = [
        s
        for s in session.patient.sessions
        if s.deleted_at is None and local_date(s.recorded_at, timezone) == day
    ]
    return sorted(same_day, key=lambda s: (s.recorded_at, s.id))


def visit_analyses_pending(db: Session, session: RecordingSession, timezone: str) -> bool:
    """Whether an analysis of a trial of ``session``'s visit is queued or running."""
    session_ids = [s.id for s in visit_sessions(session, timezone)]
    pending = db.scalar(
        select(func.count())
        .select_from(Job)
        .join(Trial, Job.trial_id == Trial.id)
        .where(
            Job.kind == "analyze_trial",
            Job.status.in_(("queued", "running")),
            Trial.session_id.in_(session_ids),
        )
    )
    return bool(pending)


def visit_trials(session: RecordingSession, timezone: str) -> list[Trial]:
    """The visible trials with a result of ``session``'s visit, oldest session first."""
    return [
        t
        for s in visit_sessions(session, timezone)
        for t in s.trials
        if t.deleted_at is None and t.result is not None
    ]

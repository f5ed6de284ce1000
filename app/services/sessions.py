"""Clinical sessions: create, list per patient, read, update, soft delete.

A deleted session (``deleted_at`` set) and its trials answer 404 and vanish
from lists; rows, files and the audit trail are kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime, timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session

from app import job_views, jobs
from app.actors import Actor
from app.audit import audit
from app.errors import AppError, InvalidRequestError
from app.models import Calibration, Job, RecordingSession, Rig, Trial, utcnow
from app.schemas import SessionCreate, SessionUpdate
from app.services.calibrations import calibration_for
from app.services.changes import audit_update, changed_fields
from app.services.common import (
    cancel_trial_jobs,
    load_patient,
    load_session,
    not_found,
    paginate,
)


def _check_calibration(db: Session, calibration_id: int, rig_id: int) -> None:
    cal = db.get(Calibration, calibration_id)
    if cal is None or cal.rig_id != rig_id:
        raise InvalidRequestError(
            f"The calibration {calibration_id} is not a calibration of rig {rig_id};"
            " choose one listed under /rigs/{rig_id}/calibrations."
        )


MAX_AHEAD = timedelta(days=1)
"""How far ahead of the server's clock a session's ``recorded_at`` may be: a day, for a
clock set wrong or a local time sent without its zone (read as UTC)."""


def _check_recorded_at(recorded_at: datetime) -> None:
    """Refuse a recording time in the future (2099: a typo, or a date format misread)."""
    if recorded_at > utcnow() + MAX_AHEAD:
        raise InvalidRequestError(
            f"The recording's date and time (recorded_at), {recorded_at:%Y-%m-%d %H:%M} UTC,"
            " is more than a day ahead of now; give when the recording was made (ISO 8601,"
            " UTC when no zone is given).",
            field="recorded_at",
        )


def create_session(db: Session, actor: Actor, data: SessionCreate) -> RecordingSession:
    _check_recorded_at(data.recorded_at)
    patient = load_patient(db, actor, data.patient_id, "create")
    if db.get(Rig, data.rig_id) is None:
        raise not_found(db, actor, "create", "rig", data.rig_id, "The rig")
    if data.calibration_id is not None:
        _check_calibration(db, data.calibration_id, data.rig_id)
    row = RecordingSession(
        **data.model_dump(),
        clinician_user_id=actor.user_id,
    )
    db.add(row)
    db.flush()
    audit(db, actor, "create", "session", row.id, patient.id)
    db.commit()
    return row


def list_sessions(
    db: Session, actor: Actor, *, patient_id: int, limit: int, offset: int
) -> tuple[list[RecordingSession], int]:
    """The patient's sessions, newest first, and their total."""
    patient = load_patient(db, actor, patient_id, "list")
    query = select(RecordingSession).where(
        RecordingSession.patient_id == patient.id, RecordingSession.deleted_at.is_(None)
    )
    items, total = paginate(
        db,
        query,
        RecordingSession.recorded_at.desc(),
        RecordingSession.id.desc(),
        limit=limit,
        offset=offset,
    )
    audit(db, actor, "list", "session", None, patient.id)
    db.commit()
    return items, int(total)


def get_session(db: Session, actor: Actor, session_id: int) -> RecordingSession:
    row = load_session(db, actor, session_id, "read")
    audit(db, actor, "read", "session", row.id, row.patient_id)
    db.commit()
    return row


def update_session(
    db: Session, actor: Actor, session_id: int, data: SessionUpdate
) -> RecordingSession:
    """Change the given fields; states cannot be cleared, notes/rating/calibration can.

    The PDF reports of the session's measured trials are made again by the worker.
    Audited as an update naming the fields changed, their values kept beside the event
    (:mod:`app.services.changes`).
    """
    row = load_session(db, actor, session_id, "update")
    changes = data.model_dump(exclude_unset=True)
    for required in ("medication_state", "dbs_state"):
        if changes.get(required, "") is None:
            changes.pop(required)
    if changes.get("calibration_id") is not None:
        _check_calibration(db, changes["calibration_id"], row.rig_id)
    changed = changed_fields(row, changes)
    if changed:  # the reports of the session's measured trials show it
        for trial in row.trials:
            if trial.deleted_at is None and trial.result is not None:
                jobs.enqueue_report_pdf(db, trial.id)
    audit_update(db, actor, "session", row.id, row.patient_id, changed)
    db.commit()
    return row


def delete_session(db: Session, actor: Actor, session_id: int) -> None:
    """Soft-delete a session; the queued or running jobs of its trials are cancelled."""
    row = load_session(db, actor, session_id, "delete")
    row.deleted_at = utcnow()
    cancel_trial_jobs(db, select(Trial.id).where(Trial.session_id == row.id))
    audit(db, actor, "delete", "session", row.id, row.patient_id)
    db.commit()


# --------------------------------------------------------------------------- pages


@dataclass(frozen=True)
class TrialRow:
    """A trial on its session's page, with its newest job."""

    trial: Trial
    job: Job | None

    @property
    def retry_with(self) -> tuple[str, ...]:
        """The re-analyses a failed job's error suggests: ``swap_cameras``, ``offset``."""
        if self.job is None or self.job.status != "failed" or not self.job.error:
            return ()
        error = self.job.error.lower()
        out = []
        if "swapped" in error:
            out.append("swap_cameras")
        if "offset" in error or "synchron" in error:
            out.append("offset")
        return tuple(out)


@dataclass(frozen=True)
class SessionOverview:
    """The session page: its visible trials and the calibration that will measure them.

    ``calibration_problem`` says why no calibration can be used (then ``calibration`` is None).
    """

    session: RecordingSession
    trials: list[TrialRow]
    calibration: Calibration | None
    calibration_problem: str | None
    hidden: list[Trial] = field(default_factory=list)
    """Hidden trials, each with who hid it, when and why (an admin can restore them)."""


def session_overview(db: Session, actor: Actor, session_id: int) -> SessionOverview:
    """The session page (audited as a read of the session)."""
    row = load_session(db, actor, session_id, "read")
    trials = [t for t in row.trials if t.deleted_at is None]
    newest = job_views.latest_jobs(db, trial_ids=[t.id for t in trials])
    calibration, problem = None, None
    try:
        calibration = calibration_for(db, row)
    except AppError as exc:
        problem = str(exc)
    overview = SessionOverview(
        session=row,
        trials=[TrialRow(t, newest.get(t.id)) for t in trials],
        calibration=calibration,
        calibration_problem=problem,
        hidden=[t for t in row.trials if t.deleted_at is not None],
    )
    audit(db, actor, "read", "session", row.id, row.patient_id)
    db.commit()
    return overview

"""Which queued jobs wait for another job before they can be claimed (:mod:`app.jobs`).

An analysis waits while a calibration that may measure its trial is being
computed: it stays ``queued`` behind that calibration's ``calibrate`` job,
spending no attempt, and is claimed once the calibration is ready or has
failed (the analysis then says which calibration failed:
:func:`app.services.calibrations.calibration_for`).
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import and_, exists, func, or_, select, update
from sqlalchemy.orm import Session, aliased

from app.models import Calibration, Job, RecordingSession, Trial

ANALYZE_TRIAL = "analyze_trial"
"""The kind of job that measures a trial (its first analysis or a re-analysis)."""

WAITING_FOR_CALIBRATION = "waiting for the rig's calibration being computed"
"""The ``stage`` of an analysis queued behind a ``calibrate`` job."""


def waits_for_calibration() -> Any:
    """SQL condition on ``jobs``: an analysis whose trial may be measured by a calibration
    still being computed (``pending``, its ``calibrate`` job queued or running).

    That is the session's chosen calibration (``sessions.calibration_id``, for a trial of
    the session's rig), or else any calibration of the trial's rig valid from before the
    session (``valid_from <= recorded_at``): once ready it may be the one
    :func:`app.services.calibrations.calibration_for` picks. A pending calibration whose
    job has ended (failed, cancelled) holds nothing back.
    """
    calibrate_job = aliased(Job)
    trial_rig = func.coalesce(Trial.rig_id, RecordingSession.rig_id)
    chosen = and_(
        RecordingSession.calibration_id.is_not(None),
        trial_rig == RecordingSession.rig_id,
    )
    covers = or_(
        and_(chosen, Calibration.id == RecordingSession.calibration_id),
        and_(
            ~chosen,
            Calibration.rig_id == trial_rig,
            Calibration.valid_from <= RecordingSession.recorded_at,
        ),
    )
    return and_(
        Job.kind == ANALYZE_TRIAL,
        exists(
            select(Calibration.id)
            .select_from(Trial)
            .join(RecordingSession, Trial.session_id == RecordingSession.id)
            .join(Calibration, covers)
            .join(calibrate_job, calibrate_job.calibration_id == Calibration.id)
            .where(
                Trial.id == Job.trial_id,
                Calibration.status == "pending",
                calibrate_job.status.in_(("queued", "running")),
            )
        ),
    )


def say_waiting(db: Session) -> None:
    """Give the analyses held back by a calibration being computed the stage that says so
    (``GET /jobs/{id}``: queued, waiting for the rig's calibration); claiming sets another."""
    db.execute(
        update(Job)
        .where(
            Job.status == "queued",
            or_(Job.stage.is_(None), Job.stage != WAITING_FOR_CALIBRATION),
            waits_for_calibration(),
        )
        .values(stage=WAITING_FOR_CALIBRATION)
        .execution_options(synchronize_session=False)
    )

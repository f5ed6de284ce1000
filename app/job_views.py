"""What the pages and the API show of jobs: a job's public view, and each trial's or
calibration's newest job (the queue itself is :mod:`app.jobs`)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.jobs import REPORT_PDF
from app.models import Job


def job_status(db: Session, job_id: int) -> dict[str, Any] | None:
    """The public view of a job (``GET /api/v1/jobs/{id}``), or None if it does not exist."""
    job = db.get(Job, job_id)
    if job is None:
        return None
    return {
        "id": job.id,
        "kind": job.kind,
        "status": job.status,
        "progress": job.progress,
        "stage": job.stage,
        "error": job.error,
        "attempts": job.attempts,
        "max_attempts": job.max_attempts,
        "trial_id": job.trial_id,
        "calibration_id": job.calibration_id,
        "created_at": job.created_at,
        "started_at": job.started_at,
        "finished_at": job.finished_at,
    }


def latest_jobs(
    db: Session, *, trial_ids: Iterable[int] = (), calibration_ids: Iterable[int] = ()
) -> dict[int, Job]:
    """The newest job of each given trial, or of each given calibration (one query).

    Pass either ``trial_ids`` or ``calibration_ids``; the answer maps each id
    that has a job to its newest job (the highest job id: a re-analysis or a
    retry queued later wins). A ``report_pdf`` job is never one: a trial's
    latest job is its latest analysis.
    """
    trials, calibrations = list(trial_ids), list(calibration_ids)
    if trials and calibrations:
        raise ValueError("give trial_ids or calibration_ids, not both")
    owner = Job.trial_id if trials else Job.calibration_id
    ids = trials or calibrations
    if not ids:
        return {}
    newest = select(func.max(Job.id)).where(owner.in_(ids), Job.kind != REPORT_PDF).group_by(owner)
    out: dict[int, Job] = {}
    for job in db.scalars(select(Job).where(Job.id.in_(newest))):
        key = job.trial_id if trials else job.calibration_id
        if key is not None:
            out[key] = job
    return out


def latest_job(
    db: Session, *, trial_id: int | None = None, calibration_id: int | None = None
) -> Job | None:
    """The newest job of one trial or one calibration (see :func:`latest_jobs`)."""
    if trial_id is not None:
        return latest_jobs(db, trial_ids=[trial_id]).get(trial_id)
    if calibration_id is not None:
        return latest_jobs(db, calibration_ids=[calibration_id]).get(calibration_id)
    raise ValueError("give trial_id or calibration_id")

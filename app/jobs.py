"""A durable job queue in the database, with leases, heartbeats and bounded retries.

Life cycle of a :class:`app.models.Job` row::

    queued ──claim──> running ──complete──> succeeded
      ^                  │ │
      └──retry (delay)───┘ └──fail (domain error, or attempts used up)──> failed

- **enqueue** (:func:`enqueue`) adds a row in the caller's transaction, so that
  "trial stored" and "job queued" commit together.
- **claim** (:func:`claim_next`) takes the oldest claimable job in ONE
  statement: ``UPDATE jobs ... WHERE id = (SELECT id ... LIMIT 1 [FOR UPDATE
  SKIP LOCKED]) RETURNING ...``. PostgreSQL skips rows other workers are
  claiming; SQLite serialises writers, so both are race-free. Claimable means
  ``queued`` and due, or ``running`` with an **expired lease** (its worker died)
  and attempts left. Each claim gets a fresh, unique ``lease_owner`` token and
  increments ``attempts``. An analysis is not claimable while a calibration
  that may measure it is being computed (:func:`waits_for_calibration`): it
  stays queued behind that ``calibrate`` job, spending nothing, and runs once
  the calibration is ready (or failed: then the analysis says so).
- **heartbeat** (:func:`heartbeat`) extends the lease and stores progress; it
  raises :class:`LeaseLostError` when the lease now belongs to someone else. One
  the database cannot take (unreachable for a moment) is skipped, not raised: the
  job's work goes on and spends no attempt.
- **complete** (:func:`complete`) marks success *inside the transaction that
  stores the job's effect* (e.g. the Result row), guarded by the lease owner:
  a stale worker whose job was re-claimed gets :class:`LeaseLostError` and its
  whole transaction is rolled back. Together with ``results.trial_id UNIQUE``
  this makes every job's effect happen exactly once.
- **fail** (:func:`fail`) stores a user-facing sentence (never a traceback);
  retryable failures go back to ``queued`` after a delay until
  ``max_attempts`` is reached.
- **reap** (:func:`reap_expired`) fails jobs whose lease expired with no
  attempts left (a job that kills its worker every time).
- **cancel** (:func:`cancel`) fails a queued or running job (e.g. its trial was
  deleted); a worker still running it loses its lease and stores nothing.

A ``report_pdf`` job (:data:`REPORT_PDF`, :func:`enqueue_report_pdf`) makes a
trial's PDF report ahead of time, for the report cache. It is claimed before
the other kinds (about a second of work, against a minute for an analysis) and
is never a trial's latest job (:func:`app.job_views.latest_jobs`): a trial's status and the
pages' job views follow its analyses only. An analysis failing for good queues
one too: its visit's reports waited for it (``results.make_report_pdfs``).

Timestamps come from the worker's clock (UTC): machines sharing a PostgreSQL
database must keep their clocks synchronised (NTP) to well under the lease.
"""

from __future__ import annotations

import logging
import uuid
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import and_, case, exists, or_, select, update
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker

from app.faults import storage_fault
from app.job_waits import say_waiting, waits_for_calibration
from app.models import Calibration, Job, Result, Trial, utcnow

log = logging.getLogger(__name__)


class LeaseLostError(Exception):
    """This worker no longer holds the job (it was re-claimed, finished or removed)."""


@dataclass(frozen=True)
class ClaimedJob:
    """A snapshot of a job as claimed by one worker."""

    id: int
    kind: str
    payload: dict[str, Any]
    trial_id: int | None
    calibration_id: int | None
    attempts: int
    """Including this one (1 on the first attempt)."""
    max_attempts: int
    lease_owner: str
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def attempts_left(self) -> int:
        return self.max_attempts - self.attempts


REPORT_PDF = "report_pdf"
"""The kind of job that makes a trial's PDF report ahead of time (``app.handlers``)."""


def new_lease_owner(worker_name: str) -> str:
    """A unique token for one claim by ``worker_name``."""
    return f"{worker_name[:80]}:{uuid.uuid4().hex[:12]}"


def enqueue(
    db: Session,
    kind: str,
    *,
    trial_id: int | None = None,
    calibration_id: int | None = None,
    payload: dict[str, Any] | None = None,
    max_attempts: int | None = None,
) -> Job:
    """Add a queued job in the caller's transaction (flushed, so ``job.id`` is set).

    The caller commits, together with whatever the job refers to.
    ``max_attempts`` defaults to ``BRADYSCOPE_JOB_MAX_ATTEMPTS`` (3).
    """
    if max_attempts is None:
        from app.settings import get_settings

        max_attempts = get_settings().job_max_attempts
    if not kind:
        raise ValueError("kind must be a non-empty string")
    if max_attempts < 1:
        raise ValueError(f"max_attempts must be >= 1, got {max_attempts}")
    job = Job(
        kind=kind,
        trial_id=trial_id,
        calibration_id=calibration_id,
        payload=dict(payload or {}),
        max_attempts=max_attempts,
        status="queued",
        run_after=utcnow(),
    )
    db.add(job)
    db.flush()
    return job


def enqueue_report_pdf(db: Session, trial_id: int) -> Job | None:
    """Queue the making of the PDF report of ``trial_id``'s current result (caller commits).

    Call it in the transaction that changes what the report shows. None when
    such a job is already queued: it will read the trial when it runs, so it
    covers this change too (a running one may have read it already).
    """
    queued = db.scalar(
        select(Job.id)
        .where(Job.kind == REPORT_PDF, Job.trial_id == trial_id, Job.status == "queued")
        .limit(1)
    )
    if queued is not None:
        return None
    return enqueue(db, REPORT_PDF, trial_id=trial_id)


def _claimable(now: datetime) -> Any:
    return and_(
        or_(
            and_(Job.status == "queued", Job.run_after <= now),
            and_(
                Job.status == "running",
                Job.lease_expires_at < now,
                Job.attempts < Job.max_attempts,
            ),
        ),
        ~waits_for_calibration(),
    )


CLAIM_ORDER = case((Job.kind == REPORT_PDF, 0), else_=1)
"""Reports first: one takes about a second of a worker, an analysis about a minute."""


def claim_next(
    sessions: sessionmaker[Session],
    *,
    worker_name: str,
    lease_s: float,
    kinds: tuple[str, ...] | list[str] | None = None,
    now: datetime | None = None,
) -> ClaimedJob | None:
    """Claim the oldest claimable job (of ``kinds``, if given), reports first, or None.

    Commits its own transaction. The linked trial (if any; not a report's) becomes
    ``running``.
    """
    if lease_s <= 0:
        raise ValueError(f"lease_s must be > 0, got {lease_s}")
    now = now or utcnow()
    owner = new_lease_owner(worker_name)
    condition = _claimable(now)
    if kinds is not None:
        condition = and_(condition, Job.kind.in_(list(kinds)))
    candidate = (
        select(Job.id)
        .where(condition)
        .order_by(CLAIM_ORDER, Job.id)
        .limit(1)
        .with_for_update(skip_locked=True)
        .scalar_subquery()
    )
    stmt = (
        update(Job)
        .where(Job.id == candidate, condition)
        .values(
            status="running",
            lease_owner=owner,
            lease_expires_at=now + timedelta(seconds=lease_s),
            heartbeat_at=now,
            started_at=now,
            attempts=Job.attempts + 1,
            progress=0.0,
            stage="starting",
        )
        .returning(
            Job.id,
            Job.kind,
            Job.payload,
            Job.trial_id,
            Job.calibration_id,
            Job.attempts,
            Job.max_attempts,
        )
        .execution_options(synchronize_session=False)
    )
    with sessions() as db, db.begin():
        say_waiting(db)
        row = db.execute(stmt).first()
        if row is None:
            return None
        _set_trial_status(db, _status_trial(row.kind, row.trial_id), "running")
    claimed = ClaimedJob(
        id=row.id,
        kind=row.kind,
        payload=dict(row.payload or {}),
        trial_id=row.trial_id,
        calibration_id=row.calibration_id,
        attempts=row.attempts,
        max_attempts=row.max_attempts,
        lease_owner=owner,
    )
    log.info(
        "claimed job %d (%s), attempt %d of %d, as %s",
        claimed.id,
        claimed.kind,
        claimed.attempts,
        claimed.max_attempts,
        owner,
    )
    return claimed


def _guard(job: ClaimedJob) -> Any:
    return and_(Job.id == job.id, Job.lease_owner == job.lease_owner, Job.status == "running")


def _update_held(db: Session, job: ClaimedJob, values: dict[str, Any]) -> None:
    """Update ``job`` only if this claim still holds it; else :class:`LeaseLostError`."""
    result = db.execute(
        update(Job).where(_guard(job)).values(**values).execution_options(synchronize_session=False)
    )
    if result.rowcount != 1:  # type: ignore[attr-defined]
        raise LeaseLostError(f"job {job.id} is no longer held by {job.lease_owner}")


def _status_trial(kind: str, trial_id: int | None) -> int | None:
    """The trial whose status a job of ``kind`` sets: its own, or none for a report."""
    return None if kind == REPORT_PDF else trial_id


def _set_trial_status(db: Session, trial_id: int | None, status: str) -> None:
    """A trial's status mirrors its analysis job until it has a result; a trial with a
    result stays ``succeeded`` while a re-analysis runs or after one fails (its job says so)."""
    if trial_id is not None:
        query = update(Trial).where(Trial.id == trial_id)
        if status != "succeeded":
            query = query.where(~exists().where(Result.trial_id == Trial.id))
        db.execute(query.values(status=status).execution_options(synchronize_session=False))


def heartbeat(
    sessions: sessionmaker[Session],
    job: ClaimedJob,
    *,
    lease_s: float,
    progress: float | None = None,
    stage: str | None = None,
) -> bool:
    """Extend the lease of ``job`` (and store progress); commits. False when the database
    could not take it (unreachable, read-only, full): the service's fault, so the work goes
    on and the next heartbeat tries again (if none gets through before the lease runs out,
    another worker may take the job over; this one then finds it lost and stores nothing).

    Raises
    ------
    LeaseLostError
        When the job is no longer running under this claim.
    """
    now = utcnow()
    values: dict[str, Any] = {
        "heartbeat_at": now,
        "lease_expires_at": now + timedelta(seconds=lease_s),
    }
    if progress is not None:
        values["progress"] = min(max(float(progress), 0.0), 1.0)
    if stage is not None:
        values["stage"] = stage[:64]
    try:
        with sessions() as db, db.begin():
            _update_held(db, job, values)
    except DBAPIError as exc:
        if storage_fault(exc) is None:
            raise
        log.warning(
            "job %d: heartbeat not recorded (%s); the work goes on", job.id, type(exc).__name__
        )
        return False
    return True


def complete(db: Session, job: ClaimedJob) -> None:
    """Mark ``job`` (and its trial) succeeded in the caller's transaction, if this claim
    still holds it.

    Call it first in the transaction that stores the job's effect: on
    PostgreSQL it locks the job row, on SQLite it takes the write lock, so no
    other worker can re-claim the job before the transaction ends.

    Raises
    ------
    LeaseLostError
        When the job was re-claimed by another worker (or finished): roll back.
    """
    now = utcnow()
    _update_held(
        db,
        job,
        {
            "status": "succeeded",
            "progress": 1.0,
            "stage": "done",
            "error": None,
            "finished_at": now,
            "heartbeat_at": now,
            "lease_expires_at": None,
        },
    )
    _set_trial_status(db, _status_trial(job.kind, job.trial_id), "succeeded")


def _mark_targets_failed(db: Session, trial_id: int | None, calibration_id: int | None) -> None:
    _set_trial_status(db, trial_id, "failed")
    if trial_id is not None:  # its visit's reports waited for it (make_report_pdfs)
        enqueue_report_pdf(db, trial_id)
    if calibration_id is not None:
        db.execute(
            update(Calibration)
            .where(Calibration.id == calibration_id, Calibration.status == "pending")
            .values(status="failed")
            .execution_options(synchronize_session=False)
        )


def fail(
    sessions: sessionmaker[Session],
    job: ClaimedJob,
    message: str,
    *,
    retryable: bool,
    retry_delay_s: float = 0.0,
) -> str:
    """Record a failure of this attempt; returns the job's new status.

    ``message`` is the user-facing sentence kept in ``Job.error``. A retryable
    failure with attempts left goes back to ``queued`` (due after
    ``retry_delay_s × attempts``); otherwise the job, its trial and a pending
    calibration become ``failed``.

    Raises
    ------
    LeaseLostError
        When this claim no longer holds the job (nothing is changed).
    """
    now = utcnow()
    retry = retryable and job.attempts < job.max_attempts
    with sessions() as db, db.begin():
        if retry:
            values: dict[str, Any] = {
                "status": "queued",
                "run_after": now + timedelta(seconds=retry_delay_s * job.attempts),
                "lease_owner": None,
                "lease_expires_at": None,
                "stage": "waiting to retry",
                "error": message,
            }
        else:
            values = {
                "status": "failed",
                "finished_at": now,
                "lease_expires_at": None,
                "error": message,
            }
        _update_held(db, job, values)
        if retry:
            _set_trial_status(db, _status_trial(job.kind, job.trial_id), "queued")
        else:
            _mark_targets_failed(db, _status_trial(job.kind, job.trial_id), job.calibration_id)
    return str(values["status"])


def postpone(sessions: sessionmaker[Session], job: ClaimedJob, message: str, delay_s: float) -> str:
    """Put the job back in the queue for ``delay_s`` without spending its attempt: what
    stopped it is the service's (a full disk, the database down), not the job's; it
    waits, saying ``message``, until the service can take it. Returns ``queued``.

    Raises
    ------
    LeaseLostError
        When this claim no longer holds the job (nothing is changed).
    """
    with sessions() as db, db.begin():
        _update_held(
            db,
            job,
            {
                "status": "queued",
                "attempts": max(0, job.attempts - 1),
                "run_after": utcnow() + timedelta(seconds=delay_s),
                "lease_owner": None,
                "lease_expires_at": None,
                "stage": "waiting for the server (its storage or database)",
                "error": message,
            },
        )
        _set_trial_status(db, _status_trial(job.kind, job.trial_id), "queued")
    return "queued"


def cancel(db: Session, job_id: int, message: str) -> bool:
    """Fail a queued or running job with ``message`` in the caller's transaction.

    A worker still running it finds out at its next heartbeat or when it tries
    to finish, and discards its work. Returns False if the job had already
    ended (or does not exist).
    """
    now = utcnow()
    result = db.execute(
        update(Job)
        .where(Job.id == job_id, Job.status.in_(("queued", "running")))
        .values(status="failed", error=message, finished_at=now, lease_expires_at=None)
        .execution_options(synchronize_session=False)
    )
    return bool(result.rowcount)  # type: ignore[attr-defined]


WORKER_LOST_MESSAGE = (
    "the worker measuring this recording stopped {attempts} times before finishing; "
    "the recording may be too large for the server, ask the administrator to check the worker log."
)


def reap_expired(sessions: sessionmaker[Session], *, now: datetime | None = None) -> int:
    """Fail running jobs whose lease expired with no attempts left; returns how many."""
    now = now or utcnow()
    with sessions() as db, db.begin():
        rows = db.execute(
            select(
                Job.id, Job.kind, Job.attempts, Job.trial_id, Job.calibration_id, Job.lease_owner
            ).where(
                Job.status == "running",
                Job.lease_expires_at < now,
                Job.attempts >= Job.max_attempts,
            )
        ).all()
        reaped = 0
        for row in rows:
            result = db.execute(
                update(Job)
                .where(
                    Job.id == row.id,
                    Job.status == "running",
                    Job.lease_owner == row.lease_owner,
                    Job.lease_expires_at < now,
                )
                .values(
                    status="failed",
                    finished_at=now,
                    lease_expires_at=None,
                    error=WORKER_LOST_MESSAGE.format(attempts=row.attempts),
                )
                .execution_options(synchronize_session=False)
            )
            if result.rowcount == 1:  # type: ignore[attr-defined]
                _mark_targets_failed(db, _status_trial(row.kind, row.trial_id), row.calibration_id)
                reaped += 1
                log.warning("job %d failed: its lease expired after the last attempt", row.id)
    return reaped

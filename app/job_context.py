"""What a job handler gets: the claimed job, its progress and lease, and one way to finish it.

A handler is ``handler(ctx: JobContext) -> None`` (:data:`Handler`); the
worker (:mod:`app.worker`) claims a job, makes its :class:`JobContext` and
keeps its lease alive while the handler runs; the handlers themselves are in
:mod:`app.handlers`.

- :meth:`JobContext.progress` is a ``core.progress.ProgressCallback``: it
  records the stage and fraction and extends the lease (at most every 0.5 s);
- :meth:`JobContext.finish` stores the handler's effect and "succeeded" in one
  transaction guarded by the lease, so a job is done exactly once in effect; a
  database unreachable for a moment meanwhile (refused, cut, restarted) does not
  throw the computed effect away: the transaction is tried again, with a growing
  wait, while the lease would hold (:func:`store_retry_waits`);
- :class:`RetryableJobError` is a failure that another attempt, perhaps by
  another worker, may not have (its sentence is kept in the job).
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app import jobs
from app.errors import ServiceUnavailableError
from app.faults import storage_fault
from app.jobs import ClaimedJob, LeaseLostError
from app.models import Job
from app.settings import Settings
from app.storage import Storage

Handler = Callable[["JobContext"], None]

log = logging.getLogger(__name__)


class RetryableJobError(Exception):
    """A failure another attempt (perhaps by another worker) may not have.

    Its message is user-facing and kept in the job; the job is retried until
    ``max_attempts``, like an unexpected error, but without hiding the reason.
    """


PROGRESS_WRITE_INTERVAL_S = 0.5


def default_worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def database_unreachable(exc: BaseException) -> bool:
    """Whether ``exc`` says the database cannot be reached right now (refused, cut, shut
    down, its file not opened): :func:`app.faults.storage_fault`'s 503 for it, not a
    read-only or full one, and no error of the job's own (an integrity error, a bug)."""
    return type(storage_fault(exc)) is ServiceUnavailableError


def store_retry_waits(settings: Settings) -> Iterator[float]:
    """The waits (s) before each new try of storing a job's effect while the database is
    unreachable: from an eighth of the heartbeat period, doubling up to the heartbeat
    period, over the lease less one heartbeat period in all (45 s with the default
    60 s lease: 1.9, 3.8, 7.5, 15, 15 and 1.9 s).

    The lease was last renewed at most a heartbeat period before the outage began, and
    the heartbeat cannot renew it meanwhile: the waits end before it can run out, so
    the job can still be given back (:func:`app.jobs.postpone`) after the last try
    rather than taken over by another worker, which would spend an attempt. (Tries that
    take long themselves, a connection timing out, may still outlast the lease: the
    next try then finds the job taken over, as without the waits.)
    """
    heartbeat_s = settings.heartbeat_s
    left_s = settings.job_lease_s - heartbeat_s
    wait_s = heartbeat_s / 8
    while left_s > 0:
        yield min(wait_s, left_s)
        left_s -= wait_s
        wait_s = min(2 * wait_s, heartbeat_s)


class JobContext:
    """What a handler gets: the claimed job, settings, storage, and the progress/finish hooks.

    Attributes
    ----------
    job : ClaimedJob
    settings : Settings
    storage : Storage
    sessions : sessionmaker
        For the handler's own reads (keep transactions short).
    """

    def __init__(
        self,
        job: ClaimedJob,
        *,
        settings: Settings,
        storage: Storage,
        sessions: sessionmaker[Session],
        stages: tuple[tuple[str, float], ...] = (),
    ) -> None:
        self.job = job
        self.settings = settings
        self.storage = storage
        self.sessions = sessions
        self.stages = stages
        self.finished = False
        self._lock = threading.Lock()
        self._lost = threading.Event()
        self._stage = "starting"
        self._fraction = 0.0
        self._last_write = 0.0

    # ------------------------------------------------------------------ progress

    @property
    def lost(self) -> bool:
        """True once the lease was found to belong to another worker."""
        return self._lost.is_set()

    def _overall(self, stage: str, done: int, total: int) -> float:
        within = min(max(done / total, 0.0), 1.0) if total > 0 else 0.0
        names = [name for name, _ in self.stages]
        if stage not in names:
            return within
        weights = [weight for _, weight in self.stages]
        i = names.index(stage)
        return (sum(weights[:i]) + weights[i] * within) / sum(weights)

    def progress(self, stage: str, done: int, total: int) -> None:
        """A ``core.progress.ProgressCallback``: records progress, extends the lease.

        Writes to the database at most every 0.5 s (and on every stage change).
        Raises :class:`LeaseLostError` when the job was taken over, which stops
        the pipeline early.
        """
        if self.lost:
            raise LeaseLostError(f"job {self.job.id} was taken over by another worker")
        with self._lock:
            changed = stage != self._stage
            fraction = self._overall(stage, done, total)
            # With known stages the fraction spans the whole job and never goes back;
            # otherwise it is the current stage's own fraction.
            self._fraction = max(self._fraction, fraction) if self.stages else fraction
            self._stage = stage
            due = time.monotonic() - self._last_write >= PROGRESS_WRITE_INTERVAL_S
        if changed or due:
            self.beat()

    def beat(self) -> None:
        """Heartbeat now: extend the lease and store the latest progress."""
        with self._lock:
            stage, fraction = self._stage, self._fraction
            self._last_write = time.monotonic()
        try:
            jobs.heartbeat(
                self.sessions,
                self.job,
                lease_s=self.settings.job_lease_s,
                progress=fraction,
                stage=stage,
            )
        except LeaseLostError:
            self._lost.set()
            raise

    # ------------------------------------------------------------------ finishing

    def finish(self, write: Callable[[Session], None] | None = None) -> None:
        """Store the job's effect and mark it succeeded, in one transaction.

        ``write(db)`` adds the effect (rows) to the transaction; it may be called again,
        each time in a new transaction, when the database was unreachable
        (:func:`database_unreachable`) and is tried again after :func:`store_retry_waits`;
        any other error is raised at once. If this worker lost the lease meanwhile,
        nothing is stored and :class:`LeaseLostError` is raised; if the database is
        still unreachable after the last wait, its error is raised.
        """
        if self.finished:
            raise ValueError(f"job {self.job.id} is already finished")
        waits = store_retry_waits(self.settings)
        tries = 0
        while True:
            tries += 1
            try:
                self._store(write)
                break
            except LeaseLostError:
                # A commit cut off on its way back may have been stored all the same.
                if tries > 1 and self._stored_by_this_claim():
                    log.info("job %d: its result was stored by try %d", self.job.id, tries - 1)
                    break
                raise
            except Exception as exc:
                if not database_unreachable(exc):
                    raise
                wait_s = next(waits, None)
                if wait_s is None:
                    log.error(
                        "job %d (%s): its result could not be stored, the database unreachable"
                        " in %d tries (%s); the computed result is given up",
                        self.job.id,
                        self.job.kind,
                        tries,
                        type(exc).__name__,
                    )
                    raise
                log.warning(
                    "job %d (%s): its result is not stored yet, the database unreachable (%s);"
                    " it is kept and tried again in %.2g s",
                    self.job.id,
                    self.job.kind,
                    type(exc).__name__,
                    wait_s,
                )
                if self._lost.wait(wait_s):  # the heartbeat found the job taken over
                    raise LeaseLostError(
                        f"job {self.job.id} was taken over by another worker"
                    ) from exc
        self.finished = True

    def _store(self, write: Callable[[Session], None] | None) -> None:
        """One try of :meth:`finish`'s transaction."""
        with self.sessions() as db, db.begin():
            jobs.complete(db, self.job)  # first: locks the job row / takes the write lock
            if write is not None:
                write(db)

    def _stored_by_this_claim(self) -> bool:
        """Whether the job is marked succeeded under this claim (by an earlier try of
        :meth:`finish` whose commit got through but whose answer was lost)."""
        with self.sessions() as db:
            row = db.execute(
                select(Job.status, Job.lease_owner).where(Job.id == self.job.id)
            ).one_or_none()
        return row is not None and tuple(row) == ("succeeded", self.job.lease_owner)

"""What a job handler gets: the claimed job, its progress and lease, and one way to finish it.

A handler is ``handler(ctx: JobContext) -> None`` (:data:`Handler`); the
worker (:mod:`app.worker`) claims a job, makes its :class:`JobContext` and
keeps its lease alive while the handler runs; the handlers themselves are in
:mod:`app.handlers`.

- :meth:`JobContext.progress` is a ``core.progress.ProgressCallback``: it
  records the stage and fraction and extends the lease (at most every 0.5 s);
- :meth:`JobContext.finish` stores the handler's effect and "succeeded" in one
  transaction guarded by the lease, so a job is done exactly once in effect;
- :class:`RetryableJobError` is a failure that another attempt, perhaps by
  another worker, may not have (its sentence is kept in the job).
"""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable

from sqlalchemy.orm import Session, sessionmaker

from app import jobs
from app.jobs import ClaimedJob, LeaseLostError
from app.settings import Settings
from app.storage import Storage

Handler = Callable[["JobContext"], None]


class RetryableJobError(Exception):
    """A failure another attempt (perhaps by another worker) may not have.

    Its message is user-facing and kept in the job; the job is retried until
    ``max_attempts``, like an unexpected error, but without hiding the reason.
    """


PROGRESS_WRITE_INTERVAL_S = 0.5


def default_worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


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

        ``write(db)`` adds the effect (rows) to the transaction. If this worker
        lost the lease meanwhile, nothing is stored and :class:`LeaseLostError`
        is raised.
        """
        if self.finished:
            raise ValueError(f"job {self.job.id} is already finished")
        with self.sessions() as db, db.begin():
            jobs.complete(db, self.job)  # first: locks the job row / takes the write lock
            if write is not None:
                write(db)
        self.finished = True

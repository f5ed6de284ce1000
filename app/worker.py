"""The job worker: claims jobs from the queue and runs the pipeline on them.

:func:`run_worker` loops: fail jobs whose worker died too often
(:func:`app.jobs.reap_expired`), claim the next job, run its handler with a
heartbeat thread keeping the lease alive, then store the outcome:

- the handler's effect and "succeeded" in one transaction guarded by the lease
  (:meth:`JobContext.finish`), so a job is done exactly once in effect; a database
  unreachable for a moment then is waited for, the computed effect kept, while
  the lease holds;
- a :class:`core.errors.BradyscopeError` or :class:`app.errors.AppError`
  becomes the job's user-facing error, without retry (bad input stays bad); the
  log names the error's class and the job's trial, never its sentence (which
  names the uploaded files, :func:`_kind`);
- a :class:`RetryableJobError` (e.g. video files missing on this worker) is
  retried until ``max_attempts`` and keeps its sentence;
- any other exception is logged with its traceback and retried until
  ``max_attempts``; the user sees a plain sentence, not the traceback;
- a lost lease (another worker took the job over) drops the attempt silently.

The job's view of itself (progress, lease, finish) is
:class:`app.job_context.JobContext`; what each kind of job does is
:mod:`app.handlers` (:data:`app.handlers.HANDLERS`; tests pass their own
``handlers=``).
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Mapping

from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker

from app import jobs
from app.db import get_sessionmaker
from app.errors import AppError, InsufficientStorageError, ServiceUnavailableError
from app.faults import storage_fault
from app.handlers import HANDLERS, STAGES
from app.job_context import Handler, JobContext, RetryableJobError, default_worker_name
from app.jobs import ClaimedJob, LeaseLostError
from app.settings import Settings
from app.storage import Storage
from core.errors import BradyscopeError

log = logging.getLogger(__name__)


UNEXPECTED_RETRY_MESSAGE = (
    "an unexpected error interrupted attempt {attempt} of {max_attempts}; it will be retried."
)
UNEXPECTED_FINAL_MESSAGE = (
    "an unexpected error stopped this job after {max_attempts} attempts; ask the administrator "
    "to look up job {job_id} in the worker log."
)


class _Heartbeat(threading.Thread):
    """Keeps the lease of a running job alive while its handler works."""

    def __init__(self, ctx: JobContext, period_s: float) -> None:
        super().__init__(name=f"heartbeat-job-{ctx.job.id}", daemon=True)
        self.ctx = ctx
        self.period_s = period_s
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.wait(self.period_s):
            try:
                self.ctx.beat()
            except LeaseLostError:
                log.warning("job %d: lease lost; another worker has taken it over", self.ctx.job.id)
                return
            except Exception:  # a database hiccup: keep trying until the lease is lost
                log.exception("job %d: heartbeat failed", self.ctx.job.id)


# --------------------------------------------------------------------------- the loop


def run_job(
    job: ClaimedJob,
    *,
    settings: Settings,
    handler: Handler,
    sessions: sessionmaker[Session] | None = None,
    storage: Storage | None = None,
) -> str:
    """Run one claimed job to its outcome; returns the job's resulting status.

    ``"lost"`` when another worker took the job over.
    """
    sessions = sessions or get_sessionmaker(settings)
    storage = storage or Storage.from_settings(settings)
    ctx = JobContext(
        job, settings=settings, storage=storage, sessions=sessions, stages=STAGES.get(job.kind, ())
    )
    beat = _Heartbeat(ctx, settings.heartbeat_s)
    beat.start()
    try:
        handler(ctx)
        if not ctx.finished:
            ctx.finish()
        log.info("job %d (%s) succeeded", job.id, job.kind)
        return "succeeded"
    except LeaseLostError:
        log.warning("job %d: abandoned; another worker holds it now", job.id)
        return "lost"
    except (InsufficientStorageError, ServiceUnavailableError) as exc:
        log.error("%s: %s; postponed %.0f s", _named(job), _kind(exc), STORAGE_FAULT_DELAY_S)
        message = f"{exc} The job waits and retries by itself."
        return _postpone(sessions, job, message, settings=settings)
    except (BradyscopeError, AppError) as exc:
        log.info("%s failed: %s (its sentence is in the job)", _named(job), _kind(exc))
        return _fail(sessions, job, str(exc), retryable=False, settings=settings)
    except RetryableJobError as exc:
        log.warning("%s, attempt %d: %s", _named(job), job.attempts, _kind(exc))
        return _fail(sessions, job, str(exc), retryable=True, settings=settings)
    except Exception as exc:
        fault = storage_fault(exc)
        if fault is not None:  # the service's fault, not the job's: wait, keep the attempt
            log.error("%s: %s (%s); postponed %.0f s", _named(job), _kind(fault), _kind(exc),
                      STORAGE_FAULT_DELAY_S)  # fmt: skip
            message = f"{fault} The job waits and retries by itself."
            return _postpone(sessions, job, message, settings=settings)
        log.exception("job %d (%s), attempt %d: unexpected error", job.id, job.kind, job.attempts)
        if job.attempts < job.max_attempts:
            message = UNEXPECTED_RETRY_MESSAGE.format(
                attempt=job.attempts, max_attempts=job.max_attempts
            )
        else:
            message = UNEXPECTED_FINAL_MESSAGE.format(max_attempts=job.max_attempts, job_id=job.id)
        return _fail(sessions, job, message, retryable=True, settings=settings)
    finally:
        beat.done.set()
        beat.join()


def _named(job: ClaimedJob) -> str:
    """The job as the log names it: its id, kind, trial or calibration."""
    target = f", trial {job.trial_id}" if job.trial_id is not None else ""
    if job.calibration_id is not None:
        target += f", calibration {job.calibration_id}"
    return f"job {job.id} ({job.kind}{target})"


def _kind(exc: BaseException) -> str:
    """An error as the log names it: its class, never its sentence. The sentences name the
    uploaded files as the clinic named them, often after the patient; the job keeps them
    for the pages (``Job.error``), the log does not."""
    return type(exc).__name__


STORAGE_FAULT_DELAY_S = 60.0
"""A job stopped by a full disk or an unreachable database waits this long (s) to retry."""


def _postpone(
    sessions: sessionmaker[Session], job: ClaimedJob, message: str, *, settings: Settings
) -> str:
    """Give the job back without spending its attempt. While the database cannot take
    that, retry (the heartbeat keeps the lease meanwhile) until the lease would run out:
    a job whose lease runs out is taken again, and that claim counts an attempt."""
    deadline = time.monotonic() + settings.job_lease_s - settings.heartbeat_s
    while True:
        try:
            return jobs.postpone(sessions, job, message, STORAGE_FAULT_DELAY_S)
        except LeaseLostError:
            log.warning("job %d: not postponed; another worker holds it now", job.id)
            return "lost"
        except DBAPIError as exc:
            if storage_fault(exc) is None or time.monotonic() >= deadline:
                raise
            log.warning("%s: not given back yet (%s); retrying", _named(job), _kind(exc))
            time.sleep(settings.heartbeat_s)


def _fail(
    sessions: sessionmaker[Session],
    job: ClaimedJob,
    message: str,
    *,
    retryable: bool,
    settings: Settings,
) -> str:
    try:
        return jobs.fail(
            sessions,
            job,
            message,
            retryable=retryable,
            retry_delay_s=settings.job_retry_delay_s,
        )
    except LeaseLostError:
        log.warning("job %d: failure not recorded; another worker holds it now", job.id)
        return "lost"


def lower_thread_priority(steps: int) -> int | None:
    """Give up ``steps`` of CPU priority (nice) in the calling thread; returns its niceness
    now, or None where that cannot be done for one thread.

    Linux keeps a niceness per thread, and a thread starts with its creator's: the
    worker's video decoders, started for each job, run at the worker's. The threads that
    answer pages, in the same ``serve`` process, keep theirs, and so does a browser
    recording on the same machine. Elsewhere a process's threads share one niceness: the
    web server's would drop with the worker's, so nothing is changed there.
    """
    if not sys.platform.startswith("linux"):
        return None
    tid = threading.get_native_id()
    now = min(19, os.getpriority(os.PRIO_PROCESS, tid) + steps)
    os.setpriority(os.PRIO_PROCESS, tid, now)
    return now


def _clean_tmp(storage: Storage) -> None:
    """Remove the partial files of crashed processes (unchanged for an hour)."""
    try:
        removed = storage.cleanup_tmp()
        if removed:
            log.info("removed %d stale temporary file(s) from %s", removed, storage.tmp_dir)
    except OSError:
        log.exception("could not clean %s", storage.tmp_dir)


def run_worker(
    settings: Settings,
    *,
    once: bool = False,
    stop_event: threading.Event | None = None,
    handlers: Mapping[str, Handler] | None = None,
    worker_name: str | None = None,
    max_jobs: int | None = None,
    nice: int = 0,
) -> int:
    """Run jobs until stopped; returns the number of jobs run.

    Parameters
    ----------
    settings
        The database must already be migrated (:func:`app.db.migrate`).
    once
        Drain the queue: run every job that can be claimed now, then return
        (tests, cron). Otherwise wait ``settings.worker_poll_s`` when idle.
    stop_event
        Set it to stop after the current job (graceful shutdown).
    handlers
        Handler per job kind (default :data:`HANDLERS`); only these kinds are claimed.
    worker_name
        Shown in ``Job.lease_owner`` (default ``host:pid``).
    max_jobs
        Return after this many jobs.
    nice
        CPU priority this thread gives up first (:func:`lower_thread_priority`;
        ``serve`` and ``worker`` pass ``settings.worker_nice``).
    """
    if nice:
        lower_thread_priority(nice)
    handlers = dict(HANDLERS if handlers is None else handlers)
    stop_event = stop_event or threading.Event()
    worker_name = worker_name or default_worker_name()
    sessions = get_sessionmaker(settings)
    storage = Storage.from_settings(settings)
    count = 0
    log.info("worker %s started (kinds: %s)", worker_name, ", ".join(sorted(handlers)))
    _clean_tmp(storage)
    while not stop_event.is_set() and (max_jobs is None or count < max_jobs):
        try:
            jobs.reap_expired(sessions)
            job = jobs.claim_next(
                sessions,
                worker_name=worker_name,
                lease_s=settings.job_lease_s,
                kinds=tuple(handlers),
            )
        except Exception:
            if once:
                raise
            log.exception("worker %s: cannot reach the job queue; retrying", worker_name)
            stop_event.wait(settings.worker_poll_s)
            continue
        if job is None:
            if once:
                break
            stop_event.wait(settings.worker_poll_s)
            continue
        try:
            run_job(
                job,
                settings=settings,
                handler=handlers[job.kind],
                sessions=sessions,
                storage=storage,
            )
        except Exception:
            # Even recording the job's end failed (a full disk, the database gone): the
            # worker lives on; the job's lease runs out and it is taken again.
            if once:
                raise
            log.exception("worker %s: job %d ended without its outcome recorded", worker_name,
                          job.id)  # fmt: skip
            stop_event.wait(settings.worker_poll_s)
        count += 1
    log.info("worker %s stopped after %d job(s)", worker_name, count)
    return count

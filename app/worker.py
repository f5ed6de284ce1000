"""The job worker: claims jobs from the queue and runs the pipeline on them.

:func:`run_worker` loops: fail jobs whose worker died too often
(:func:`app.jobs.reap_expired`), claim the next job, run its handler with a
heartbeat thread keeping the lease alive, then store the outcome:

- the handler's effect and "succeeded" in one transaction guarded by the lease
  (:meth:`JobContext.finish`), so a job is done exactly once in effect;
- a :class:`core.errors.BradyscopeError` or :class:`app.errors.AppError`
  becomes the job's user-facing error, without retry (bad input stays bad);
- a :class:`RetryableJobError` (e.g. video files missing on this worker) is
  retried until ``max_attempts`` and keeps its sentence;
- any other exception is logged with its traceback and retried until
  ``max_attempts``; the user sees a plain sentence, not the traceback;
- a lost lease (another worker took the job over) drops the attempt silently.

Handlers
--------
A handler is ``handler(ctx: JobContext) -> None`` registered per job kind
(:data:`HANDLERS`; tests pass their own ``handlers=``). The real ones are
``analyze_trial`` (``core.pipeline.analyze_recording`` → a ``Result``) and
``calibrate`` (``core.calibration.calibrate_stereo_from_paths`` → a ready
``Calibration``). What crosses to ``core`` and back is typed:
:class:`app.services.trials.TrialInputs` and ``core.pipeline.Analysis``,
:class:`app.services.calibrations.CalibrationInputs` and
``core.calibration.CalibrationResult``; the services read and store the rows.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from app import jobs
from app.db import get_sessionmaker
from app.errors import AppError
from app.jobs import ClaimedJob, LeaseLostError
from app.services import calibrations, revisions, trials
from app.settings import Settings
from app.storage import Storage
from core.calibration import calibrate_stereo_from_paths
from core.errors import BradyscopeError, InputError
from core.overlay import overlay_document
from core.pipeline import analyze_recording, write_markers_csv
from core.video import probe_video, write_proxy

log = logging.getLogger(__name__)

Handler = Callable[["JobContext"], None]


class RetryableJobError(Exception):
    """A failure another attempt (perhaps by another worker) may not have.

    Its message is user-facing and kept in the job; the job is retried until
    ``max_attempts``, like an unexpected error, but without hiding the reason.
    """


UNEXPECTED_RETRY_MESSAGE = (
    "an unexpected error interrupted attempt {attempt} of {max_attempts}; it will be retried."
)
UNEXPECTED_FINAL_MESSAGE = (
    "an unexpected error stopped this job after {max_attempts} attempts; ask the administrator "
    "to look up job {job_id} in the worker log."
)
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


# --------------------------------------------------------------------------- handlers


def _require_files(ctx: JobContext, paths: Iterable[Path], *, what: str) -> None:
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise RetryableJobError(
            f"the recorded files of {what} are missing from the data directory "
            f"{ctx.storage.data_dir} on worker {default_worker_name()}; every worker must use "
            "the same data directory (BRADYSCOPE_DATA_DIR)."
        )


def _upload_warnings(ctx: JobContext, document: dict[str, Any]) -> dict[str, Any]:
    """``document`` with the upload's warnings (kept in the job) added to its quality warnings."""
    upload_warnings = [str(w) for w in ctx.job.payload.get("warnings", ()) if w]
    if not upload_warnings:
        return document
    quality = dict(document.get("quality") or {})
    known = list(quality.get("warnings") or [])
    quality["warnings"] = known + [w for w in upload_warnings if w not in known]
    return {**document, "quality": quality}


def _make_proxies(ctx: JobContext, needed: dict[str, Path]) -> tuple[dict[str, str], list[str]]:
    """Browser proxies (``core.video.write_proxy``) of the videos that have none yet.

    Returns the stored paths by side, and a warning per video whose proxy could
    not be made (the measurement stands without it; the review view says so).
    """
    made: dict[str, str] = {}
    warnings: list[str] = []
    total = sum(max(1, probe_video(p).frame_count) for p in needed.values())
    done = 0
    for side, source in sorted(needed.items()):
        try:
            base = done

            def step(n: int, base: int = base) -> None:
                ctx.progress("proxy", base + n, total)

            with ctx.storage.writing("proxies", ".mp4") as (tmp, path):
                write_proxy(source, tmp, progress=step)
        except InputError as exc:
            log.warning("job %d: no proxy of the %s video: %s", ctx.job.id, side, exc)
            warnings.append(f"the {side} video cannot be shown in the review view: {exc}")
            continue
        done += probe_video(source).frame_count
        made[side] = path
    return made, warnings


def analyze_trial(ctx: JobContext) -> None:
    """Measure a trial's two videos with the pipeline and store the next result revision.

    The markers CSV and the review overlay are written under ``files/`` before
    the transaction, and the browser proxies of videos that have none; if the
    transaction is rejected (lease lost) those files are removed again. A
    re-analysis (the job's ``offset_frames`` or ``swap_cameras``, asked for
    through :mod:`app.services.revisions`) adds a revision; none is replaced.
    With ``swap_cameras`` the video stored as right is measured as the rig's
    left camera and the other way round.
    """
    payload = ctx.job.payload
    offset = payload.get("offset_frames")
    swap = bool(payload.get("swap_cameras"))
    with ctx.sessions() as db:
        inputs = trials.analysis_inputs(
            db,
            ctx.storage,
            ctx.job.trial_id,
            offset_frames=float(offset) if offset is not None else None,
        )
    _require_files(ctx, inputs.files, what=f"trial {inputs.trial_id}")
    left, right = (inputs.right, inputs.left) if swap else (inputs.left, inputs.right)
    left_times, right_times = (
        (inputs.right_times, inputs.left_times) if swap else (inputs.left_times, inputs.right_times)
    )
    analysis = analyze_recording(
        inputs.rig,
        left,
        right,
        offset_frames=inputs.offset_frames,
        progress=ctx.progress,
        left_times=left_times,
        right_times=right_times,
        task=inputs.task,
    )
    document = dict(analysis.result_document())
    document.setdefault("calibration", inputs.calibration.document())
    if swap:
        document["cameras_swapped"] = True
    document = _upload_warnings(ctx, document)
    overlay = overlay_document(analysis.overlays(inputs.rig), fps=analysis.fps)
    # Which stored video each rig camera's overlay belongs to.
    for cam in overlay["cameras"]:
        cam["video"] = {"left": "right", "right": "left"}[cam["camera"]] if swap else cam["camera"]

    written: list[str] = []
    try:
        with ctx.storage.writing("results", ".csv") as (tmp_path, markers_path):
            write_markers_csv(analysis, tmp_path)
        written.append(markers_path)
        with ctx.storage.writing("overlays", ".json") as (tmp_path, overlay_path):
            tmp_path.write_text(json.dumps(overlay, allow_nan=False), encoding="utf-8")
        written.append(overlay_path)
        proxies, proxy_warnings = _make_proxies(ctx, inputs.proxies_needed)
        written.extend(proxies.values())
        if proxy_warnings:
            quality = dict(document.get("quality") or {})
            quality["warnings"] = [*(quality.get("warnings") or []), *proxy_warnings]
            document["quality"] = quality

        def write(db: Session) -> None:
            revisions.store_analysis(
                db,
                trial_id=inputs.trial_id,
                job_id=ctx.job.id,
                calibration_id=inputs.calibration.id,
                document=document,
                markers_path=markers_path,
                overlay_path=overlay_path,
                request=payload.get("revision_request"),
            )
            trials.store_proxies(db, inputs.trial_id, proxies)

        ctx.finish(write)
    except BaseException:
        for path in written:
            ctx.storage.delete(path)
        raise


def calibrate(ctx: JobContext) -> None:
    """Calibrate a rig from its two board videos; the calibration becomes ``ready``."""
    with ctx.sessions() as db:
        inputs = calibrations.calibration_inputs(
            db, ctx.storage, ctx.job.calibration_id, board=ctx.job.payload.get("board")
        )
    _require_files(ctx, (inputs.left, inputs.right), what=f"calibration {inputs.calibration_id}")
    outcome = calibrate_stereo_from_paths(
        inputs.left, inputs.right, inputs.board, progress=ctx.progress
    )
    ctx.finish(lambda db: calibrations.store_calibration(db, inputs.calibration_id, outcome))


HANDLERS: dict[str, Handler] = {"analyze_trial": analyze_trial, "calibrate": calibrate}
STAGES: dict[str, tuple[tuple[str, float], ...]] = {
    # core.pipeline.analyze_recording's stages and their rough share of the run time.
    "analyze_trial": (
        ("detection", 0.85),
        ("synchronisation", 0.04),
        ("triangulation", 0.04),
        ("tracking", 0.04),
        ("metrics", 0.03),
        ("proxy", 0.15),
    ),
    # core.calibration.calibrate_stereo_from_paths's stages.
    "calibrate": (("detection", 0.7), ("calibration", 0.3)),
}
"""Ordered ``(stage, weight)`` per job kind: the job's progress fraction spans all stages.
Stages not listed report their own fraction."""


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
    except (BradyscopeError, AppError) as exc:
        log.info("job %d (%s) failed: %s", job.id, job.kind, exc)
        return _fail(sessions, job, str(exc), retryable=False, settings=settings)
    except RetryableJobError as exc:
        log.warning("job %d (%s), attempt %d: %s", job.id, job.kind, job.attempts, exc)
        return _fail(sessions, job, str(exc), retryable=True, settings=settings)
    except Exception:
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


def run_worker(
    settings: Settings,
    *,
    once: bool = False,
    stop_event: threading.Event | None = None,
    handlers: Mapping[str, Handler] | None = None,
    worker_name: str | None = None,
    max_jobs: int | None = None,
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
    """
    handlers = dict(HANDLERS if handlers is None else handlers)
    stop_event = stop_event or threading.Event()
    worker_name = worker_name or default_worker_name()
    sessions = get_sessionmaker(settings)
    storage = Storage.from_settings(settings)
    count = 0
    log.info("worker %s started (kinds: %s)", worker_name, ", ".join(sorted(handlers)))
    try:
        removed = storage.cleanup_tmp()  # partial files of crashed processes, a day old
        if removed:
            log.info("removed %d stale temporary file(s) from %s", removed, storage.tmp_dir)
    except OSError:
        log.exception("could not clean %s", storage.tmp_dir)
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
        run_job(
            job, settings=settings, handler=handlers[job.kind], sessions=sessions, storage=storage
        )
        count += 1
    log.info("worker %s stopped after %d job(s)", worker_name, count)
    return count

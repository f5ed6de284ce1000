# ruff: noqa: F811  (the small_recording fixture imported from test_worker is a parameter here)
"""A job's computed result survives a database outage while it is stored.

:meth:`app.job_context.JobContext.finish` tries its transaction again, after
:func:`app.job_context.store_retry_waits`, while the database is unreachable as
:func:`app.faults.storage_fault` says so; before, the result was thrown away and the job
computed again from the start. The finishing transaction's commit is made to fail here
with the drivers' own errors for an unreachable database (its statements reach the
database, the commit does not), or, on PostgreSQL, the database is taken away for real
through a TCP proxy (tests/app/tcp_proxy.py).
"""

from __future__ import annotations

import logging
import sqlite3
from collections.abc import Callable, Iterator
from datetime import UTC, datetime

import psycopg
import pytest
from sqlalchemy import event, select, update
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session
from test_worker import _trial_with_videos, small_recording  # noqa: F401 - a fixture

from app import handlers, jobs
from app.db import get_sessionmaker
from app.job_context import JobContext, store_retry_waits
from app.models import Job, Patient, RecordingSession, Result, Rig, Trial
from app.settings import Settings
from app.worker import UNEXPECTED_RETRY_MESSAGE, run_job, run_worker

PATIENT_FILE = "pacient_Novak_Jan.sqlite3"

OUTAGES: dict[str, Callable[[], Exception]] = {
    # psycopg could not reach the server (refused, cut): no SQLSTATE.
    "postgresql-refused": lambda: OperationalError(
        "COMMIT", None, psycopg.OperationalError("connection refused")
    ),
    # SQLite's file gone with its disk (a network share), named as the driver names it.
    "sqlite-unopened": lambda: OperationalError(
        "COMMIT", None, sqlite3.OperationalError(f"unable to open database file {PATIENT_FILE}")
    ),
}


class FinishCommits:
    """Counts the commits of finishing transactions (:meth:`JobContext.finish`) and makes
    the first ``fail`` of them raise ``outage()``: before the commit (nothing stored) or,
    ``answer_lost``, after it (stored, but the answer cut off on its way back)."""

    def __init__(self, fail: int, outage: Callable[[], Exception], *, answer_lost: bool) -> None:
        self.fail_left = fail
        self.outage = outage
        self.answer_lost = answer_lost
        self.tries = 0

    def before_commit(self, session: Session) -> None:
        if not session.info.get("finishing"):
            return
        self.tries += 1
        session.flush()  # the transaction's statements reach the database
        if not self.answer_lost:
            self._fail()

    def after_commit(self, session: Session) -> None:
        if session.info.get("finishing") and self.answer_lost:
            self._fail()

    def _fail(self) -> None:
        if self.fail_left > 0:
            self.fail_left -= 1
            raise self.outage()


@pytest.fixture
def finish_commits(
    monkeypatch: pytest.MonkeyPatch,
) -> Iterator[Callable[..., FinishCommits]]:
    """``finish_commits(fail, outage, answer_lost=False)``: a :class:`FinishCommits` in
    force until the test ends."""
    installed: list[FinishCommits] = []
    complete = jobs.complete

    def completing(db: Session, job: jobs.ClaimedJob) -> None:
        complete(db, job)
        db.info["finishing"] = True

    monkeypatch.setattr(jobs, "complete", completing)

    def install(
        fail: int, outage: Callable[[], Exception], *, answer_lost: bool = False
    ) -> FinishCommits:
        faults = FinishCommits(fail, outage, answer_lost=answer_lost)
        event.listen(Session, "before_commit", faults.before_commit)
        event.listen(Session, "after_commit", faults.after_commit)
        installed.append(faults)
        return faults

    yield install
    for faults in installed:
        event.remove(Session, "before_commit", faults.before_commit)
        event.remove(Session, "after_commit", faults.after_commit)


@pytest.fixture
def settings(app_settings: Settings) -> Settings:
    """A short lease, so that the tries' waits are short (0.8 s in all)."""
    return app_settings.model_copy(update={"job_lease_s": 1.0, "job_heartbeat_s": 0.2})


def _enqueue(sessions, kind: str = "analyze_trial") -> tuple[int, int]:
    """(trial id, job id): a new trial and its job."""
    with sessions() as db, db.begin():
        rig, patient = Rig(name="r"), Patient(code="PD-11")
        db.add_all([rig, patient])
        db.flush()
        session = RecordingSession(
            patient_id=patient.id, rig_id=rig.id, recorded_at=datetime(2026, 1, 1, tzinfo=UTC)
        )
        db.add(session)
        db.flush()
        trial = Trial(session_id=session.id, hand="left")
        db.add(trial)
        db.flush()
        return trial.id, jobs.enqueue(db, kind, trial_id=trial.id, max_attempts=3).id


def _job(sessions, job_id: int) -> Job:
    with sessions() as db:
        job = db.get(Job, job_id)
        assert job is not None
        return job


def _results(sessions, trial_id: int) -> list[dict]:
    with sessions() as db:
        return [r.document for r in db.scalars(select(Result).where(Result.trial_id == trial_id))]


class _Measuring:
    """A handler that computes once per call (``computed``; its result says which
    computation it is) and adds that result each time its ``write`` is called (``writes``),
    then calls ``on_write(db)``."""

    def __init__(self, trial_id: int, on_write: Callable[[Session], None] | None = None) -> None:
        self.trial_id = trial_id
        self.on_write = on_write
        self.computed = 0
        self.writes = 0

    def __call__(self, ctx: JobContext) -> None:
        self.computed += 1
        document = {"computation": self.computed}

        def write(db: Session) -> None:
            self.writes += 1
            db.add(Result(trial_id=self.trial_id, job_id=ctx.job.id, document=document))
            if self.on_write is not None:
                self.on_write(db)

        ctx.finish(write)


# --------------------------------------------------------------------------- the waits


@pytest.mark.parametrize(
    "lease", [{}, {"job_lease_s": 1.0, "job_heartbeat_s": 0.2}, {"job_lease_s": 20.0}]
)
def test_the_waits_grow_up_to_a_heartbeat_and_end_within_the_lease(tmp_path, lease) -> None:
    settings = Settings(data_dir=tmp_path, **lease)
    waits = list(store_retry_waits(settings))
    assert len(waits) >= 3  # a few tries, not one
    assert sum(waits) == pytest.approx(settings.job_lease_s - settings.heartbeat_s)
    assert max(waits) == pytest.approx(settings.heartbeat_s)
    growing = waits[:-1]
    assert growing == sorted(growing) and growing[1] == pytest.approx(2 * growing[0])


def test_no_wait_when_the_heartbeat_leaves_no_time_in_the_lease(tmp_path) -> None:
    settings = Settings(data_dir=tmp_path, job_lease_s=1.0, job_heartbeat_s=1.0)
    assert list(store_retry_waits(settings)) == []


# --------------------------------------------------------------------------- stored by a retry


@pytest.mark.parametrize("outage", sorted(OUTAGES))
def test_a_result_whose_commits_meet_an_outage_is_stored_by_a_later_try(
    settings, db_sessionmaker, finish_commits, caplog, outage
) -> None:
    """The first two commits of the result fail as an unreachable database's do: the
    third stores the result computed once, on the job's first attempt."""
    trial_id, job_id = _enqueue(db_sessionmaker)
    faults = finish_commits(2, OUTAGES[outage])
    handler = _Measuring(trial_id)
    with caplog.at_level(logging.WARNING, logger="app"):
        run_worker(settings, once=True, max_jobs=1, handlers={"analyze_trial": handler})
    job = _job(db_sessionmaker, job_id)
    assert (job.status, job.attempts, job.error) == ("succeeded", 1, None)
    assert (handler.computed, handler.writes, faults.tries) == (1, 3, 3)
    assert _results(db_sessionmaker, trial_id) == [{"computation": 1}]
    with db_sessionmaker() as db:
        assert db.get(Trial, trial_id).status == "succeeded"
    waiting = [r for r in caplog.records if "not stored yet" in r.getMessage()]
    assert len(waiting) == 2
    assert all(f"job {job_id} (analyze_trial)" in r.getMessage() for r in waiting)
    assert "OperationalError" in caplog.text and "Novak" not in caplog.text


def test_a_commit_whose_answer_was_lost_is_found_stored(
    settings, db_sessionmaker, finish_commits
) -> None:
    """The commit got through but its answer was cut off: the next try finds the job
    succeeded under its own claim, and the job ends succeeded (not lost: an analysis's
    files, which the stored result names, would be removed then)."""
    trial_id, job_id = _enqueue(db_sessionmaker)
    faults = finish_commits(1, OUTAGES["postgresql-refused"], answer_lost=True)
    handler = _Measuring(trial_id)
    claimed = jobs.claim_next(db_sessionmaker, worker_name="w", lease_s=settings.job_lease_s)
    assert claimed is not None and claimed.id == job_id
    assert run_job(claimed, settings=settings, handler=handler) == "succeeded"
    job = _job(db_sessionmaker, job_id)
    assert (job.status, job.attempts) == ("succeeded", 1)
    # The second try stops at the job's row, already succeeded: no second write.
    assert (handler.computed, handler.writes, faults.tries) == (1, 1, 1)
    assert _results(db_sessionmaker, trial_id) == [{"computation": 1}]


# --------------------------------------------------------------------------- given up


def test_an_outage_outlasting_the_tries_gives_the_job_back_with_its_attempt(
    settings, db_sessionmaker, finish_commits, caplog
) -> None:
    """Every commit fails: after the last wait the job is given back as before the
    tries, its attempt not spent, and the log says so without the driver's words."""
    trial_id, job_id = _enqueue(db_sessionmaker)
    faults = finish_commits(10**6, OUTAGES["sqlite-unopened"])
    handler = _Measuring(trial_id)
    with caplog.at_level(logging.INFO, logger="app"):
        run_worker(settings, once=True, max_jobs=1, handlers={"analyze_trial": handler})
    job = _job(db_sessionmaker, job_id)
    assert (job.status, job.attempts) == ("queued", 0), (job.status, job.error)
    assert "The job waits and retries by itself." in (job.error or "")
    tries = len(list(store_retry_waits(settings))) + 1
    assert (handler.computed, handler.writes, faults.tries) == (1, tries, tries)
    assert _results(db_sessionmaker, trial_id) == []
    assert f"job {job_id} (analyze_trial): its result could not be stored" in caplog.text
    assert f"in {tries} tries (OperationalError)" in caplog.text
    assert "postponed" in caplog.text and "Novak" not in caplog.text


def test_a_job_taken_over_during_the_tries_stores_nothing(
    settings, db_sessionmaker, finish_commits
) -> None:
    """Another worker takes the job over while this one waits to try again: the next try
    finds the lease lost and this worker stops, its result not stored."""
    trial_id, job_id = _enqueue(db_sessionmaker)
    faults = finish_commits(10**6, OUTAGES["postgresql-refused"])

    class _TakeOver(logging.Handler):
        done = False

        def emit(self, record: logging.LogRecord) -> None:
            if "not stored yet" in record.getMessage() and not self.done:
                self.done = True
                with db_sessionmaker() as db, db.begin():
                    db.execute(update(Job).where(Job.id == job_id).values(lease_owner="other"))

    take_over = _TakeOver(logging.WARNING)
    logging.getLogger("app.job_context").addHandler(take_over)
    handler = _Measuring(trial_id)
    try:
        run_worker(settings, once=True, max_jobs=1, handlers={"analyze_trial": handler})
    finally:
        logging.getLogger("app.job_context").removeHandler(take_over)
    job = _job(db_sessionmaker, job_id)
    assert (job.status, job.lease_owner, job.attempts) == ("running", "other", 1)
    assert take_over.done and faults.tries == 1  # the next try found the job taken
    assert _results(db_sessionmaker, trial_id) == []


# --------------------------------------------------------------------------- not retried


def _duplicate_revision(db: Session, trial_id: int, job_id: int) -> None:
    db.add(Result(trial_id=trial_id, job_id=job_id, revision=1, document={}))
    db.flush()  # revision 1 of this trial is there already: UNIQUE (trial_id, revision)


def _a_bug(db: Session, trial_id: int, job_id: int) -> None:
    raise ZeroDivisionError("a bug in the handler")


@pytest.mark.parametrize("write", [_duplicate_revision, _a_bug], ids=["integrity", "bug"])
def test_errors_other_than_an_outage_are_not_tried_again(
    settings, db_sessionmaker, caplog, write
) -> None:
    """An integrity error or a bug is the job's, not the database's absence: raised at
    once (one write), and the attempt is spent as any unexpected error's."""
    trial_id, job_id = _enqueue(db_sessionmaker)
    with db_sessionmaker() as db, db.begin():
        db.add(Result(trial_id=trial_id, job_id=job_id, revision=1, document={"earlier": 1}))
    writes: list[int] = []
    errors: list[BaseException] = []

    def handler(ctx: JobContext) -> None:
        def store(db: Session) -> None:
            writes.append(1)
            write(db, trial_id, ctx.job.id)

        try:
            ctx.finish(store)
        except BaseException as exc:
            errors.append(exc)
            raise

    with caplog.at_level(logging.WARNING, logger="app"):
        run_worker(settings, once=True, max_jobs=1, handlers={"analyze_trial": handler})
    expected = IntegrityError if write is _duplicate_revision else ZeroDivisionError
    assert len(writes) == 1 and [type(e) for e in errors] == [expected]
    job = _job(db_sessionmaker, job_id)
    assert (job.status, job.attempts) == ("queued", 1)
    assert job.error == UNEXPECTED_RETRY_MESSAGE.format(attempt=1, max_attempts=3)
    assert "not stored yet" not in caplog.text
    assert _results(db_sessionmaker, trial_id) == [{"earlier": 1}]


# --------------------------------------------------------------------------- a real analysis


@pytest.mark.slow
def test_an_analysis_stored_through_an_outage_is_measured_once_and_keeps_its_files(
    app_settings, db_sessionmaker, storage, small_recording, finish_commits, monkeypatch
) -> None:
    """The real analysis handler: its result's first two commits fail; the third stores
    it, the recording measured once, and every file the result names (markers, overlay,
    plots, proxies) is there, none left over in the temporary folder."""
    measured: list[int] = []
    analyze = handlers.analyze_recording

    def counting(*args, **kwargs):
        measured.append(1)
        return analyze(*args, **kwargs)

    monkeypatch.setattr(handlers, "analyze_recording", counting)
    with db_sessionmaker() as db, db.begin():
        trial_id, job_id = _trial_with_videos(db, storage, small_recording, calibrated=True)
    faults = finish_commits(2, OUTAGES["postgresql-refused"])
    run_worker(app_settings, once=True, max_jobs=1)
    job = _job(db_sessionmaker, job_id)
    assert (job.status, job.attempts, job.error) == ("succeeded", 1, None)
    assert (len(measured), faults.tries) == (1, 3)
    with db_sessionmaker() as db:
        result = db.scalars(select(Result).where(Result.trial_id == trial_id)).one()
        proxies = [v.proxy_path for v in db.get(Trial, trial_id).videos]
    assert result.document["metrics"]["tap_count"] == small_recording.truth["tap_count"]
    named = [result.markers_path, result.overlay_path, result.plots_path, *proxies]
    assert len(named) == 5 and all(p and storage.absolute(p).is_file() for p in named), named
    assert list(storage.tmp_dir.iterdir()) == []


# --------------------------------------------------------------------------- PostgreSQL


@pytest.mark.postgres
def test_postgresql_gone_while_a_result_is_stored_then_back_stores_it(proxied) -> None:
    """The database server goes away for real as the result is written (the connection
    cut, new ones refused) and returns once the worker has met its absence: the result,
    computed once, is stored on the job's first attempt."""
    settings, proxy = proxied
    settings = settings.model_copy(update={"job_lease_s": 30.0, "job_heartbeat_s": 2.0})
    sessions = get_sessionmaker(settings)
    trial_id, job_id = _enqueue(sessions)

    def cut_in_the_first_write(db: Session) -> None:
        if handler.writes == 1:
            db.flush()  # the result's rows reach the server, then it is gone
            proxy.stop()

    handler = _Measuring(trial_id, on_write=cut_in_the_first_write)

    class _Back(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if "not stored yet" in record.getMessage():
                proxy.start()

    back = _Back(logging.WARNING)
    logging.getLogger("app.job_context").addHandler(back)
    try:
        run_worker(settings, once=True, max_jobs=1, handlers={"analyze_trial": handler})
    finally:
        logging.getLogger("app.job_context").removeHandler(back)
        proxy.start()
    job = _job(sessions, job_id)
    assert (job.status, job.attempts) == ("succeeded", 1), (job.status, job.error)
    assert (handler.computed, handler.writes) == (1, 2)
    assert _results(sessions, trial_id) == [{"computation": 1}]

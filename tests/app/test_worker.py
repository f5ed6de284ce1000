"""The worker loop: outcomes of handlers, progress, retries, lease loss, and kill -9 take-over."""

from __future__ import annotations

import threading
from datetime import UTC, datetime

import pytest
from sqlalchemy import select

from app import jobs
from app.errors import InvalidRequestError
from app.jobs import LeaseLostError
from app.models import Job, Patient, RecordingSession, Result, Rig, Trial
from app.worker import JobContext, run_job, run_worker
from core.errors import DetectionError


def _enqueue_trial_job(sm, **kw) -> tuple[int, int]:
    with sm() as db, db.begin():
        rig, patient = Rig(name="r"), Patient(code="PD-7")
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
        return trial.id, jobs.enqueue(db, "analyze_trial", trial_id=trial.id, **kw).id


def _job(sm, job_id) -> Job:
    with sm() as db:
        return db.get(Job, job_id)


def test_success_stores_effect_and_marks_trial(app_settings, db_sessionmaker):
    sm = db_sessionmaker
    trial_id, job_id = _enqueue_trial_job(sm)
    seen: list[tuple[str, float]] = []

    def handler(ctx: JobContext) -> None:
        for done in range(4):
            ctx.progress("tracking", done, 4)
            seen.append((_job(sm, job_id).stage, _job(sm, job_id).progress))
        ctx.finish(lambda db: db.add(Result(trial_id=trial_id, job_id=job_id, document={"a": 1})))

    assert run_worker(app_settings, once=True, handlers={"analyze_trial": handler}) == 1
    job = _job(sm, job_id)
    assert (job.status, job.progress, job.stage, job.attempts) == ("succeeded", 1.0, "done", 1)
    assert seen[0] == ("tracking", 0.0)  # a stage change is written at once
    with sm() as db:
        assert db.get(Trial, trial_id).status == "succeeded"
        assert [r.document for r in db.scalars(select(Result))] == [{"a": 1}]


def test_progress_spans_known_stages(app_settings, db_sessionmaker, monkeypatch):
    from app import worker

    sm = db_sessionmaker
    _, job_id = _enqueue_trial_job(sm)
    monkeypatch.setitem(worker.STAGES, "analyze_trial", ("detection", "tracking"))
    fractions = []

    def handler(ctx: JobContext) -> None:
        ctx.progress("detection", 1, 2)
        ctx.beat()
        fractions.append(_job(sm, job_id).progress)
        ctx.progress("tracking", 1, 2)
        ctx.beat()
        fractions.append(_job(sm, job_id).progress)

    run_worker(app_settings, once=True, handlers={"analyze_trial": handler})
    assert fractions == [0.25, 0.75]


@pytest.mark.parametrize(
    "error",
    [
        DetectionError("no markers were found in the left video; check the lighting."),
        InvalidRequestError("trial 1 has no right video; upload the trial again."),
    ],
)
def test_domain_errors_fail_at_once_with_their_sentence(app_settings, db_sessionmaker, error):
    sm = db_sessionmaker
    trial_id, job_id = _enqueue_trial_job(sm)
    calls = []

    def handler(ctx: JobContext) -> None:
        calls.append(ctx.job.attempts)
        raise error

    run_worker(app_settings, once=True, handlers={"analyze_trial": handler})
    job = _job(sm, job_id)
    assert (job.status, job.error, calls) == ("failed", str(error), [1])
    with sm() as db:
        assert db.get(Trial, trial_id).status == "failed"


def test_unexpected_errors_retry_then_fail_without_traceback(app_settings, db_sessionmaker):
    sm = db_sessionmaker
    _, job_id = _enqueue_trial_job(sm, max_attempts=3)
    calls = []

    def handler(ctx: JobContext) -> None:
        calls.append(ctx.job.attempts)
        raise ZeroDivisionError("internal detail")

    assert run_worker(app_settings, once=True, handlers={"analyze_trial": handler}) == 3
    job = _job(sm, job_id)
    assert calls == [1, 2, 3]
    assert job.status == "failed" and f"job {job_id}" in job.error
    assert "ZeroDivision" not in job.error and "internal detail" not in job.error


def test_transient_error_then_success(app_settings, db_sessionmaker):
    sm = db_sessionmaker
    _, job_id = _enqueue_trial_job(sm)

    def handler(ctx: JobContext) -> None:
        if ctx.job.attempts == 1:
            raise OSError("disk hiccup")

    run_worker(app_settings, once=True, handlers={"analyze_trial": handler})
    job = _job(sm, job_id)
    assert (job.status, job.attempts, job.error) == ("succeeded", 2, None)


def test_worker_that_lost_its_lease_stores_nothing(app_settings, db_sessionmaker):
    from datetime import timedelta

    from app.models import utcnow

    sm = db_sessionmaker
    trial_id, job_id = _enqueue_trial_job(sm)
    stale = jobs.claim_next(sm, worker_name="stale", lease_s=1.0)
    fresh = jobs.claim_next(
        sm, worker_name="fresh", lease_s=60.0, now=utcnow() + timedelta(seconds=2)
    )
    assert fresh is not None

    def handler(ctx: JobContext) -> None:
        ctx.finish(lambda db: db.add(Result(trial_id=trial_id, job_id=job_id, document={})))

    assert run_job(stale, settings=app_settings, handler=handler) == "lost"
    with sm() as db:
        assert db.scalars(select(Result)).all() == []
    assert _job(sm, job_id).lease_owner == fresh.lease_owner

    def slow_handler(ctx: JobContext) -> None:  # progress notices the loss and stops
        with pytest.raises(LeaseLostError):
            ctx.beat()
        ctx.progress("tracking", 1, 10)

    assert run_job(stale, settings=app_settings, handler=slow_handler) == "lost"


def test_stop_event_stops_an_idle_worker(app_settings):
    stop = threading.Event()
    thread = threading.Thread(
        target=run_worker, args=(app_settings,), kwargs={"stop_event": stop, "handlers": {}}
    )
    thread.start()
    stop.set()
    thread.join(timeout=10)
    assert not thread.is_alive()


def test_kill9_of_a_worker_mid_job_sqlite(app_settings, worker_script, kill9_scenario):
    kill9_scenario(app_settings, worker_script)

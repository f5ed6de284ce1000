"""The job queue: claim order, leases, take-over, exactly-once effect, bounded retries."""

from __future__ import annotations

import threading
from datetime import UTC, datetime, timedelta

import pytest
from sqlalchemy import func, select

from app import job_views, jobs
from app.jobs import LeaseLostError
from app.models import Job, Patient, RecordingSession, Result, Rig, Trial, utcnow
from app.services import trials

LEASE_S = 5.0


def _trial(db) -> Trial:
    rig, patient = Rig(name=f"rig-{utcnow().timestamp()}"), Patient(code=f"PD-{utcnow()}")
    db.add_all([rig, patient])
    db.flush()
    session = RecordingSession(
        patient_id=patient.id, rig_id=rig.id, recorded_at=datetime(2026, 1, 5, tzinfo=UTC)
    )
    db.add(session)
    db.flush()
    trial = Trial(session_id=session.id, hand="right")
    db.add(trial)
    db.flush()
    return trial


def _claim(sm, name="w1", **kw):
    return jobs.claim_next(sm, worker_name=name, lease_s=LEASE_S, **kw)


def _job(sm, job_id) -> Job:
    with sm() as db:
        return db.get(Job, job_id)


def test_enqueue_then_claim_oldest_first(db_sessionmaker):
    sm = db_sessionmaker
    with sm() as db, db.begin():
        first = jobs.enqueue(db, "analyze_trial", payload={"n": 1}).id
        second = jobs.enqueue(db, "analyze_trial", payload={"n": 2}).id
    a = _claim(sm)
    b = _claim(sm)
    assert (a.id, b.id) == (first, second)
    assert a.payload == {"n": 1} and a.attempts == 1 and a.lease_owner != b.lease_owner
    assert _claim(sm) is None
    job = _job(sm, first)
    assert job.status == "running" and job.lease_owner == a.lease_owner
    assert job.lease_expires_at > utcnow() and job.heartbeat_at is not None


def test_claim_filters_by_kind(db_sessionmaker):
    sm = db_sessionmaker
    with sm() as db, db.begin():
        jobs.enqueue(db, "calibrate")
    assert _claim(sm, kinds=("analyze_trial",)) is None
    assert _claim(sm, kinds=("calibrate",)).kind == "calibrate"


def test_claim_marks_the_trial_running_and_complete_stores_effect_once(db_sessionmaker):
    sm = db_sessionmaker
    with sm() as db, db.begin():
        trial_id = _trial(db).id
        job_id = jobs.enqueue(db, "analyze_trial", trial_id=trial_id).id
    claimed = _claim(sm)
    with sm() as db:
        assert db.get(Trial, trial_id).status == "running"
    with sm() as db, db.begin():
        jobs.complete(db, claimed)
        db.add(Result(trial_id=trial_id, job_id=job_id, document={"ok": True}))
    job = _job(sm, job_id)
    assert (job.status, job.progress, job.error) == ("succeeded", 1.0, None)
    with pytest.raises(LeaseLostError):  # completing twice is refused
        with sm() as db, db.begin():
            jobs.complete(db, claimed)
    assert _claim(sm) is None


def test_expired_lease_is_reclaimed_and_stale_worker_is_rejected(db_sessionmaker):
    sm = db_sessionmaker
    with sm() as db, db.begin():
        trial_id = _trial(db).id
        job_id = jobs.enqueue(db, "analyze_trial", trial_id=trial_id).id
    stale = _claim(sm, "stale")
    # Not claimable while the lease runs...
    assert _claim(sm, "fresh", now=utcnow() + timedelta(seconds=LEASE_S / 2)) is None
    # ...but claimable once it expired (the stale worker went silent).
    fresh = _claim(sm, "fresh", now=utcnow() + timedelta(seconds=LEASE_S + 1))
    assert fresh is not None and fresh.id == job_id and fresh.attempts == 2

    with pytest.raises(LeaseLostError):
        jobs.heartbeat(sm, stale, lease_s=LEASE_S)
    with pytest.raises(LeaseLostError):  # the late write is rolled back entirely
        with sm() as db, db.begin():
            jobs.complete(db, stale)
            db.add(Result(trial_id=trial_id, job_id=job_id, document={"by": "stale"}))
    with pytest.raises(LeaseLostError):
        jobs.fail(sm, stale, "late failure", retryable=True)

    jobs.heartbeat(sm, fresh, lease_s=LEASE_S, progress=0.5, stage="tracking")
    assert (_job(sm, job_id).progress, _job(sm, job_id).stage) == (0.5, "tracking")
    with sm() as db, db.begin():
        jobs.complete(db, fresh)
        db.add(Result(trial_id=trial_id, job_id=job_id, document={"by": "fresh"}))
    with sm() as db:
        results = db.scalars(select(Result)).all()
        assert [r.document for r in results] == [{"by": "fresh"}]


def test_retryable_failures_are_bounded(db_sessionmaker):
    sm = db_sessionmaker
    with sm() as db, db.begin():
        trial_id = _trial(db).id
        job_id = jobs.enqueue(db, "analyze_trial", trial_id=trial_id, max_attempts=2).id
    first = _claim(sm)
    assert jobs.fail(sm, first, "boom 1", retryable=True) == "queued"
    job = _job(sm, job_id)
    assert (job.status, job.error, job.lease_owner) == ("queued", "boom 1", None)
    with sm() as db:
        assert db.get(Trial, trial_id).status == "queued"
    second = _claim(sm)
    assert second.attempts == 2
    assert jobs.fail(sm, second, "boom 2", retryable=True) == "failed"
    job = _job(sm, job_id)
    assert (job.status, job.error) == ("failed", "boom 2") and job.finished_at is not None
    with sm() as db:
        assert db.get(Trial, trial_id).status == "failed"
    # Only the failure for good queues the reports of the trial's visit, which waited for it.
    report = _claim(sm)
    assert report is not None and (report.kind, report.trial_id) == (jobs.REPORT_PDF, trial_id)
    assert _claim(sm) is None


def test_retry_waits_for_its_delay(db_sessionmaker):
    sm = db_sessionmaker
    with sm() as db, db.begin():
        jobs.enqueue(db, "analyze_trial")
    claimed = _claim(sm)
    jobs.fail(sm, claimed, "boom", retryable=True, retry_delay_s=60.0)
    assert _claim(sm) is None
    assert _claim(sm, now=utcnow() + timedelta(seconds=61)) is not None


def test_non_retryable_failure_is_final(db_sessionmaker):
    sm = db_sessionmaker
    with sm() as db, db.begin():
        job_id = jobs.enqueue(db, "analyze_trial").id
    claimed = _claim(sm)
    assert jobs.fail(sm, claimed, "the left video has no markers", retryable=False) == "failed"
    assert _job(sm, job_id).error == "the left video has no markers"


def test_reap_fails_jobs_whose_worker_died_on_the_last_attempt(db_sessionmaker):
    sm = db_sessionmaker
    with sm() as db, db.begin():
        trial_id = _trial(db).id
        job_id = jobs.enqueue(db, "analyze_trial", trial_id=trial_id, max_attempts=1).id
    _claim(sm)
    later = utcnow() + timedelta(seconds=LEASE_S + 1)
    assert _claim(sm, now=later) is None  # no attempts left: not re-claimed
    assert jobs.reap_expired(sm, now=utcnow()) == 0  # lease still valid now
    assert jobs.reap_expired(sm, now=later) == 1
    job = _job(sm, job_id)
    assert job.status == "failed" and "stopped 1 times" in job.error
    with sm() as db:
        assert db.get(Trial, trial_id).status == "failed"
        reports = db.scalars(select(Job).where(Job.kind == jobs.REPORT_PDF)).all()
        assert [(r.trial_id, r.status) for r in reports] == [(trial_id, "queued")]


def test_concurrent_claims_on_sqlite_never_share_a_job(db_sessionmaker):
    sm = db_sessionmaker
    n_jobs, n_threads = 40, 4
    with sm() as db, db.begin():
        ids = {jobs.enqueue(db, "analyze_trial").id for _ in range(n_jobs)}
    claimed: list[int] = []
    lock = threading.Lock()
    barrier = threading.Barrier(n_threads)

    def grab(name: str) -> None:
        barrier.wait()
        while (job := _claim(sm, name)) is not None:
            with lock:
                claimed.append(job.id)

    threads = [threading.Thread(target=grab, args=(f"t{i}",)) for i in range(n_threads)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert sorted(claimed) == sorted(ids)  # each exactly once
    with sm() as db:
        assert db.scalar(select(func.count()).where(Job.status == "running")) == n_jobs


def test_job_status_view(db_sessionmaker):
    sm = db_sessionmaker
    with sm() as db, db.begin():
        job_id = jobs.enqueue(db, "calibrate").id
    with sm() as db:
        view = job_views.job_status(db, job_id)
        assert (view["status"], view["progress"], view["stage"], view["error"]) == (
            "queued",
            0.0,
            None,
            None,
        )
        assert job_views.job_status(db, 999) is None


def test_enqueue_validates_arguments(db_session):
    with pytest.raises(ValueError, match="max_attempts"):
        jobs.enqueue(db_session, "calibrate", max_attempts=0)
    with pytest.raises(ValueError, match="kind"):
        jobs.enqueue(db_session, "")


def test_cancel_a_queued_job_and_a_running_one(db_sessionmaker):
    sm = db_sessionmaker
    with sm() as db, db.begin():
        queued = jobs.enqueue(db, "analyze_trial").id
        running = jobs.enqueue(db, "analyze_trial").id
    with sm() as db, db.begin():
        assert jobs.cancel(db, queued, "the trial was deleted")
    claimed = _claim(sm)
    assert claimed.id == running  # the cancelled job is not claimed
    with sm() as db, db.begin():
        assert jobs.cancel(db, running, "the trial was deleted")
    with pytest.raises(LeaseLostError):  # its worker finds out and stores nothing
        jobs.heartbeat(sm, claimed, lease_s=LEASE_S)
    with pytest.raises(LeaseLostError):
        with sm() as db, db.begin():
            jobs.complete(db, claimed)
    assert (_job(sm, running).status, _job(sm, running).error) == (
        "failed",
        "the trial was deleted",
    )
    with sm() as db, db.begin():
        assert not jobs.cancel(db, running, "again")  # already ended


def test_report_jobs_are_claimed_first_and_queued_once_per_trial(db_sessionmaker):
    sm = db_sessionmaker
    with sm() as db, db.begin():
        measured, other = _trial(db), _trial(db)
        analysis = jobs.enqueue(db, "analyze_trial", trial_id=other.id).id
        report = jobs.enqueue_report_pdf(db, measured.id)
        assert report is not None
        assert jobs.enqueue_report_pdf(db, measured.id) is None  # the queued one covers it
        report_id = report.id
    assert report_id > analysis
    with sm() as db:
        queued = {j.id: j for j in db.scalars(select(Job))}
        assert [trials.queue_position(db, queued[i]) for i in (report_id, analysis)] == [1, 2]
    assert [_claim(sm).id, _claim(sm).id] == [report_id, analysis]
    with sm() as db, db.begin():  # running: a change now needs a job of its own
        assert jobs.enqueue_report_pdf(db, measured.id) is not None


def test_a_report_job_is_no_trials_latest_job_and_leaves_its_status(db_sessionmaker):
    """A trial's status and its job on the pages follow its analyses only."""
    sm = db_sessionmaker
    with sm() as db, db.begin():
        trial_id = _trial(db).id
        analysis = jobs.enqueue(db, "analyze_trial", trial_id=trial_id).id
        report = jobs.enqueue(db, jobs.REPORT_PDF, trial_id=trial_id, max_attempts=1).id
    with sm() as db:
        assert job_views.latest_job(db, trial_id=trial_id).id == analysis
        assert job_views.latest_jobs(db, trial_ids=[trial_id])[trial_id].id == analysis
    claimed = _claim(sm, kinds=(jobs.REPORT_PDF,))
    assert claimed.id == report
    with sm() as db:
        assert db.get(Trial, trial_id).status == "queued"  # its analysis has not started
    assert jobs.fail(sm, claimed, "WeasyPrint failed", retryable=False) == "failed"
    with sm() as db:
        assert db.get(Trial, trial_id).status == "queued"
    claimed = _claim(sm)
    assert claimed.id == analysis
    with sm() as db:
        assert db.get(Trial, trial_id).status == "running"


def test_every_kind_the_worker_runs_is_a_listed_job_kind() -> None:
    from app.handlers import HANDLERS
    from app.models import JOB_KINDS

    assert sorted(HANDLERS) == sorted(JOB_KINDS)
    assert jobs.REPORT_PDF in JOB_KINDS


def test_a_full_disk_postpones_the_job_without_spending_its_attempts(
    app_settings, db_sessionmaker, monkeypatch
):
    """An operations review filled the disk: the analysis used its three attempts in
    seconds and said "an unexpected error"; and once even recording a job's end failed,
    the worker thread died and the queue stood still until a restart."""
    import errno
    import threading

    from app.worker import run_worker

    with db_sessionmaker() as db:
        first = jobs.enqueue(db, "analyze_trial", trial_id=_trial(db).id).id
        second = jobs.enqueue(db, "analyze_trial", trial_id=_trial(db).id).id
        db.commit()

    def full(ctx) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    assert run_worker(app_settings, handlers={"analyze_trial": full}, max_jobs=1) == 1
    job = _job(db_sessionmaker, first)
    assert (job.status, job.attempts) == ("queued", 0)
    assert "storage is full" in job.error and "retries by itself" in job.error
    assert job.run_after.replace(tzinfo=UTC) > utcnow() + timedelta(seconds=30)

    # Recording the outcome fails too (the database on the full disk): the worker lives on.
    def broken_fail(*args, **kwargs):
        raise RuntimeError("database or disk is full")

    monkeypatch.setattr(jobs, "fail", broken_fail)
    done: list[str] = []

    def refused(ctx) -> None:
        done.append("ran")
        raise ValueError("not a storage fault")

    stop = threading.Event()
    worker = threading.Thread(
        target=run_worker,
        args=(app_settings,),
        kwargs={"handlers": {"analyze_trial": refused}, "stop_event": stop, "max_jobs": 2},
    )
    worker.start()
    worker.join(timeout=30)
    stop.set()
    # the worker lived on: it took the job again once its lease ran out (the first job
    # waits for its 60 s), and the outcome, unrecorded again, leaves it to its lease
    assert not worker.is_alive() and done == ["ran", "ran"]
    assert _job(db_sessionmaker, second).status == "running"
    assert _job(db_sessionmaker, first).status == "queued"

"""The service on PostgreSQL: SKIP LOCKED claims, several worker processes, kill -9, migrations."""

from __future__ import annotations

import subprocess
import sys
from collections import Counter

import pytest
import sqlalchemy as sa

from app import jobs
from app.db import current_revision, dispose_engines, get_engine, get_sessionmaker, head_revision
from app.models import Job

pytestmark = pytest.mark.postgres


def test_claim_skips_rows_locked_by_another_claimer(pg_settings):
    sm = get_sessionmaker(pg_settings)
    with sm() as db, db.begin():
        first = jobs.enqueue(db, "analyze_trial").id
        second = jobs.enqueue(db, "analyze_trial").id
    with get_engine(pg_settings).connect() as other:
        # Another worker is in the middle of claiming the first job.
        other.execute(sa.text("SELECT id FROM jobs WHERE id = :i FOR UPDATE"), {"i": first})
        claimed = jobs.claim_next(sm, worker_name="w", lease_s=5.0)  # must not block
        assert claimed is not None and claimed.id == second
        other.rollback()
    assert jobs.claim_next(sm, worker_name="w", lease_s=5.0).id == first


def test_timestamps_are_stored_with_time_zone(pg_settings):
    with get_engine(pg_settings).connect() as conn:
        kind = conn.execute(
            sa.text(
                "SELECT data_type FROM information_schema.columns "
                "WHERE table_name = 'jobs' AND column_name = 'created_at'"
            )
        ).scalar()
    assert kind == "timestamp with time zone"


def test_concurrent_start_ups_migrate_once(tmp_path, pg_empty_url):
    code = (
        "from app.settings import Settings; from app.db import migrate; "
        f"migrate(Settings(data_dir={str(tmp_path)!r}, database_url={pg_empty_url!r}))"
    )
    procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(3)]
    assert [p.wait(timeout=60) for p in procs] == [0, 0, 0]
    from app.settings import Settings

    assert current_revision(Settings(data_dir=tmp_path, database_url=pg_empty_url)) == (
        head_revision()
    )
    dispose_engines()


def test_several_worker_processes_run_each_job_exactly_once(pg_settings, worker_script, wait_for):
    n_jobs, n_workers = 24, 3
    sm = get_sessionmaker(pg_settings)
    with sm() as db, db.begin():
        ids = [jobs.enqueue(db, "analyze_trial").id for _ in range(n_jobs)]
    args = [
        sys.executable,
        str(worker_script),
        str(pg_settings.data_dir),
        pg_settings.database_url,
        "30",  # lease (s): long, so that a worker starved of CPU is not presumed dead here
        "0",  # drain the queue, then exit
    ]
    procs = [subprocess.Popen(args) for _ in range(n_workers)]
    try:
        # Hold every worker on its first job until all of them hold one, so that they
        # really race for the rest of the queue.

        def all_running() -> bool:
            with sm() as db:
                owners = db.scalars(sa.select(Job.lease_owner).where(Job.status == "running")).all()
            return len({o.rsplit(":", 1)[0] for o in owners}) == n_workers

        wait_for(all_running, timeout_s=90, what="every worker to hold a job")
        (pg_settings.data_dir / "gate").touch()
        assert [p.wait(timeout=90) for p in procs] == [0] * n_workers
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    lines = [
        line.split() for line in (pg_settings.data_dir / "executions.log").read_text().splitlines()
    ]
    starts = Counter(int(job) for job, _, what in lines if what == "start")
    assert starts == Counter(ids)  # every job started exactly once
    assert len({pid for _, pid, _ in lines}) == n_workers
    with sm() as db:
        statuses = Counter(db.scalars(sa.select(Job.status)).all())
    assert statuses == {"succeeded": n_jobs}


def test_kill9_of_a_worker_mid_job_postgres(pg_settings, worker_script, kill9_scenario):
    kill9_scenario(pg_settings, worker_script)


def test_report_jobs_are_claimed_before_older_analyses(pg_settings):
    sm = get_sessionmaker(pg_settings)
    with sm() as db, db.begin():
        analysis = jobs.enqueue(db, "analyze_trial").id
        report = jobs.enqueue(db, jobs.REPORT_PDF).id
    with get_engine(pg_settings).connect() as other:
        # Another worker is claiming the report: the next claim takes the analysis.
        other.execute(sa.text("SELECT id FROM jobs WHERE id = :i FOR UPDATE"), {"i": report})
        assert jobs.claim_next(sm, worker_name="w", lease_s=5.0).id == analysis
        other.rollback()
    assert jobs.claim_next(sm, worker_name="w", lease_s=5.0).id == report
    with sm() as db, db.begin():
        later_analysis = jobs.enqueue(db, "analyze_trial").id
        later_report = jobs.enqueue(db, jobs.REPORT_PDF).id
    claimed = [jobs.claim_next(sm, worker_name="w", lease_s=5.0).id for _ in range(2)]
    assert claimed == [later_report, later_analysis]

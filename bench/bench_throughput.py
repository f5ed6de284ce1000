"""Trials per hour of one worker: a recording uploaded and measured end to end, as in service.

For each recording kind (the sessions ``bench/bench_analyze.py --keep DIR``
simulated, or ``--dir`` sessions), a fresh data directory gets a rig with that
session's calibration, a patient and a session; the pair is uploaded
``--trials`` times through the trial use case (``app.services.trials.create_trial``,
which checks the videos by decoding them) and one worker (``run_worker``)
measures the queued trials: analysis with the browser proxies written from
the frames it decodes, ``markers.csv``, overlay, plots, result, then each
trial's PDF report (its own job). Prints per trial the worker's wall time and
this process's CPU time (all threads), of the analysis job and of the report
job, and from them:

- trials per hour for one worker (3600 / wall s per trial) on this machine now;
- trials per hour per core (3600 / CPU s per trial): what N workers on N
  otherwise idle cores can reach at best (with PostgreSQL, workers are
  separate ``bradyscope worker`` processes that share nothing but the
  database and the data directory).

With ``--workers N --postgres URL`` (a PostgreSQL server the bench may create
a database on, e.g. ``postgresql+psycopg://postgres@127.0.0.1:5432/postgres``)
the trials go into a new database there instead, and N ``bradyscope worker``
processes measure them, as a hospital's workers would: it prints the wall time
from their start until every analysis has succeeded, trials per hour with N
workers, and their CPU (the database is dropped afterwards). Run it with N = 1
and N = 2 on the same trials to see what a second worker adds on this machine.

Usage::

    python bench/bench_analyze.py --kind all --no-memory --repeat 1 --keep /tmp/abench
    python bench/bench_throughput.py --sessions /tmp/abench [--trials 3]
    python bench/bench_throughput.py --sessions /tmp/abench --compare-proxy-sizes
    python bench/bench_throughput.py --dir SESSION --trials 4 --workers 2 \\
        --postgres postgresql+psycopg://postgres@127.0.0.1:5432/postgres
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this tree's app and core, not another checkout's


def _cpu_s() -> float:
    me = resource.getrusage(resource.RUSAGE_SELF)
    return me.ru_utime + me.ru_stime


def _timed_handlers() -> dict[str, list[float]]:
    """The worker's handlers wrapped to record the CPU (s, this process) each job took."""
    from app import handlers, jobs

    spent: dict[str, list[float]] = {"analyze_trial": [], jobs.REPORT_PDF: []}
    for kind in spent:
        handler = handlers.HANDLERS[kind]

        def timed(ctx: Any, handler: Any = handler, kind: str = kind) -> None:
            c0 = _cpu_s()
            try:
                handler(ctx)
            finally:
                spent[kind].append(_cpu_s() - c0)

        handlers.HANDLERS[kind] = timed
    return spent


def _upload(settings, actor, session_id: int, left: Path, right: Path) -> None:
    from app.services.trials import create_trial
    from app.storage import Storage
    from app.uploads import ParsedUpload, StagedFile

    storage = Storage.from_settings(settings)
    upload = ParsedUpload(storage, fields={"hand": "right"})
    try:
        for name, path in (("left_video", left), ("right_video", right)):
            incoming = storage.receive("videos", path.suffix, max_bytes=settings.max_upload_bytes)
            upload.files[name] = StagedFile(name, path.name, incoming)
            with open(path, "rb") as fh:
                while chunk := fh.read(1 << 20):
                    incoming.write(chunk)
            incoming.flush()
        from app.db import get_sessionmaker

        with get_sessionmaker(settings)() as db:
            create_trial(db, actor, session_id, upload)
    finally:
        upload.close()


@contextlib.contextmanager
def _postgres_database(server_url: str) -> Iterator[str]:
    """A new, empty database on ``server_url``'s server (dropped afterwards); its URL."""
    import sqlalchemy as sa

    name = f"bradyscope_bench_{uuid.uuid4().hex[:12]}"
    admin = sa.create_engine(server_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(sa.text(f'CREATE DATABASE "{name}"'))
    try:
        yield f"{server_url.rsplit('/', 1)[0]}/{name}"
    finally:
        with admin.connect() as conn:
            conn.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


def _run_worker_processes(settings: Any, n_workers: int, n_trials: int) -> tuple[float, float]:
    """Start ``n_workers`` ``bradyscope worker`` processes on ``settings``' database and
    data directory; wall s until every ``analyze_trial`` job succeeded, and their CPU s."""
    from sqlalchemy import func, select

    from app.db import get_sessionmaker
    from app.models import Job

    env = {
        **os.environ,
        "BRADYSCOPE_DATA_DIR": str(settings.data_dir),
        "BRADYSCOPE_DATABASE_URL": settings.database_url,
        "BRADYSCOPE_WORKER_POLL_S": "0.2",
        "BRADYSCOPE_LOG_LEVEL": "WARNING",
    }
    command = [str(Path(sys.executable).with_name("bradyscope")), "worker"]
    sessions = get_sessionmaker(settings)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    workers = [subprocess.Popen(command, env=env) for _ in range(n_workers)]
    try:
        while True:
            with sessions() as db:
                states = dict(
                    db.execute(
                        select(Job.status, func.count())
                        .where(Job.kind == "analyze_trial")
                        .group_by(Job.status)
                    )
                    .tuples()
                    .all()
                )
            if states.get("failed"):
                raise SystemExit(f"{states['failed']} analysis job(s) failed: {states}")
            if states.get("succeeded", 0) == n_trials:
                break
            if any(w.poll() is not None for w in workers):
                raise SystemExit("a worker process exited before the trials were measured")
            time.sleep(0.1)
        wall = time.perf_counter() - t0
    finally:
        for w in workers:
            w.send_signal(signal.SIGTERM)
        for w in workers:
            w.wait(timeout=120)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    return wall, cpu


def bench(
    session_dir: Path, n_trials: int, n_workers: int = 0, postgres: str | None = None
) -> None:
    with contextlib.ExitStack() as stack:
        database_url = None
        if n_workers:
            if postgres is None:
                raise SystemExit("--workers needs --postgres (a server the bench may use)")
            database_url = stack.enter_context(_postgres_database(postgres))
        _bench(session_dir, n_trials, n_workers, database_url)


def _bench(session_dir: Path, n_trials: int, n_workers: int, database_url: str | None) -> None:
    from app.actors import ROLE_SCOPES, Actor
    from app.db import get_sessionmaker, migrate
    from app.models import Calibration, Patient, RecordingSession, Rig, User
    from app.settings import settings_with
    from app.worker import run_worker

    left = next(iter(sorted(session_dir.glob("left.*"))))
    right = next(iter(sorted(session_dir.glob("right.*"))))
    with tempfile.TemporaryDirectory(prefix="bench-throughput-") as tmp:
        settings = settings_with(data_dir=Path(tmp), database_url=database_url)
        migrate(settings)
        doc = json.loads((session_dir / "rig.json").read_text())
        with get_sessionmaker(settings)() as db:
            user = User(email="bench@example.org", password_hash="!", role="clinician")
            rig = Rig(name="bench-rig")
            patient = Patient(code="BENCH-1")
            db.add_all([user, rig, patient])
            db.flush()
            db.add(
                Calibration(
                    rig_id=rig.id,
                    version=1,
                    valid_from=datetime(2000, 1, 1, tzinfo=UTC),
                    rig_json=doc,
                    rms_px=0.0,
                    quality={"rms_px": 0.0},
                    source="rig_file",
                    status="ready",
                    created_by_user_id=user.id,
                )
            )
            session = RecordingSession(
                patient_id=patient.id, rig_id=rig.id, recorded_at=datetime.now(UTC)
            )
            db.add(session)
            db.commit()
            actor = Actor(
                type="user",
                id=user.id,
                name=user.email,
                scopes=ROLE_SCOPES["clinician"],
                role="clinician",
            )
            session_id = session.id
        c0, t0 = _cpu_s(), time.perf_counter()
        for _ in range(n_trials):
            _upload(settings, actor, session_id, left, right)
        up_wall, up_cpu = (time.perf_counter() - t0) / n_trials, (_cpu_s() - c0) / n_trials
        if n_workers:
            wall, cpu = _run_worker_processes(settings, n_workers, n_trials)
            print(
                f"{session_dir.name}: {n_trials} trials measured by {n_workers} worker"
                f" process(es) on PostgreSQL in {wall:.1f} s ({cpu / n_trials:.1f} s of their"
                f" CPU a trial, reports included): {3600 * n_trials / wall:.0f} trials/hour;"
                f" upload check {up_cpu:.1f} s of CPU a trial, not counted;"
                f" load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
            )
            return
        spent = _timed_handlers()
        c0, t0 = _cpu_s(), time.perf_counter()
        done = run_worker(settings, once=True)
        wall, cpu = (time.perf_counter() - t0) / n_trials, (_cpu_s() - c0) / n_trials
        if done != 2 * n_trials or len(spent["analyze_trial"]) != n_trials:
            raise SystemExit(f"the worker ran {done} jobs, not an analysis and a report each")
    analysis_cpu = sum(spent["analyze_trial"]) / n_trials
    report_cpu = sum(spent["report_pdf"]) / n_trials
    total_wall, total_cpu = up_wall + wall, up_cpu + cpu
    print(
        f"{session_dir.name}: {n_trials} trials; per trial: upload check {up_wall:.1f} s"
        f" (CPU {up_cpu:.1f} s), worker {wall:.1f} s (CPU {cpu:.1f} s: the analysis with its"
        f" proxies, plots and files {analysis_cpu:.1f} s, the PDF report {report_cpu:.1f} s)"
    )
    print(
        f"  one worker: {3600 / total_wall:.0f} trials/hour here now;"
        f" per core: {3600 / total_cpu:.0f} trials/hour (3600 / CPU s per trial);"
        f" load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )


def compare_proxy_sizes(session_dir: Path, repeat: int = 2) -> None:
    """``write_proxy`` of the left video at full size (as before 960-px proxies) and
    reduced, alternating in this process: CPU s, best of ``repeat``, and their ratio."""
    import core.video as video

    source = next(iter(sorted(session_dir.glob("left.*"))))
    best = {"full size": float("inf"), "reduced": float("inf")}
    limit = video.PROXY_MAX_WIDTH_PX
    with tempfile.TemporaryDirectory(prefix="bench-proxy-") as tmp:
        try:
            for _ in range(repeat):
                for name, width in (("full size", 1 << 30), ("reduced", limit)):
                    video.PROXY_MAX_WIDTH_PX = width
                    c0 = _cpu_s()
                    video.write_proxy(source, Path(tmp) / "proxy.mp4")
                    best[name] = min(best[name], _cpu_s() - c0)
        finally:
            video.PROXY_MAX_WIDTH_PX = limit
    size = video.probe_video(source).image_size
    small = video.proxy_size(size)
    print(
        f"  proxy of {source.name} ({size.width}x{size.height}): full size"
        f" {best['full size']:.2f} s CPU, reduced to {small.width}x{small.height}"
        f" {best['reduced']:.2f} s (ratio {best['reduced'] / best['full size']:.2f});"
        f" best of {repeat}, load average {os.getloadavg()[0]:.1f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=Path, help="a folder of simulated sessions (session_*)")
    ap.add_argument("--dir", type=Path, action="append", default=[], help="one session folder")
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument(
        "--workers",
        type=int,
        default=0,
        help="measure with this many `bradyscope worker` processes on PostgreSQL (--postgres)",
    )
    ap.add_argument("--postgres", help="a PostgreSQL server URL the bench may create a database on")
    ap.add_argument(
        "--compare-proxy-sizes",
        action="store_true",
        help="only time write_proxy of each left video at full size and reduced (alternating)",
    )
    args = ap.parse_args()
    dirs = list(args.dir)
    if args.sessions is not None:
        dirs += sorted(d for d in args.sessions.glob("session_*") if (d / "rig.json").is_file())
    if not dirs:
        ap.error("give --sessions or --dir")
    for d in dirs:
        if args.compare_proxy_sizes:
            compare_proxy_sizes(d)
        else:
            bench(d, args.trials, args.workers, args.postgres)


if __name__ == "__main__":
    main()

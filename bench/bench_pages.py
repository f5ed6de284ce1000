"""Time the pages a clinician opens against a running server (median of 20 requests).

What is timed, over HTTP, as a logged-in clinician:

- the trial (result) page ``/trials/{id}``: its first view, then the median of
  ``--repeat`` views;
- the PDF report ``/trials/{id}/download/pdf``: the first request after the
  trial was measured (the worker made the PDF then, ``app.reports.pdf_cache``),
  then the median of ``--repeat``; with ``--trials`` N > 1 the first request of
  each other trial's PDF too;
- the patient page ``/patients/{id}`` (trend plots): first, then median;
- the PDF after a change of what it shows (the clinician's rating, posted as
  the trial page's form does), ``--repeat`` times each: asked for **at once**
  (the worker stopped: the request makes the PDF), and asked for **once the
  worker made it** (a ``bradyscope worker`` process; the bench waits for its
  ``report_pdf`` job, and prints how long after the rating that was: the
  worker polls the queue every ``BRADYSCOPE_WORKER_POLL_S``, 1 s).

Beside each median it prints the server's CPU time per request (read from
``/proc/<pid>/stat`` before and after, so that it does not count the time the
server waited for a core on a loaded machine), the worker's CPU per report it
made, and the load average.

Without ``--url`` it makes its own server: a fresh data directory (temporary,
or ``--data-dir``), the demo's rig and patient with ``--trials`` simulated
recordings measured by the real worker (which makes their PDF reports too),
then ``bradyscope serve --workers-in-process 0`` on a free port and, for the
last part, ``bradyscope worker``. With ``--url`` it times a server you run
(``--email``, ``--password``, ``--trial`` and ``--patient`` needed), without
the rating changes.

Usage::

    python bench/bench_pages.py [--repeat 20] [--trials 1] [--data-dir DIR]
    python bench/bench_pages.py --url http://127.0.0.1:8000 --email demo@example.org \\
        --password ... --trial 1 --patient 1
"""

from __future__ import annotations

import argparse
import os
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu_s(pid: int | None) -> float:
    """User + system CPU seconds of process ``pid`` (NaN when unknown)."""
    if pid is None:
        return float("nan")
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks


def _login(client: httpx.Client, email: str, password: str) -> None:
    form = client.get("/login")
    token = re.search(r'name="csrf_token" value="([^"]+)"', form.text)
    if token is None:
        raise SystemExit("no login form at /login")
    r = client.post(
        "/login", data={"email": email, "password": password, "csrf_token": token.group(1)}
    )
    if r.status_code != 303:
        raise SystemExit(f"login refused ({r.status_code})")


def _time(
    client: httpx.Client, path: str, repeat: int, pid: int | None
) -> tuple[float, float, list[float], float]:
    """(first request s, its server CPU s, the next ``repeat`` requests' times s, server
    CPU s per request)."""
    cpu0 = _cpu_s(pid)
    t0 = time.perf_counter()
    r = client.get(path)
    first = time.perf_counter() - t0
    first_cpu = _cpu_s(pid) - cpu0
    if r.status_code != 200:
        raise SystemExit(f"GET {path}: {r.status_code}")
    times = []
    cpu0 = _cpu_s(pid)
    for _ in range(repeat):
        t0 = time.perf_counter()
        r = client.get(path)
        times.append(time.perf_counter() - t0)
        if r.status_code != 200:
            raise SystemExit(f"GET {path}: {r.status_code}")
    return first, first_cpu, times, (_cpu_s(pid) - cpu0) / max(repeat, 1)


def _prepare(data_dir: Path, n_trials: int) -> tuple[str, str, list[int], int]:
    """A migrated data directory with the demo's first ``n_trials`` measured; (email, password,
    the measured trials' ids, patient id)."""
    from sqlalchemy import select

    from app import demo
    from app.db import get_sessionmaker, migrate
    from app.models import Patient, Trial
    from app.settings import settings_with
    from app.worker import run_worker

    settings = settings_with(data_dir=data_dir)
    migrate(settings)
    t0 = time.perf_counter()
    text = demo.seed_demo(settings, background=False, max_trials=n_trials)
    run_worker(settings, once=True)
    print(f"prepared {n_trials} demo trial(s) in {time.perf_counter() - t0:.1f} s")
    password = re.search(r"password: (\S+)", text)
    assert password is not None
    with get_sessionmaker(settings)() as db:
        trials = db.scalars(
            select(Trial.id).where(Trial.status == "succeeded").order_by(Trial.id)
        ).all()
        patient = db.scalars(select(Patient)).first()
        if not trials or patient is None:
            raise SystemExit("the demo trial was not measured")
        return demo.DEMO_EMAIL, password.group(1), list(trials), patient.id


def _rate(client: httpx.Client, trial_id: int, n: int) -> None:
    """Post the clinician's rating of ``trial_id`` as the trial page's form does (a new
    comment each time, so that every report differs)."""
    page = client.get(f"/trials/{trial_id}")
    token = re.search(r'name="csrf_token" value="([^"]+)"', page.text)
    if page.status_code != 200 or token is None:
        raise SystemExit(f"no rating form on /trials/{trial_id} ({page.status_code})")
    r = client.post(
        f"/trials/{trial_id}/rating",
        data={
            "clinician_rating": str(1 + n % 2),
            "comment": f"bench {n}",
            "csrf_token": token.group(1),
        },
    )
    if r.status_code != 303:
        raise SystemExit(f"rating refused ({r.status_code})")


def _reports_pending(data_dir: Path, trial_id: int) -> bool:
    """Whether a ``report_pdf`` job of ``trial_id`` is queued or running."""
    from sqlalchemy import select

    from app import jobs
    from app.db import get_sessionmaker
    from app.models import Job
    from app.settings import settings_with

    with get_sessionmaker(settings_with(data_dir=data_dir))() as db:
        return (
            db.scalar(
                select(Job.id)
                .where(
                    Job.kind == jobs.REPORT_PDF,
                    Job.trial_id == trial_id,
                    Job.status.in_(("queued", "running")),
                )
                .limit(1)
            )
            is not None
        )


def _get(client: httpx.Client, path: str, pid: int | None) -> tuple[float, float]:
    """(seconds, server CPU seconds) of one GET."""
    cpu0 = _cpu_s(pid)
    t0 = time.perf_counter()
    r = client.get(path)
    took = time.perf_counter() - t0
    if r.status_code != 200:
        raise SystemExit(f"GET {path}: {r.status_code}")
    return took, _cpu_s(pid) - cpu0


def _row(name: str, times: list[float], cpus: list[float], extra: str = "") -> None:
    print(
        f"  {name:34s} median {1000 * statistics.median(times):5.0f} ms"
        f" (min {1000 * min(times):5.0f}, max {1000 * max(times):5.0f}),"
        f" server CPU median {1000 * statistics.median(cpus):5.0f} ms{extra}"
    )


def _after_rating(
    client: httpx.Client, data_dir: Path, trial_id: int, repeat: int, pid: int | None
) -> None:
    """The PDF after each of ``repeat`` rating changes, asked for at once with no worker
    running (the request makes it), then with a worker, once it made it."""
    pdf = f"/trials/{trial_id}/download/pdf"
    times, cpus = [], []
    for n in range(repeat):
        _rate(client, trial_id, n)
        took, cpu = _get(client, pdf, pid)
        times.append(took)
        cpus.append(cpu)
    _row("PDF at once after a rating", times, cpus, " (no worker: made by the request)")

    worker = subprocess.Popen(
        [str(Path(sys.executable).with_name("bradyscope")), "worker", "--data-dir", str(data_dir)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        while _reports_pending(data_dir, trial_id):  # the job the last change queued
            if time.monotonic() > deadline or worker.poll() is not None:
                raise SystemExit("the worker did not run the queued report job")
            time.sleep(0.05)
        times, cpus, ready, worker_cpus = [], [], [], []
        for n in range(repeat, 2 * repeat):
            worker_cpu0 = _cpu_s(worker.pid)
            _rate(client, trial_id, n)
            t0 = time.perf_counter()
            while _reports_pending(data_dir, trial_id):
                if time.perf_counter() - t0 > 120 or worker.poll() is not None:
                    raise SystemExit("the worker did not make the report")
                time.sleep(0.05)
            ready.append(time.perf_counter() - t0)
            worker_cpus.append(_cpu_s(worker.pid) - worker_cpu0)
            took, cpu = _get(client, pdf, pid)
            times.append(took)
            cpus.append(cpu)
        _row(
            "PDF after a rating, worker's copy",
            times,
            cpus,
            f"; ready {statistics.median(ready):.2f} s after the rating (median;"
            f" max {max(ready):.2f} s), worker CPU median"
            f" {1000 * statistics.median(worker_cpus):.0f} ms a report",
        )
    finally:
        worker.terminate()
        worker.wait(timeout=60)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--trials", type=int, default=1, help="demo trials to measure first")
    parser.add_argument("--data-dir", type=Path, default=None)
    parser.add_argument("--url", default=None, help="time this running server instead")
    parser.add_argument("--email")
    parser.add_argument("--password")
    parser.add_argument("--trial", type=int)
    parser.add_argument("--patient", type=int)
    args = parser.parse_args()

    server: subprocess.Popen[bytes] | None = None
    tmp = None
    pid: int | None = None
    data_dir: Path | None = None
    try:
        if args.url:
            url, email, password = args.url, args.email, args.password
            trial_ids, patient_id = [args.trial], args.patient
            if not (email and password and args.trial and patient_id):
                parser.error("--url needs --email, --password, --trial and --patient")
        else:
            if args.data_dir is None:
                tmp = tempfile.TemporaryDirectory(prefix="bench-pages-")
                data_dir = Path(tmp.name)
            else:
                data_dir = args.data_dir
            email, password, trial_ids, patient_id = _prepare(data_dir, args.trials)
            port = _free_port()
            url = f"http://127.0.0.1:{port}"
            server = subprocess.Popen(
                [
                    str(Path(sys.executable).with_name("bradyscope")),
                    "serve",
                    "--data-dir",
                    str(data_dir),
                    "--port",
                    str(port),
                    "--workers-in-process",
                    "0",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            pid = server.pid
            deadline = time.monotonic() + 120
            while True:
                try:
                    if httpx.get(url + "/health", timeout=2).status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                if time.monotonic() > deadline or server.poll() is not None:
                    raise SystemExit("the server did not start")
                time.sleep(0.2)
        with httpx.Client(base_url=url, timeout=120) as client:
            _login(client, email, password)
            trial_id = trial_ids[0]
            rows = [
                ("result page", f"/trials/{trial_id}"),
                ("PDF report", f"/trials/{trial_id}/download/pdf"),
                ("patient page", f"/patients/{patient_id}"),
            ]
            print(
                f"server {url}; load average {os.getloadavg()[0]:.2f}"
                f" ({os.cpu_count()} cores); median of {args.repeat} requests"
            )
            print(
                f"  {'':14s} {'first':>8s} {'(CPU)':>8s} {'median':>8s} {'min':>8s}"
                f" {'server CPU':>11s}"
            )
            for name, path in rows:
                first, first_cpu, times, cpu = _time(client, path, args.repeat, pid)
                print(
                    f"  {name:14s} {1000 * first:6.0f} ms {1000 * first_cpu:5.0f} ms"
                    f" {1000 * statistics.median(times):5.0f} ms"
                    f" {1000 * min(times):5.0f} ms {1000 * cpu:8.0f} ms"
                )
            if len(trial_ids) > 1:
                # The other trials' PDFs, each asked for once: the worker made them after
                # their analysis.
                new = [_get(client, f"/trials/{t}/download/pdf", pid) for t in trial_ids[1:]]
                _row(
                    f"PDF first request ({len(new)} trials)",
                    [n[0] for n in new],
                    [n[1] for n in new],
                    " (made by the worker after the analysis)",
                )
            if data_dir is not None and args.repeat > 0:
                print(f"rating changes (load average {os.getloadavg()[0]:.2f}):")
                _after_rating(client, data_dir, trial_id, args.repeat, pid)
            print(f"load average after: {os.getloadavg()[0]:.2f}")
    finally:
        if server is not None:
            server.terminate()
            server.wait(timeout=30)
        if tmp is not None:
            tmp.cleanup()


if __name__ == "__main__":
    main()

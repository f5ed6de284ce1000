"""Time ``make run`` from a fresh data directory: its first page, then the whole demo measured.

Runs ``make run PORT=<free port>`` in the repository with
``BRADYSCOPE_DATA_DIR`` set to a new empty directory (the venv must exist:
this times the start, not the install), and prints:

- the seconds until ``/login`` first answers 200 (the first page);
- the seconds until each demo recording's analysis job has succeeded, and
  until all of them have (the demo measured);
- the CPU seconds the server process tree used, and the load average.

The server is stopped (SIGTERM) at the end and the data directory removed
unless ``--keep DIR`` names one.

Usage::

    python bench/bench_startup.py [--timeout-s 900] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _tree_cpu_s(pid: int) -> float:
    """User + system CPU seconds of ``pid`` and its live descendants, plus reaped children."""
    ticks = os.sysconf("SC_CLK_TCK")
    total = 0.0
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            children = Path(f"/proc/{p}/task/{p}/children").read_text().split()
        except OSError:
            continue
        total += sum(int(v) for v in fields[11:15]) / ticks  # utime stime cutime cstime
        todo.extend(int(c) for c in children)
    return total


def _jobs(db: Path) -> tuple[int, int, int]:
    """(analysis jobs queued in all, succeeded, failed); zeros while the database is new."""
    if not db.is_file():
        return 0, 0, 0
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5) as con:
            rows = con.execute(
                "SELECT status, COUNT(*) FROM jobs WHERE kind = 'analyze_trial' GROUP BY status"
            ).fetchall()
    except sqlite3.Error:
        return 0, 0, 0
    counts = dict(rows)
    return sum(counts.values()), counts.get("succeeded", 0), counts.get("failed", 0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timeout-s", type=float, default=900.0)
    parser.add_argument("--keep", type=Path, default=None, help="data directory to keep")
    parser.add_argument(
        "--first-page-only", action="store_true", help="stop once the first page answers"
    )
    args = parser.parse_args()

    from app.demo_plan import demo_trials

    n_demo = len(demo_trials())
    if args.keep is not None:
        if args.keep.exists() and any(args.keep.iterdir()):
            raise SystemExit(f"{args.keep} is not empty: give a new directory")
        data_dir = args.keep
        data_dir.mkdir(parents=True, exist_ok=True)
    else:
        data_dir = Path(tempfile.mkdtemp(prefix="bench-startup-"))
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    env = {**os.environ, "BRADYSCOPE_DATA_DIR": str(data_dir)}
    load0 = os.getloadavg()[0]
    t0 = time.monotonic()
    server = subprocess.Popen(
        ["make", "--no-print-directory", "run", f"PORT={port}"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    first_page = None
    done_at: list[float] = []
    try:
        while time.monotonic() - t0 < args.timeout_s:
            if server.poll() is not None:
                raise SystemExit(f"make run ended ({server.returncode})")
            now = time.monotonic() - t0
            if first_page is None:
                try:
                    if httpx.get(url + "/login", timeout=2).status_code == 200:
                        first_page = now
                        print(f"first page (/login) after {first_page:.1f} s", flush=True)
                except httpx.TransportError:
                    pass
            _queued, succeeded, failed = _jobs(data_dir / "bradyscope.sqlite3")
            while len(done_at) < succeeded:
                done_at.append(now)
                print(
                    f"  demo recording {len(done_at)}/{n_demo} measured at {now:.1f} s", flush=True
                )
            if failed:
                raise SystemExit(f"{failed} demo analysis job(s) failed")
            if first_page is not None and (args.first_page_only or succeeded >= n_demo):
                break
            time.sleep(0.25)
        else:
            raise SystemExit(f"not finished after {args.timeout_s:.0f} s")
        cpu = _tree_cpu_s(server.pid)
        if args.first_page_only:
            print(f"make run: first page {first_page:.1f} s; load average {load0:.2f} before")
            return
        print(
            f"make run: first page {first_page:.1f} s, all {n_demo} demo recordings measured"
            f" {done_at[-1]:.1f} s after start; server CPU {cpu:.1f} s;"
            f" load average {load0:.2f} before, {os.getloadavg()[0]:.2f} after"
            f" ({os.cpu_count()} cores)"
        )
        print(
            f"data directory: {sum(f.stat().st_size for f in data_dir.rglob('*') if f.is_file()) / 1e6:.0f} MB"
        )
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=60)
        if args.keep is None:
            shutil.rmtree(data_dir, ignore_errors=True)


if __name__ == "__main__":
    main()

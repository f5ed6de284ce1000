"""`bradyscope worker`: run analysis, calibration and report jobs (INTERFACES.md).

Start as many as the machine has cores, here or on other machines sharing a
PostgreSQL database (``BRADYSCOPE_DATABASE_URL``) and the data directory
(``BRADYSCOPE_DATA_DIR``, e.g. on a shared file system), with the server's
time zone (``BRADYSCOPE_TIMEZONE``: the PDF reports it makes ahead are dated in
it, and a report in another zone is not the one asked for). SIGTERM or Ctrl-C stop
the worker after its current job; a worker killed outright has its job taken
over by another worker once the job's lease expires.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from pathlib import Path
from types import FrameType

from app.settings import Settings, settings_with


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "worker",
        help="run analysis, calibration and report jobs (more workers, or on other machines)",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
    )
    p.add_argument(
        "--data-dir", type=Path, default=None, help="overrides BRADYSCOPE_DATA_DIR (default ./data)"
    )
    p.add_argument("--once", action="store_true", help="run the jobs queued now, then exit")
    p.add_argument("--name", default=None, help="worker name shown in job rows (default host:pid)")
    p.set_defaults(func=run)


def install_stop_signals(stop_event: threading.Event) -> None:
    """First SIGTERM/SIGINT: stop after the current job. Second: stop now."""

    def handler(signum: int, frame: FrameType | None) -> None:
        if stop_event.is_set():
            raise KeyboardInterrupt
        print(
            "bradyscope worker: stopping after the current job (signal again to stop now).",
            file=sys.stderr,
        )
        stop_event.set()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


def run(args: argparse.Namespace) -> int:
    from app.db import migrate
    from app.storage import close_to_others, hold_service_lock
    from app.worker import run_worker

    settings: Settings = settings_with(data_dir=args.data_dir)
    close_to_others(settings.data_dir, umask=True)
    running = hold_service_lock(settings.data_dir)  # noqa: F841 - held until the process ends
    logging.getLogger("app").setLevel(logging.DEBUG if args.verbose else logging.INFO)
    migrate(settings)
    stop_event = threading.Event()
    install_stop_signals(stop_event)
    print(
        f"bradyscope worker: polling the job queue of {settings.display_database}.",
        file=sys.stderr,
    )
    from app.cli.serve import exit_if_threads_linger

    try:
        count = run_worker(
            settings,
            once=args.once,
            stop_event=stop_event,
            worker_name=args.name,
            nice=settings.worker_nice,
        )
    except KeyboardInterrupt:
        # Second signal: stop now. The job's lease expires and another worker resumes it.
        print("bradyscope worker: interrupted.", file=sys.stderr)
        exit_if_threads_linger(130)
        raise
    print(f"bradyscope worker: stopped after {count} job(s).", file=sys.stderr)
    exit_if_threads_linger(0)
    return 0

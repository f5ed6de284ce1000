"""`bradyscope serve`: the web application plus an embedded worker (INTERFACES.md).

Start-up order: bring the database to the newest migration (once, under the
start-up lock), optionally seed the demo's rows (``--demo``), then serve HTTP
with uvicorn until SIGINT/SIGTERM; once it answers, start the embedded worker
thread(s) and the demo's simulated recordings (so that the first page does
not wait for the pipeline's imports and the simulation). Heavier
sites run ``--workers-in-process 0`` here and separate ``bradyscope worker``
processes.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from collections.abc import Mapping
from pathlib import Path
from types import FrameType
from typing import Any

from app.settings import Settings, settings_with

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "serve",
        help="run the web application and an embedded job worker",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
    )
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (default 8000)")
    p.add_argument(
        "--data-dir", type=Path, default=None, help="overrides BRADYSCOPE_DATA_DIR (default ./data)"
    )
    p.add_argument(
        "--demo",
        action="store_true",
        help="create a demo clinician, patient, sessions and rig (credentials are printed)",
    )
    p.add_argument(
        "--workers-in-process",
        type=int,
        default=1,
        metavar="N",
        help="job worker threads inside this process (default 1; 0 = use 'bradyscope worker')",
    )
    p.set_defaults(func=run)


def format_demo_info(info: Any) -> str:
    """What ``seed_demo`` returned, as lines for the terminal."""
    if info is None:
        return "demo data ready."
    if isinstance(info, Mapping):
        return "\n".join(f"  {key}: {value}" for key, value in info.items())
    if hasattr(info, "__dataclass_fields__"):
        return "\n".join(f"  {name}: {getattr(info, name)}" for name in info.__dataclass_fields__)
    return str(info)


def start_embedded_workers(
    settings: Settings, count: int, stop_event: threading.Event
) -> list[threading.Thread]:
    """Start ``count`` worker threads that run until ``stop_event`` is set."""
    from app.job_context import default_worker_name
    from app.worker import run_worker

    threads = []
    for i in range(count):
        thread = threading.Thread(
            target=run_worker,
            args=(settings,),
            kwargs={
                "stop_event": stop_event,
                "worker_name": f"{default_worker_name()}:w{i}",
                "nice": settings.worker_nice,
            },
            name=f"bradyscope-worker-{i}",
            daemon=True,
        )
        thread.start()
        threads.append(thread)
    return threads


class PathWithoutQuery(logging.Filter):
    """Drop the query string from uvicorn's access log lines.

    A query can hold a patient code (``/patients?q=``) or a clinician's words
    (``?reason=``); the log is kept outside the audit trail and outlives an
    erasure, so it keeps the path only.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args
        if isinstance(args, tuple) and len(args) >= 3 and isinstance(args[2], str):
            record.args = (*args[:2], args[2].split("?", 1)[0], *args[3:])
        return True


def uvicorn_config(app: Any, *, host: str, port: int, verbose: bool = False) -> Any:
    """uvicorn's settings for the app: no proxy headers of its own, no queries logged.

    uvicorn would believe ``X-Forwarded-For`` from any loopback client
    (``proxy_headers`` with its default ``FORWARDED_ALLOW_IPS``); the app honours
    them itself, only from ``BRADYSCOPE_TRUSTED_PROXIES`` (``app.main.create_app``).
    """
    import uvicorn

    config = uvicorn.Config(
        app,
        host=host,
        port=port,
        log_level="debug" if verbose else "info",
        proxy_headers=False,
        forwarded_allow_ips="",
        server_header=False,
        # a stopping server waits this long (s) for requests still running, then ends
        timeout_graceful_shutdown=30,
    )
    access = logging.getLogger("uvicorn.access")  # configured by uvicorn.Config
    if not any(isinstance(f, PathWithoutQuery) for f in access.filters):
        access.addFilter(PathWithoutQuery())
    return config


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from app.db import migrate
    from app.errors import InvalidRequestError
    from app.storage import close_to_others, hold_service_lock

    if args.workers_in_process < 0:
        raise InvalidRequestError("--workers-in-process must be 0 or more.")
    settings = settings_with(data_dir=args.data_dir)
    close_to_others(settings.data_dir, umask=True)
    running = hold_service_lock(settings.data_dir)  # noqa: F841 - held until the process ends
    logging.getLogger("app").setLevel(logging.DEBUG if args.verbose else logging.INFO)
    migrate(settings)

    serving = threading.Event()  # set once the server answers
    if args.demo:
        from app.demo import seed_demo

        # the address a browser on this machine opens (0.0.0.0 listens on every address)
        shown = "127.0.0.1" if args.host in ("0.0.0.0", "::", "") else args.host
        shown = f"[{shown}]" if ":" in shown else shown
        info = seed_demo(settings, start=serving, url=f"http://{shown}:{args.port}/")
        print("bradyscope demo:\n" + format_demo_info(info), flush=True)

    from app.main import create_app

    app = create_app(settings)
    stop_event = threading.Event()
    threads: list[threading.Thread] = []
    print(
        f"bradyscope serve: http://{args.host}:{args.port}/  (data: {settings.data_dir}, "
        f"database: {settings.display_database}, {args.workers_in_process} embedded worker(s))",
        file=sys.stderr,
        flush=True,
    )
    config = uvicorn_config(app, host=args.host, port=args.port, verbose=args.verbose)
    server = uvicorn.Server(config)

    def after_start() -> None:
        while not server.started:
            if stop_event.wait(0.05):
                return
        from app.passwords import dummy_hash

        dummy_hash()  # so that the first refused login takes as long as any other
        threads.extend(start_embedded_workers(settings, args.workers_in_process, stop_event))
        serving.set()
        from app.reports.rendering import warm_up_pdf

        warm_up_pdf()  # so that the first PDF report does not also load WeasyPrint and its fonts

    threading.Thread(target=after_start, name="bradyscope-start", daemon=True).start()

    # uvicorn handles SIGINT/SIGTERM itself, then re-raises the signal once it has shut
    # down; these handlers receive it so that the embedded workers stop cleanly too.
    def stop_workers(signum: int, frame: FrameType | None) -> None:
        stop_event.set()

    signal.signal(signal.SIGTERM, stop_workers)
    signal.signal(signal.SIGINT, stop_workers)
    try:
        server.run()
    finally:
        stop_event.set()
        for thread in list(threads):
            thread.join(timeout=10)
    exit_if_threads_linger(0)
    return 0


def exit_if_threads_linger(status: int) -> None:
    """Leave at once if background threads still run (a long job, the demo's simulation).

    Letting the interpreter finalise under a thread that is inside OpenCV's C++
    code aborts the process ("terminate called without an active exception").
    Their work is not lost: a job's lease expires and a worker takes it over;
    the demo resumes its missing recordings at the next start.
    """
    lingering = [t.name for t in threading.enumerate() if t is not threading.main_thread()]
    if not lingering:
        return
    from app.db import dispose_engines

    log.info("exiting while background threads still run: %s", ", ".join(lingering))
    dispose_engines()
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)

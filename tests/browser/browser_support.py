"""Helpers of the browser tests (imported by conftest.py and the test modules).

Debian's Chromium (never a downloaded browser), the served app's data directory
and the commands run on it.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
EMAIL = "browser.clinician@example.org"
PASSWORD = "browser-test-password-1"


@dataclass(frozen=True)
class Served:
    url: str
    data_dir: Path
    log: Path
    email: str = EMAIL
    password: str = PASSWORD


@dataclass(frozen=True)
class Recording:
    left: Path
    right: Path
    rig: Path
    truth: dict


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def bradyscope_command() -> list[str]:
    exe = shutil.which("bradyscope", path=str(Path(sys.executable).parent))
    return [exe] if exe else [sys.executable, "-m", "app.cli"]


def served_env(data_dir: Path) -> dict[str, str]:
    """The environment of ``bradyscope`` commands on the served data directory."""
    # A private SQLite database in the temporary data directory, whatever the caller's setup.
    env = {k: v for k, v in os.environ.items() if k != "BRADYSCOPE_DATABASE_URL"}
    return env | {
        "BRADYSCOPE_DATA_DIR": str(data_dir),
        "BRADYSCOPE_PASSWORD": PASSWORD,
        "BRADYSCOPE_WORKER_POLL_S": "0.2",
    }


def create_api_key(served: Served, name: str) -> str:
    """A new API key (all scopes) made with ``bradyscope admin create-api-key``."""
    made = subprocess.run(
        [*bradyscope_command(), "admin", "create-api-key", name],
        env=served_env(served.data_dir),
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return next(line for line in made.stdout.splitlines() if line.startswith("bsk_"))


def launch_chromium(playwright: object, *extra_args: str) -> object:
    """Debian's Chromium with the tests' arguments and ``extra_args``."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=[*CHROMIUM_ARGS, *extra_args])

"""Helpers of the browser tests (imported by conftest.py and the test modules).

Debian's Chromium (never a downloaded browser), the served app's data directory
and the commands run on it.
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

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


def log_in(page: Any, served: Served) -> str:
    """Log ``page`` in as the served demo clinician; the CSRF token of the patient list."""
    page.fill("#email", served.email)
    page.fill("#password", served.password)
    page.keyboard.press("Enter")
    page.wait_for_url(re.compile(r"/patients$"))
    return str(page.locator("input[name=csrf_token]").first.get_attribute("value"))


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


class AnswerCuttingProxy:
    """A TCP proxy in front of the served app that can lose the answer to an upload.

    Everything is relayed both ways, except that once :attr:`cut_after` is set, a
    connection whose request line starts with it (``b"POST /sessions/1/trials"``) has
    its request relayed in full to the server and its answer dropped: the client's
    connection is closed as the answer begins. The server has then done the work; the
    browser has sent every byte and sees only a lost connection. :attr:`cut` counts
    the answers dropped.
    """

    def __init__(self, target_url: str) -> None:
        host, port = target_url.removeprefix("http://").split(":")
        self._target = (host, int(port))
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self._listener.getsockname()[1]}"
        self.cut_after: bytes | None = None
        self.cut = 0
        self._stop = threading.Event()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        server = socket.create_connection(self._target)
        doomed = threading.Event()

        def upstream() -> None:  # browser -> app
            try:
                while chunk := client.recv(65536):
                    if self.cut_after is not None and chunk.startswith(self.cut_after):
                        doomed.set()
                    server.sendall(chunk)
            except OSError:
                pass
            finally:
                server.close()

        threading.Thread(target=upstream, daemon=True).start()
        try:
            while chunk := server.recv(65536):
                if doomed.is_set():
                    self.cut += 1
                    # The answer is lost: reset the browser's connection (shutdown also
                    # wakes the relaying thread blocked on it, so the socket really closes).
                    client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                    break
                client.sendall(chunk)
        except OSError:
            pass
        finally:
            try:
                client.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            client.close()

    def close(self) -> None:
        self._stop.set()
        self._listener.close()

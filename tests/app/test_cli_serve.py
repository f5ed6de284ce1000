"""`bradyscope serve`: migrates a fresh data directory, serves HTTP, stops on SIGTERM."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import urllib.request

import pytest

from app.db import current_revision, dispose_engines, head_revision
from app.settings import Settings


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _health(port: int) -> int | None:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2) as response:
            return response.status
    except OSError:
        return None


@pytest.mark.slow
def test_serve_on_a_fresh_data_dir(tmp_path, wait_for):
    data_dir = tmp_path / "fresh"
    port = _free_port()
    env = {**os.environ, "BRADYSCOPE_DATA_DIR": str(data_dir)}
    env.pop("BRADYSCOPE_DATABASE_URL", None)
    command = [
        os.path.join(os.path.dirname(sys.executable), "bradyscope"),
        "serve",
        "--port",
        str(port),
    ]
    proc = subprocess.Popen(command, env=env, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(
            lambda: _health(port) == 200 or proc.poll() is not None,
            timeout_s=120,
            what="the server to answer /health",
        )
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        assert current_revision(Settings(data_dir=data_dir)) == head_revision()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        dispose_engines()
    assert proc.returncode == 0, err
    assert f"http://127.0.0.1:{port}/" in err and "1 embedded worker(s)" in err


def test_negative_worker_count_is_refused(tmp_path, capsys, monkeypatch):
    from app.cli import main

    monkeypatch.setenv("BRADYSCOPE_DATA_DIR", str(tmp_path))
    assert main(["serve", "--workers-in-process", "-1"]) == 2
    assert "--workers-in-process" in capsys.readouterr().err


def test_demo_info_is_printed_readably():
    from app.cli.serve import format_demo_info

    text = format_demo_info({"email": "demo@bradyscope.local", "password": "demo-pass"})
    assert text.splitlines() == ["  email: demo@bradyscope.local", "  password: demo-pass"]

"""Fixtures for the browser tests: a real ``bradyscope serve`` and Debian's Chromium.

``served`` starts ``bradyscope serve`` (web app + embedded worker) on a free
port with a fresh data directory and a clinician account made with
``bradyscope admin create-user``. ``browser`` launches ``/usr/bin/chromium``
through Playwright (never a downloaded browser). ``recording`` is a short
simulated stereo recording (640 x 512 px, 100 fps) with its true rig file.

Screenshots go to ``$BRADYSCOPE_SCREENSHOT_DIR`` if set, else to a pytest
temporary directory (printed at the end of the run).
"""

from __future__ import annotations

import os
import subprocess
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from browser_support import (
    CHROMIUM,
    EMAIL,
    Recording,
    Served,
    bradyscope_command,
    free_port,
    launch_chromium,
    served_env,
)


@pytest.fixture(scope="session")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Recording:
    from core.camera import ImageSize
    from core.simulation.kinematics import TappingScenario
    from core.simulation.session import ImagingScenario, simulate_session

    out = tmp_path_factory.mktemp("recording")
    sim = simulate_session(
        out,
        seed=7,
        tapping=TappingScenario(
            duration_s=4.0,
            amplitude_mm=45.0,
            frequency_hz=3.0,
            decrement_mm_per_tap=-0.6,
            hesitations=(6,),
        ),
        imaging=ImagingScenario(image_size=ImageSize(640, 512)),
    )
    return Recording(sim.left_video, sim.right_video, sim.rig_path, sim.truth)


@pytest.fixture(scope="session")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    data_dir = tmp_path_factory.mktemp("served-data")
    env = served_env(data_dir)
    subprocess.run(
        [
            *bradyscope_command(),
            "admin",
            "create-user",
            EMAIL,
            "--role",
            "clinician",
            "--name",
            "Dr. Browser",
        ],
        env=env,
        check=True,
        capture_output=True,
        timeout=120,
    )
    port = free_port()
    log = data_dir / "serve.log"
    with open(log, "wb") as fh:
        proc = subprocess.Popen(
            [*bradyscope_command(), "serve", "--host", "127.0.0.1", "--port", str(port)],
            env=env,
            stdout=fh,
            stderr=subprocess.STDOUT,
        )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180  # s: a loaded 2-core machine starts slowly
        while True:
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"bradyscope serve did not start:\n{log.read_text()[-3000:]}")
            time.sleep(0.2)  # polling for start-up, not timing a measurement
        yield Served(url, data_dir, log)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture(scope="session")
def playwright() -> Iterator[object]:
    """One Playwright driver per test process (its sync API runs once per thread)."""
    if not Path(CHROMIUM).is_file():
        if os.environ.get("CI"):
            pytest.fail(f"{CHROMIUM} is missing in CI; install Debian's chromium package")
        pytest.skip(f"{CHROMIUM} is not installed (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        yield pw


@pytest.fixture(scope="session")
def browser(playwright: object) -> Iterator[object]:
    b = launch_chromium(playwright)
    try:
        yield b
    finally:
        b.close()


@pytest.fixture(scope="session")
def screenshot_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    given = os.environ.get("BRADYSCOPE_SCREENSHOT_DIR")
    path = Path(given) if given else tmp_path_factory.mktemp("screenshots")
    path.mkdir(parents=True, exist_ok=True)
    return path

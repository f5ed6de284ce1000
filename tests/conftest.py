"""Fixtures shared by every test folder.

- ``shared_data_dir``: the outside data next to the repository (``../shared/data``).
- ``simulated_session``: a factory that simulates a stereo recording once per
  test run and scenario (shared across xdist workers through a file lock), so
  that many tests can measure the same recording without re-rendering it.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import pickle
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data_dir() -> Path:
    """``../shared/data``; CI always has it, so its absence fails there and skips elsewhere."""
    if not SHARED_DATA.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"the shared test data is missing at {SHARED_DATA}")
        pytest.skip(f"the shared test data is not next to this checkout ({SHARED_DATA})")
    return SHARED_DATA


@pytest.fixture(scope="session")
def simulated_session(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Any]:
    """Factory: ``simulated_session(seed=1, tapping=TappingScenario(...), imaging=...)``.

    Returns the simulator's ``SimulatedSession``; identical arguments give the
    same (cached) files within one test run.
    """
    from core.simulation.session import simulate_session

    # With xdist every worker has its own basetemp below one shared run folder.
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent
    cache = root / "simulated-sessions"
    cache.mkdir(parents=True, exist_ok=True)

    def make(*, seed: int = 1, **kwargs: Any) -> Any:
        key = hashlib.sha256(repr((seed, sorted(kwargs.items()))).encode()).hexdigest()[:16]
        out = cache / key
        with open(cache / f"{key}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                done = out / "session.pickle"
                if done.exists():
                    return pickle.loads(done.read_bytes())
                session = simulate_session(out, seed=seed, **kwargs)
                done.write_bytes(pickle.dumps(session))
                return session
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)

    return make

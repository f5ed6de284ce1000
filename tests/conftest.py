"""Fixtures shared by every test folder.

- ``shared_data_dir``: the outside data next to the repository (``../shared/data``).
- ``run_once``: a factory that computes an expensive value once per test run
  (shared across xdist workers through a file lock and a pickle).
- ``simulated_session``: a factory that simulates a stereo recording once per
  test run and scenario (``run_once``), so that many tests can measure the
  same recording without re-rendering it.
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
def run_once(
    tmp_path_factory: pytest.TempPathFactory,
) -> Callable[[str, Callable[[Path], Any]], Any]:
    """Factory: ``run_once(key, make)`` returns ``make(folder)``, computed once per test run.

    The first caller (in whichever xdist worker) runs ``make`` in a folder of its
    own under the run's temporary directory and pickles the result; every later
    caller with the same key, in any worker, waits for it (a file lock) and reads
    the pickle. For expensive inputs shared by several tests: the 10-s simulated
    acceptance recordings and their analyses.
    """
    # With xdist every worker has its own basetemp below one shared run folder.
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent
    cache = root / "run-once"
    cache.mkdir(parents=True, exist_ok=True)
    loaded: dict[str, Any] = {}

    def get(key: str, make: Callable[[Path], Any]) -> Any:
        if key in loaded:
            return loaded[key]
        name = hashlib.sha256(key.encode()).hexdigest()[:16]
        out = cache / name
        with open(cache / f"{name}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                done = cache / f"{name}.pickle"
                if done.exists():
                    value = pickle.loads(done.read_bytes())
                else:
                    out.mkdir(exist_ok=True)
                    try:
                        value = make(out)
                    except Exception as exc:  # kept, so that later callers fail at once
                        value = _Failed(exc)
                    done.write_bytes(pickle.dumps(value))
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)
        loaded[key] = value
        if isinstance(value, _Failed):
            raise RuntimeError(f"run_once({key!r}) failed earlier in this run") from value.exc
        return value

    return get


class _Failed:
    """A ``run_once`` computation that raised: the exception, for the later callers."""

    def __init__(self, exc: Exception) -> None:
        self.exc = exc


@pytest.fixture(scope="session")
def simulated_session(run_once: Callable[..., Any]) -> Callable[..., Any]:
    """Factory: ``simulated_session(seed=1, tapping=TappingScenario(...), imaging=...)``.

    Returns the simulator's ``SimulatedSession``; identical arguments give the
    same (cached) files within one test run, across xdist workers.
    """
    from core.simulation.session import simulate_session

    def make(*, seed: int = 1, **kwargs: Any) -> Any:
        key = repr((seed, sorted(kwargs.items())))
        return run_once(key, lambda out: simulate_session(out, seed=seed, **kwargs))

    return make

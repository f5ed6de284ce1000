"""The marker detector's answers in one analysis, replayed in a later analysis of the same
videos (imported by tests/core and bench/bench_analyze.py).

``core.pipeline`` searches each video in its own thread (``detect-0``, ``detect-1``), in
frame order, so the answers are kept per thread. A replayed call must ask for the same
search points and radius as the recorded one: an analysis that searched elsewhere (a rig-
or setting-dependent search) fails instead of being given another frame's answers.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np


class RecordedDetector:
    """``record`` as the detector of a first analysis, then ``replay`` in the next ones
    (``rewind`` before each)."""

    def __init__(self) -> None:
        from core.markers import _default_detector

        self._real = _default_detector(None)
        self._calls: dict[str, list[tuple[Any, Any, Any]]] = {}
        self._done: dict[str, int] = {}

    def record(self, image: Any, pts: Any, radius: Any) -> Any:
        out = self._real(image, pts, radius)
        stored = None if pts is None else np.array(pts, copy=True)
        self._calls.setdefault(threading.current_thread().name, []).append((stored, radius, out))
        return out

    def replay(self, image: Any, pts: Any, radius: Any) -> Any:
        name = threading.current_thread().name
        k = self._done.get(name, 0)
        self._done[name] = k + 1
        calls = self._calls[name]
        assert k < len(calls), f"{name}: the analysis searched more frames than recorded"
        pts0, radius0, out = calls[k]
        same = (pts0 is None and pts is None) or (
            pts0 is not None and pts is not None and np.array_equal(pts0, pts)
        )
        assert same and radius0 == radius, f"{name}: frame {k} searched elsewhere"
        return out

    def rewind(self) -> None:
        self._done.clear()

    def all_replayed(self) -> bool:
        return all(self._done.get(n, 0) == len(c) for n, c in self._calls.items())

"""A progress bar on stderr for the long commands, silent when stderr is not a terminal."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from core.progress import ProgressCallback


@contextmanager
def progress_bar(*, enabled: bool | None = None) -> Iterator[ProgressCallback | None]:
    """Yield a core progress callback drawing one tqdm bar per stage, or None when quiet."""
    if enabled is None:
        enabled = sys.stderr.isatty()
    if not enabled:
        yield None
        return
    from tqdm import tqdm

    state: dict[str, Any] = {"stage": None, "bar": None}

    def callback(stage: str, done: int, total: int) -> None:
        if stage != state["stage"]:
            if state["bar"] is not None:
                state["bar"].close()
            state["bar"] = tqdm(total=total, desc=stage, unit="frame", file=sys.stderr, leave=False)
            state["stage"] = stage
        bar = state["bar"]
        if total and bar.total != total:
            bar.total = total
        bar.n = done
        bar.refresh()

    try:
        yield callback
    finally:
        if state["bar"] is not None:
            state["bar"].close()

"""The progress-callback convention shared by every long-running function in core/.

A long function takes ``progress: ProgressCallback | None = None`` and calls
``progress(stage, done, total)`` now and then: ``stage`` is a short noun such
as ``"detection"``, ``done``/``total`` count the stage's units (usually frames).
core/ never prints; the command line draws a bar and the worker stores the
fraction in the job row.
"""

from __future__ import annotations

from collections.abc import Callable

ProgressCallback = Callable[[str, int, int], None]


def report(progress: ProgressCallback | None, stage: str, done: int, total: int) -> None:
    """Call ``progress`` if one was given."""
    if progress is not None:
        progress(stage, done, total)

"""Which software made a result: the package version and the algorithm version.

``ALGORITHM_VERSION`` names the measurement as a whole (segmentation,
filtering, metric formulas). It changes whenever a change of ``core`` would
change a number of ``result.json`` for the same recording, and only then, so
that two results with the same algorithm version can be compared as they
stand. ``tests/core/test_version.py`` measures a fixed simulated recording and
fails when its numbers move while this constant stays.

The package version comes from the installed package's metadata (pyproject).
"""

from __future__ import annotations

from importlib import metadata

#: Bump when the numbers of ``result.json`` would change for the same recording.
ALGORITHM_VERSION = "2026.4"

PACKAGE_NAME = "bradyscope"


def software_version() -> str:
    """The installed package's version (``"0.1.0"``), or ``"unknown"`` when not installed."""
    try:
        return metadata.version(PACKAGE_NAME)
    except metadata.PackageNotFoundError:
        return "unknown"


def software_document() -> dict[str, str]:
    """The ``software`` object of ``result.json``: ``{"version": ..., "algorithm": ...}``."""
    return {"version": software_version(), "algorithm": ALGORITHM_VERSION}


__all__ = ["ALGORITHM_VERSION", "software_document", "software_version"]

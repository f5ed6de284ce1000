"""The compiled loops of the serial part (``core/_geometry.pyx``), or a clear error if not built."""

from __future__ import annotations

try:
    from core import _geometry
except ImportError as exc:  # pragma: no cover - a source tree that was never installed
    raise ImportError(
        "core._geometry (the compiled loops of core/_geometry.pyx) is not built: install the"
        " project with `pip install -e .` (needs a C compiler), or run"
        " `python setup.py build_ext --inplace`"
    ) from exc

__all__ = ["_geometry"]

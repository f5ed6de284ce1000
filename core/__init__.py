"""bradyscope's measurement pipeline: a library of pure functions and frozen dataclasses.

Only numpy, scipy and OpenCV are used here; the web product lives in ``app/``.
"""

from core.errors import BradyscopeError

__all__ = ["BradyscopeError"]

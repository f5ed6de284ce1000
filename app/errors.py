"""The service's error hierarchy: each class carries the HTTP status it maps to.

Raise these anywhere in ``app/`` with one sentence that tells the user what was
wrong and what to do. The web layer maps them in one exception handler
(``exc.http_status`` → status, ``str(exc)`` → ``{"detail": ...}``); the command
line turns them into one line on stderr and exit status 2.

Domain errors from ``core/`` (:class:`core.errors.BradyscopeError`) are not
subclasses; :func:`http_status_for` gives their status too (bad input → 422).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from core.errors import BradyscopeError


class AppError(Exception):
    """A request or command could not be served; ``str(exc)`` is the user-facing sentence.

    ``audited``: the use case has recorded the refusal in the audit trail itself, so
    that the upload runner (:func:`app.uploads.run_upload`) does not record it again.
    """

    http_status: int = 400

    def __init__(self, message: str = "", *, audited: bool = False) -> None:
        super().__init__(message)
        self.audited = audited


class InvalidRequestError(AppError):
    """The request is well-formed but its content is not acceptable.

    ``issues``: the invalid fields as a validation error lists them (``{"loc": ["body",
    "rig_id"], "msg": ..., "type": ...}``), answered as ``errors`` beside ``detail``;
    ``field`` (in ``where``: ``body`` or ``query``) adds one with this message.
    """

    http_status = 422

    def __init__(
        self,
        message: str = "",
        *,
        field: str | None = None,
        where: str = "body",
        kind: str = "value_error",
        issues: Sequence[dict[str, Any]] = (),
        audited: bool = False,
    ) -> None:
        super().__init__(message, audited=audited)
        self.issues = [*issues]
        if field is not None:
            self.issues.append({"loc": [where, field], "msg": message, "type": kind})


class AuthenticationError(AppError):
    """No valid credentials (missing, wrong, expired or revoked)."""

    http_status = 401


class PermissionDeniedError(AppError):
    """Authenticated, but not allowed to do this (role or API-key scope)."""

    http_status = 403


class NotFoundError(AppError):
    """The resource does not exist (or is deleted, or not visible to the caller)."""

    http_status = 404


class ConflictError(AppError):
    """The request conflicts with the current state (duplicate code, result not ready...)."""

    http_status = 409


class CalibrationMissingError(ConflictError):
    """No ready calibration can be used for a session."""


class PayloadTooLargeError(AppError):
    """An upload exceeds the configured size limit."""

    http_status = 413


class UnsupportedMediaError(AppError):
    """An upload is not a video (or rig file) that bradyscope can read."""

    http_status = 415


class RateLimitedError(AppError):
    """Too many attempts (for example logins); try again later.

    ``retry_after_s`` becomes the ``Retry-After`` header (None: no time can be
    given, e.g. an account locked until an administrator unlocks it).
    """

    http_status = 429

    def __init__(self, message: str, *, retry_after_s: int | None = None) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


class StorageError(AppError):
    """A file could not be stored or read under the data directory."""

    http_status = 500


class ServiceUnavailableError(AppError):
    """The database or another dependency is not reachable right now."""

    http_status = 503


class StorageReadOnlyError(ServiceUnavailableError):
    """The data directory or the database refuses writes (read-only file system)."""


class InsufficientStorageError(AppError):
    """The disk holding the data directory or the database is full (HTTP 507)."""

    http_status = 507


def http_status_for(exc: BaseException) -> int:
    """The HTTP status for an application or domain error (500 for anything else)."""
    if isinstance(exc, AppError):
        return exc.http_status
    if isinstance(exc, BradyscopeError):
        return 422
    return 500


__all__ = [
    "AppError",
    "AuthenticationError",
    "CalibrationMissingError",
    "ConflictError",
    "InsufficientStorageError",
    "InvalidRequestError",
    "NotFoundError",
    "PayloadTooLargeError",
    "PermissionDeniedError",
    "RateLimitedError",
    "ServiceUnavailableError",
    "StorageError",
    "StorageReadOnlyError",
    "UnsupportedMediaError",
    "http_status_for",
]

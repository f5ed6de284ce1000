"""Helpers shared by the page routes: who is logged in, CSRF, rendering, errors.

Pages use the browser session of :mod:`app.auth`. A page without a logged-in
user redirects to ``/login?next=...``. Every form carries the session's CSRF
token (hidden field ``csrf_token``; the upload script sends it as the
``X-CSRF-Token`` header instead). Errors of the service (``AppError``) are
shown as a page in plain words, with the status the API would have used.
"""

from __future__ import annotations

import hmac
from typing import Any
from urllib.parse import quote, urlsplit

from fastapi import Request
from fastapi.responses import HTMLResponse, RedirectResponse
from sqlalchemy.orm import Session

from app.auth import CSRF_HEADER, Actor, get_optional_user
from app.web.templating import templates

NAV = (("patients", "/patients", "Patients"), ("rigs", "/rigs", "Calibration"))


def settings_of(request: Request) -> Any:
    return request.app.state.settings


def open_db(request: Request) -> Session:
    """A new database session from the app's factory (the caller closes it)."""
    db: Session = request.app.state.session_factory()
    return db


def page_user(request: Request, db: Session) -> Actor | None:
    """The logged-in browser user, or None."""
    return get_optional_user(request, db)


def safe_next(target: str | None) -> str:
    """A same-site path to go to after login (never an absolute URL elsewhere)."""
    if not target:
        return "/patients"
    parts = urlsplit(target)
    if (
        parts.scheme
        or parts.netloc
        or not target.startswith("/")
        or target.startswith("//")
        or "\\" in target  # browsers read "/\\evil.example" as "//evil.example"
        or any(ord(c) < 32 for c in target)
    ):
        return "/patients"
    return target


def login_redirect(request: Request) -> RedirectResponse:
    path = request.url.path
    if request.url.query:
        path += "?" + request.url.query
    return RedirectResponse(f"/login?next={quote(path, safe='')}", status_code=303)


def csrf_ok(user: Actor, sent: str | None) -> bool:
    """Whether ``sent`` is the session's CSRF token (constant-time comparison)."""
    return (
        bool(sent)
        and user.csrf_token is not None
        and hmac.compare_digest(str(sent), user.csrf_token)
    )


def csrf_from_header(request: Request) -> str | None:
    return request.headers.get(CSRF_HEADER)


def wants_json(request: Request) -> bool:
    """The upload script asks for JSON answers; plain forms get pages and redirects."""
    return "application/json" in request.headers.get("accept", "")


def render(
    request: Request,
    template: str,
    user: Actor | None,
    *,
    status_code: int = 200,
    active: str = "",
    **context: Any,
) -> HTMLResponse:
    """Render a page with the layout's context (user, CSRF token, navigation)."""
    base = {
        "user": user,
        "csrf_token": user.csrf_token if user is not None else "",
        "nav": NAV,
        "active": active,
        "error": context.pop("error", None),
        "message": context.pop("message", request.query_params.get("msg")),
    }
    base.update(context)
    return templates.TemplateResponse(request, template, base, status_code=status_code)


def error_page(
    request: Request, user: Actor | None, *, status_code: int, message: str
) -> HTMLResponse:
    titles = {
        400: "The request could not be used",
        403: "Not allowed",
        404: "Not found",
        409: "Not ready",
        413: "File too large",
        415: "Unsupported file",
        422: "The input could not be used",
        429: "Too many attempts",
        503: "Temporarily unavailable",
    }
    return render(
        request,
        "error.html",
        user,
        status_code=status_code,
        title=titles.get(status_code, "Something went wrong"),
        detail=message,
    )


def status_of(exc: BaseException) -> int:
    return int(getattr(exc, "http_status", 400))

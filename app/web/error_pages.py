"""The error page of a server's fault (500, 503, 507) for a browser, not raw JSON.

A page's request (not ``/api/``, its ``Accept`` preferring HTML) that fails on the
server's side gets the site's error page: the sentence, the request id to quote to
the administrator, and a way back (the same page again when it was a plain visit,
and the patient list). The API keeps ``{"detail": ...}``.
"""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import HTMLResponse

from app.audit import request_id_var
from app.web.common import render

SERVER_ERROR_TITLES = {
    500: "Something went wrong",
    503: "Temporarily unavailable",
    507: "Not saved",
}

UNEXPECTED = "The server met an unexpected error, so this was not done."
"""A 500's sentence on the page (the request id follows it there)."""


def _quality(accept: str, media_type: str) -> float:
    """The ``q`` that ``accept`` gives ``media_type`` itself (0 when unnamed)."""
    for part in accept.split(","):
        name, *params = (p.strip() for p in part.split(";"))
        if name.lower() == media_type:
            for param in params:
                key, _, value = param.partition("=")
                if key.strip().lower() == "q":
                    try:
                        return float(value)
                    except ValueError:
                        return 0.0
            return 1.0
    return 0.0


def prefers_html(request: Request, *, api_prefix: str) -> bool:
    """A browser's request of a page or a page's form: not the API, and its ``Accept``
    names HTML above JSON (a script asking for JSON, or curl's ``*/*``, gets JSON)."""
    if request.url.path.startswith(api_prefix):
        return False
    accept = request.headers.get("accept", "")
    return _quality(accept, "text/html") > max(0.0, _quality(accept, "application/json"))


def request_id_of(request: Request) -> str:
    """The request's id (set by the security middleware in the scope, and its context)."""
    return str(request.scope.get("state", {}).get("request_id") or request_id_var.get() or "")


def server_error_page(request: Request, status_code: int, message: str) -> HTMLResponse:
    """The error page of a 5xx: ``message``, the request id, and the way back."""
    retry = None
    if request.method in ("GET", "HEAD"):  # the same page again (on this site only)
        retry = "/" + request.url.path.lstrip("/\\")  # no "//host", no backslash
        if request.url.query:
            retry += f"?{request.url.query}"
    return render(
        request,
        "error.html",
        None,
        status_code=status_code,
        title=SERVER_ERROR_TITLES.get(status_code, SERVER_ERROR_TITLES[500]),
        detail=message,
        request_id=request_id_of(request),
        retry_url=retry,
    )

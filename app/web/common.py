"""Helpers shared by the page routes: who is logged in, CSRF, rendering, errors.

Pages use the browser session of :mod:`app.auth`. A page without a logged-in
user redirects to ``/login?next=...``. Every form carries the session's CSRF
token (hidden field ``csrf_token``; the upload script sends it as the
``X-CSRF-Token`` header instead). Errors of the service (``AppError``) are
shown as a page in plain words, with the status the API would have used.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Mapping
from typing import Annotated, Any, NoReturn, TypeVar
from urllib.parse import quote, urlsplit

from fastapi import Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from pydantic import ValidationError
from sqlalchemy.orm import Session

from app.actors import Actor
from app.apikeys import AUDIT_READ
from app.audit import audit_failure
from app.auth import (
    CSRF_HEADER,
    SessionDep,
    csrf_matches,
    get_optional_user,
    record_csrf_refusal,
)
from app.errors import AppError, PermissionDeniedError
from app.settings import Settings
from app.templating import templates
from app.uploads import ParsedUpload, run_upload
from core.errors import BradyscopeError

NAV = (("patients", "/patients", "Patients"), ("rigs", "/rigs", "Calibration"))
ADMIN_NAV = (("audit", "/admin/audit", "Audit trail"),)

T = TypeVar("T")

CSRF_MESSAGE = "The form's security token was missing or out of date; reload the page and retry."


def settings_of(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


def open_db(request: Request) -> Session:
    """A new database session from the app's factory (the caller closes it)."""
    db: Session = request.app.state.session_factory()
    return db


def with_own_db(request: Request, fn: Callable[..., T], *args: Any) -> T:
    """``fn(db, *args)`` with a database session of its own, closed afterwards.

    For work run in the thread pool by ``async`` routes (which have no ``SessionDep``).
    """
    db = open_db(request)
    try:
        return fn(db, *args)
    finally:
        db.close()


def page_user(request: Request, db: Session) -> Actor | None:
    """The logged-in browser user, or None."""
    return get_optional_user(request, db)


class LoginRequired(Exception):
    """No logged-in browser user: the app answers with a redirect to the login page."""


class PageForbidden(Exception):
    """A logged-in user whose role does not open this page (audited): a 403 page."""

    def __init__(self, user: Actor, message: str) -> None:
        super().__init__(message)
        self.user = user


PATIENT_PAGES_SCOPE = "patients:read"
"""What every page of patients, recordings, results and rigs needs (an auditor lacks it)."""


def require_any_page_user(request: Request, db: SessionDep) -> Actor:
    """The logged-in browser user; else :class:`LoginRequired` (see ``app.main``)."""
    user = page_user(request, db)
    if user is None:
        raise LoginRequired
    return user


def require_page_user(request: Request, db: SessionDep) -> Actor:
    """The logged-in user of a clinical page: holding ``patients:read``, else a 403 page
    and an ``access route PATH denied`` event (:class:`PageForbidden`)."""
    user = require_any_page_user(request, db)
    if not user.has_scope(PATIENT_PAGES_SCOPE):
        refuse_page(db, user, request)
    return user


def refuse_page(db: Session, user: Actor, request: Request) -> NoReturn:
    """Audit and refuse a page the user's role does not open."""
    audit_failure(db, user, "access", "route", request.url.path[:64], outcome="denied")
    raise PageForbidden(user, "This account reads the audit trail only, not patients' data.")


def scope_refusal(db: Session, user: Actor, request: Request, scope: str) -> AppError | None:
    """Why ``user`` may not make this request (audited), or None when it holds ``scope``;
    for the routes that read their user themselves (uploads, the job page's polling)."""
    if user.has_scope(scope):
        return None
    audit_failure(db, user, "access", "route", request.url.path[:64], outcome="denied")
    return PermissionDeniedError(f"Your account's role lacks the scope {scope}.")


PageUser = Annotated[Actor, Depends(require_page_user)]
"""A clinical page's user: without a logged-in user it redirects to ``/login?next=...``;
a user whose role does not read patients' data gets a 403 page."""

AnyPageUser = Annotated[Actor, Depends(require_any_page_user)]
"""Any logged-in user (the audit trail's page checks its own scope)."""


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


def csrf_refused(db: Session, user: Actor, sent: str | None, request: Request) -> bool:
    """Whether a page's form came without the session's CSRF token; a refusal is audited
    (``access route PATH denied``) and committed before the page says so."""
    if csrf_matches(user, sent):
        return False
    record_csrf_refusal(db, user, request.url.path)
    return True


class CsrfRefused(PermissionDeniedError):
    """An upload's form without the session's CSRF token (403, audited)."""


def csrf_from_header(request: Request) -> str | None:
    return request.headers.get(CSRF_HEADER)


def wants_json(request: Request) -> bool:
    """The upload script asks for JSON answers; plain forms get pages and redirects."""
    return "application/json" in request.headers.get("accept", "")


#: The notices a redirect may ask a page to show (``?msg=``), as the pages' own redirects
#: word them. Anything else is not shown: a crafted link must not put its own sentence
#: ("Result verified by the neurologist.") in a clinical page's status notice.
NOTICES = re.compile(
    r"(Patient created|Session created|Session updated|Trial hidden|Trial restored"
    r"|Rating saved|Revision \d{1,9} stored|Rig created|Calibration v\d{1,9} saved"
    r"|Visit signed \(signature \d{1,9}\)|You are logged out"
    r"|Single sign-on is not set up here)\."
)


def notice_of(msg: str | None) -> str | None:
    """``msg`` when it is one of :data:`NOTICES`, else None."""
    return msg if msg is not None and NOTICES.fullmatch(msg) else None


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
        "home": "/patients"
        if user is None or user.has_scope(PATIENT_PAGES_SCOPE)
        else "/admin/audit",
        "nav": (NAV if user is None or user.has_scope(PATIENT_PAGES_SCOPE) else ())
        + (ADMIN_NAV if user is not None and user.has_scope(AUDIT_READ) else ()),
        "active": active,
        "clinic_tz": settings_of(request).timezone,
        "error": context.pop("error", None),
        "message": context.pop("message", notice_of(request.query_params.get("msg"))),
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
        507: "Storage full",
    }
    return render(
        request,
        "error.html",
        user,
        status_code=status_code,
        title=titles.get(status_code, "Something went wrong"),
        detail=message,
    )


def not_found_page(request: Request, user: Actor | None, exc: AppError) -> HTMLResponse:
    """The 404 page for a missing resource (the service has audited the miss)."""
    return error_page(request, user, status_code=status_of(exc), message=str(exc))


def status_of(exc: BaseException) -> int:
    return int(getattr(exc, "http_status", 400))


SESSION_LABELS = {
    "rig_id": "Camera rig",
    "recorded_at": "Date and time of the recording",
    "medication_state": "Medication state",
    "dbs_state": "Deep brain stimulation",
    "time_since_levodopa_min": "Time since the last levodopa dose",
    "more_affected_side": "More affected side",
    "dominant_hand": "Dominant hand",
    "notes": "Notes",
}
"""The session form's labels, used in the error messages of the new-session and edit forms."""


PATTERN_WORDS = {
    "code": "must use letters, digits, dots, underscores and dashes only, starting with a"
    " letter or a digit (e.g. PD-0042)",
}
"""What a field's pattern allows, in words (a form showed the regular expression itself)."""


def _bound_words(kind: str, bound: object, *, year: bool) -> str:
    """``greater_than_equal`` 1900 → "must be 1900 or later" (a year) or "... or more"."""
    return {
        "greater_than_equal": f"must be {bound} or {'later' if year else 'more'}",
        "less_than_equal": f"must be {bound} or {'earlier' if year else 'less'}",
        "greater_than": f"must be {'after' if year else 'more than'} {bound}",
        "less_than": f"must be {'before' if year else 'less than'} {bound}",
    }[kind]


#: pydantic's error types in a form's words (the field's label goes before them).
_TYPE_WORDS = {
    "missing": "is required",
    "int_parsing": "must be a whole number",
    "int_type": "must be a whole number",
    "int_from_float": "must be a whole number",
    "float_parsing": "must be a number",
    "float_type": "must be a number",
    "bool_parsing": "must be yes or no",
    "date_parsing": "must be a date such as 2026-03-01",
    "date_from_datetime_parsing": "must be a date such as 2026-03-01",
    "datetime_parsing": "must be a date and time such as 2026-03-01 10:30",
    "datetime_from_date_parsing": "must be a date and time such as 2026-03-01 10:30",
    "datetime_type": "must be a date and time such as 2026-03-01 10:30",
    "string_type": "must be text",
}


def _error_words(err: Mapping[str, Any], field: str) -> str | None:
    """One validation error as what the value must be ("must be 1900 or later"); None when
    pydantic's type has no words here (its own message is used, after the label)."""
    kind, ctx = str(err.get("type", "")), err.get("ctx") or {}
    if kind in ("greater_than_equal", "less_than_equal", "greater_than", "less_than"):
        bound = next(iter(ctx.values()), "?")
        return _bound_words(kind, bound, year=field.endswith("year"))
    if kind == "string_too_short":
        n = int(ctx.get("min_length", 1))
        return "must not be empty" if n <= 1 else f"must have at least {n} characters"
    if kind == "string_too_long":
        n = int(ctx.get("max_length", 0))
        return f"must have at most {n} character{'s' if n != 1 else ''}"
    if kind in ("literal_error", "enum"):
        return f"must be {str(ctx.get('expected', '')).replace(chr(39), '')}"
    if kind == "string_pattern_mismatch":  # not a regular expression: words
        return PATTERN_WORDS.get(field, "contains characters that are not allowed")
    return _TYPE_WORDS.get(kind)


def _the(label: str) -> str:
    """ "Birth year" → "The birth year"; an acronym keeps its capitals ("The DBS state")."""
    if label[:2].isupper():
        return f"The {label}"
    return f"The {label[:1].lower()}{label[1:]}"


def validation_message(exc: ValidationError, labels: Mapping[str, str] | None = None) -> str:
    """The first problems of a form in words, each named by the form's own label: "The birth
    year must be 1900 or later." (not pydantic's "Input should be greater than or equal to
    1900"). Every page form's validation errors come through here."""
    sentences = []
    for err in exc.errors()[:3]:
        field = ".".join(str(p) for p in err.get("loc", ()) if p != "body")
        name = (labels or {}).get(field) or field.replace("_", " ").capitalize()
        words = _error_words(err, field)
        if words is not None:
            sentences.append(f"{_the(name)} {words}." if name else f"The value {words}.")
            continue
        message = str(err.get("msg", "invalid")).removeprefix("Value error, ").rstrip(".")
        sentences.append(f"{name}: {message}." if name else f"{message}.")
    return " ".join(sentences)


async def _record_csrf_refusal(request: Request, actor: Actor) -> None:
    await run_in_threadpool(with_own_db, request, record_csrf_refusal, actor, request.url.path)


async def run_page_upload(
    request: Request,
    user: Actor | None,
    *,
    refusal: AppError | None,
    file_fields: Mapping[str, str],
    text_fields: Iterable[str],
    fail: Callable[[Session, Actor, int, str], Response],
    use_case: Callable[[Session, Actor, ParsedUpload], Response],
    prepare: Callable[[ParsedUpload], None] | None = None,
    rejected: Callable[[Session, Actor], None] | None = None,
) -> Response:
    """A page's upload: log-in, CSRF and target checks, then :func:`app.uploads.run_upload`.

    Parameters
    ----------
    user : Actor or None
        The logged-in user (``None``: log in again, 401 for the upload script).
    refusal : AppError or None
        Why the target cannot take the upload, found before the body is read.
    file_fields, text_fields
        Accepted parts (``csrf_token`` is always accepted).
    fail : callable
        ``fail(db, user, status, message)`` renders an error page (run in the thread pool
        with a database session of its own); the upload script gets JSON instead.
    use_case : callable
        ``use_case(db, user, upload)`` stores the upload and returns the success answer (run
        likewise); an ``AppError`` or a core error becomes ``fail``.
    prepare : callable, optional
        Adjusts the parsed form before the use case (e.g. drops unused empty parts).
    rejected : callable, optional
        ``rejected(db, user)`` audits an upload refused for its content (with a
        database session of its own).
    """

    if user is None:
        if wants_json(request):
            return JSONResponse({"detail": "Please log in again."}, status_code=401)
        return login_redirect(request)
    actor = user

    async def failed(status: int, message: str) -> Response:
        if wants_json(request):
            return JSONResponse({"detail": message}, status_code=status)
        return await run_in_threadpool(with_own_db, request, fail, actor, status, message)

    header_token = csrf_from_header(request)
    if header_token is not None and not csrf_matches(user, header_token):
        await _record_csrf_refusal(request, actor)
        return await failed(403, CSRF_MESSAGE)
    if refusal is not None:
        return await failed(status_of(refusal), str(refusal))

    def accept(upload: ParsedUpload) -> None:
        if header_token is None and not csrf_matches(actor, upload.fields.get("csrf_token")):
            raise CsrfRefused(CSRF_MESSAGE)
        if prepare is not None:
            prepare(upload)

    settings = settings_of(request)
    try:
        return await run_upload(
            request,
            storage=request.app.state.storage,
            max_file_bytes=int(settings.max_upload_bytes),
            file_fields=file_fields,
            text_fields=frozenset(text_fields) | {"csrf_token"},
            use_case=lambda upload: with_own_db(request, use_case, actor, upload),
            accept=accept,
            on_rejected=None
            if rejected is None
            else (lambda exc: with_own_db(request, rejected, actor)),
        )
    except AppError as exc:
        if isinstance(exc, CsrfRefused):
            await _record_csrf_refusal(request, actor)
        return await failed(status_of(exc), str(exc))
    except BradyscopeError as exc:  # a core error while checking the videos
        return await failed(422, str(exc))

"""Login and logout pages.

The login form has its own CSRF protection before any session exists: a
random token in a short-lived cookie that the form must echo (double submit).
"""

from __future__ import annotations

import hmac
import secrets
from typing import Annotated

from fastapi import APIRouter, Form, Query, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response

from app import oidc
from app.actors import Actor
from app.audit import ANONYMOUS, audit_failure
from app.auth import SESSION_COOKIE, SessionDep
from app.chain import load_key
from app.errors import AppError
from app.login import login_from_request, login_sso, logout_from_request, set_session_cookie
from app.web.common import (
    PATIENT_PAGES_SCOPE,
    csrf_refused,
    page_user,
    render,
    safe_next,
    settings_of,
    status_of,
)

router = APIRouter()

LOGIN_CSRF_COOKIE = "bradyscope_login_csrf"


def _login_form(
    request: Request,
    *,
    next_url: str,
    error: str | None = None,
    status_code: int = 200,
    email: str = "",
) -> HTMLResponse:
    token = secrets.token_urlsafe(24)
    response = render(
        request,
        "login.html",
        None,
        status_code=status_code,
        title="Log in",
        login_csrf=token,
        next_url=next_url,
        email=email,
        error=error,
        sso_label=settings_of(request).oidc_display_name
        if oidc.enabled(settings_of(request))
        else None,
        local_login=bool(settings_of(request).local_login),
    )
    response.set_cookie(
        LOGIN_CSRF_COOKIE,
        token,
        max_age=3600,
        path="/login",
        httponly=True,
        samesite="strict",
        secure=settings_of(request).secure_cookies,
    )
    return response


AUDIT_HOME = "/admin/audit"
"""Where a user whose role reads no patients' data (an auditor) lands: the one page of theirs."""


def _landing(user: Actor, next_url: str | None = None) -> str:
    """Where a logged-in user goes: ``next_url`` (checked) or the patient list; an auditor
    to the audit trail, since every clinical page would refuse them (403, audited)."""
    if not user.has_scope(PATIENT_PAGES_SCOPE):
        return AUDIT_HOME
    return safe_next(next_url)


@router.get("/login", response_class=HTMLResponse)
def login_page(request: Request, db: SessionDep, next: str | None = None) -> Response:
    user = page_user(request, db)
    if user is not None:
        return RedirectResponse(_landing(user, next), status_code=303)
    return _login_form(request, next_url=safe_next(next))


@router.post("/login", response_class=HTMLResponse)
def login_submit(
    request: Request,
    db: SessionDep,
    email: Annotated[str, Form(max_length=320)] = "",
    password: Annotated[str, Form(max_length=1024)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
    next: Annotated[str, Form(max_length=2000)] = "/patients",
) -> Response:
    cookie = request.cookies.get(LOGIN_CSRF_COOKIE, "")
    if not cookie or not hmac.compare_digest(cookie, csrf_token):
        return _login_form(
            request,
            next_url=safe_next(next),
            email=email,
            status_code=403,
            error="The login form was out of date; please enter your e-mail and password again.",
        )
    response = RedirectResponse(safe_next(next), status_code=303)
    try:
        result = login_from_request(db, request, response, email=email, password=password)
    except AppError as exc:
        return _login_form(
            request,
            next_url=safe_next(next),
            email=email,
            status_code=status_of(exc),
            error=str(exc),
        )
    response.headers["location"] = _landing(result.actor, next)
    response.delete_cookie(LOGIN_CSRF_COOKIE, path="/login")
    return response


@router.get("/login/oidc")
def oidc_start(request: Request, next: str | None = None) -> Response:
    """Send the browser to the hospital's identity provider (single sign-on)."""
    settings = settings_of(request)
    if not oidc.enabled(settings):
        return RedirectResponse("/login?msg=Single+sign-on+is+not+set+up+here.", status_code=303)
    try:
        begun = oidc.start(
            settings, _instance_key(request), _callback_url(request), safe_next(next)
        )
    except AppError as exc:
        return _login_form(
            request, next_url=safe_next(next), status_code=status_of(exc), error=str(exc)
        )
    response = RedirectResponse(begun.url, status_code=303)
    response.set_cookie(
        oidc.STATE_COOKIE,
        begun.cookie,
        max_age=oidc.STATE_MAX_AGE_S,
        path=oidc.CALLBACK_PATH,
        httponly=True,
        samesite="lax",  # the provider sends the browser back with a top-level GET
        secure=bool(settings.secure_cookies),
    )
    return response


@router.get(oidc.CALLBACK_PATH)
def oidc_callback(
    request: Request,
    db: SessionDep,
    code: Annotated[str, Query(max_length=4096)] = "",
    state: Annotated[str, Query(max_length=512)] = "",
    error: Annotated[str, Query(max_length=200)] = "",
) -> Response:
    """The provider's answer: validate it, open the session, go where the user was heading."""
    settings = settings_of(request)
    try:
        if not oidc.enabled(settings):
            raise oidc.OidcError("Single sign-on is not set up here; log in with your password.")
        if error or not code:
            raise oidc.OidcError(
                f"The identity provider did not log you in ({error or 'no code'}); try again."
            )
        identity = oidc.finish(
            settings,
            _instance_key(request),
            cookie=request.cookies.get(oidc.STATE_COOKIE),
            code=code,
            state=state,
            redirect_uri=_callback_url(request),
        )
        response = RedirectResponse(safe_next(identity.next_url), status_code=303)
        result = login_sso(
            db,
            settings,
            identity,
            ip=request.client.host[:45] if request.client else None,
            user_agent=request.headers.get("user-agent"),
            replace_token=request.cookies.get(SESSION_COOKIE),
        )
    except AppError as exc:
        # Without single sign-on there is nothing to log into: anyone's requests here
        # would only fill the trail.
        if isinstance(exc, oidc.OidcError) and oidc.enabled(settings):
            audit_failure(db, ANONYMOUS, "login", "user", None, outcome="denied")
        failed = _login_form(
            request, next_url="/patients", status_code=status_of(exc), error=str(exc)
        )
        failed.delete_cookie(oidc.STATE_COOKIE, path=oidc.CALLBACK_PATH)
        return failed
    response.headers["location"] = _landing(result.actor, identity.next_url)
    set_session_cookie(response, result.token, settings=settings)
    response.delete_cookie(oidc.STATE_COOKIE, path=oidc.CALLBACK_PATH)
    return response


def _callback_url(request: Request) -> str:
    return str(request.url_for("oidc_callback"))


def _instance_key(request: Request) -> bytes:
    return load_key(settings_of(request).audit_key_path)


@router.post("/logout")
def logout(
    request: Request, db: SessionDep, csrf_token: Annotated[str, Form(max_length=200)] = ""
) -> Response:
    user = page_user(request, db)
    response = RedirectResponse("/login?msg=You+are+logged+out.", status_code=303)
    if user is not None and csrf_refused(db, user, csrf_token, request):
        return RedirectResponse(_landing(user), status_code=303)
    logout_from_request(db, request, response)
    return response


@router.get("/")
def home(request: Request, db: SessionDep) -> Response:
    """The patient list; an auditor's home is the audit trail. Without a login, the patient
    list's own redirect to the login page."""
    user = page_user(request, db)
    return RedirectResponse(_landing(user) if user is not None else "/patients", status_code=303)

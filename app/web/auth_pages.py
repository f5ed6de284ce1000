"""Login and logout pages.

The login form has its own CSRF protection before any session exists: a
random token in a short-lived cookie that the form must echo (double submit).
"""

from __future__ import annotations

import hmac
import secrets
from typing import Annotated

from fastapi import APIRouter, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response

from app.auth import SessionDep, login_from_request, logout_from_request
from app.errors import AppError
from app.web.common import csrf_ok, page_user, render, safe_next, settings_of, status_of

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


@router.get("/login", response_class=HTMLResponse)
def login_page(request: Request, db: SessionDep, next: str | None = None) -> Response:
    if page_user(request, db) is not None:
        return RedirectResponse(safe_next(next), status_code=303)
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
        login_from_request(db, request, response, email=email, password=password)
    except AppError as exc:
        return _login_form(
            request,
            next_url=safe_next(next),
            email=email,
            status_code=status_of(exc),
            error=str(exc),
        )
    response.delete_cookie(LOGIN_CSRF_COOKIE, path="/login")
    return response


@router.post("/logout")
def logout(
    request: Request, db: SessionDep, csrf_token: Annotated[str, Form(max_length=200)] = ""
) -> Response:
    user = page_user(request, db)
    response = RedirectResponse("/login?msg=You+are+logged+out.", status_code=303)
    if user is not None and not csrf_ok(user, csrf_token):
        return RedirectResponse("/patients", status_code=303)
    logout_from_request(db, request, response)
    return response


@router.get("/")
def home() -> Response:
    return RedirectResponse("/patients", status_code=303)

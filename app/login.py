"""Logging in and out: password and single sign-on logins, re-authentication, browser sessions.

- :func:`login_user` checks an e-mail and password and opens a browser
  session; :func:`login_sso` opens one for the person the identity provider
  vouched for (:mod:`app.oidc`); both go through :func:`open_session`, which
  stores only the SHA-256 of the cookie token (:func:`app.auth.session_key`).
- **Login throttling** (:mod:`app.throttle`): growing delays per account and
  per (address, account) pair, counted atomically before the password is
  checked; 429 with ``Retry-After`` while an attempt must wait.
- :func:`reauthenticate` checks a logged-in user's password again (for
  signing), through the same throttle.
- :func:`logout_user` ends a session; ``*_from_request`` wrap both for a
  request and its cookie.

Checking what a request carries (API keys, cookies, CSRF, scopes) is
:mod:`app.auth`.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from datetime import timedelta

from fastapi import Request, Response
from sqlalchemy import select
from sqlalchemy.orm import Session

from app import throttle
from app.actors import ROLE_SCOPES, Actor
from app.audit import ANONYMOUS, audit, audit_failure
from app.auth import SESSION_COOKIE, client_ip, request_settings, session_key
from app.errors import AuthenticationError, PermissionDeniedError, RateLimitedError
from app.models import BrowserSession, User, utcnow
from app.oidc import Identity
from app.passwords import NO_PASSWORD, dummy_hash, hash_password, needs_rehash, verify_password
from app.settings import Settings
from app.throttle import normalise_email


def _check_password(
    db: Session, settings: Settings, *, email: str, password: str, ip: str | None
) -> User:
    """The active user whose password this is (throttled); audits and raises otherwise."""
    try:
        throttle.admit_attempt(db, settings, email, ip)  # commits the counted attempt
    except RateLimitedError:
        audit_failure(db, ANONYMOUS, "login", "user", None, outcome="throttled")
        raise
    user = db.scalar(select(User).where(User.email == normalise_email(email)))
    # Verify against a dummy hash for unknown users and accounts without a local password
    # (single sign-on only): same time, no account enumeration.
    local = user is not None and user.password_hash != NO_PASSWORD
    ok = verify_password(user.password_hash if user and local else dummy_hash(), password)
    if not ok or not local or user is None or not user.is_active:
        audit(db, ANONYMOUS, "login", "user", user.id if user else None, outcome="denied")
        db.commit()
        raise AuthenticationError("The e-mail address or the password is wrong.")
    throttle.record_success(db, settings, email, ip)
    throttle.forget_stale(db, settings)
    return user


def reauthenticate(
    db: Session, settings: Settings, actor: Actor, password: str, *, ip: str | None = None
) -> User:
    """Check the logged-in user's password again (e.g. before signing a report).

    Goes through the login throttle of that account and address, and audits the
    check (``reauthenticate``; ``denied`` on a wrong password). Commits.

    Raises
    ------
    PermissionDeniedError
        ``actor`` is not a browser user (API keys cannot re-authenticate), or the password
        is wrong (403: the login itself stands; a 401 would read as an expired session).
    RateLimitedError
        Too many wrong passwords (429).
    AuthenticationError
        The account was deactivated (401: its session is over).
    """
    if actor.type != "user":
        raise PermissionDeniedError("Only a logged-in person can confirm with a password.")
    user = db.get(User, actor.id)
    if user is None or not user.is_active:
        raise AuthenticationError("This account is no longer active.")
    try:
        throttle.admit_attempt(db, settings, user.email, ip)
    except RateLimitedError:
        audit_failure(db, actor, "reauthenticate", "user", user.id, outcome="throttled")
        raise
    if not verify_password(user.password_hash, password):
        audit(db, actor, "reauthenticate", "user", user.id, outcome="denied")
        db.commit()
        raise PermissionDeniedError(
            "The password is wrong; type the password you log in with to confirm, and retry."
        )
    throttle.record_success(db, settings, user.email, ip)
    audit(db, actor, "reauthenticate", "user", user.id)
    db.commit()
    return user


@dataclass(frozen=True)
class LoginResult:
    """A successful login: the cookie token (give it to the browser only) and the session."""

    token: str
    csrf_token: str
    user: User
    actor: Actor


def login_user(
    db: Session,
    *,
    settings: Settings,
    email: str,
    password: str,
    ip: str | None = None,
    user_agent: str | None = None,
    replace_token: str | None = None,
) -> LoginResult:
    """Check e-mail and password (throttled) and open a browser session; commits.

    Parameters
    ----------
    db : Session
    settings : app.settings.Settings
        For the throttle (``login_*``) and ``session_ttl_s``.
    email, password : str
    ip, user_agent : str, optional
        Recorded with the attempt and the session.
    replace_token : str, optional
        The browser's previous session token: that session is ended (no
        session fixation).

    Raises
    ------
    RateLimitedError
        The account, or this address for this account, must wait (429).
    AuthenticationError
        Wrong e-mail or password, or an inactive account (401).
    """
    if not settings.local_login:
        raise AuthenticationError(
            "Log in through the hospital's single sign-on; passwords are switched off here."
        )
    user = _check_password(db, settings, email=email, password=password, ip=ip)
    return open_session(
        db,
        settings,
        user,
        ip=ip,
        user_agent=user_agent,
        replace_token=replace_token,
        password=password,
    )


def login_sso(
    db: Session,
    settings: Settings,
    identity: Identity,
    *,
    ip: str | None = None,
    user_agent: str | None = None,
    replace_token: str | None = None,
) -> LoginResult:
    """Open a session for the person the identity provider vouched for (``app.oidc``); commits.

    The account is the one bound to the token's subject, else the one with its
    e-mail address (then bound to the subject). Without such an account the
    login is refused, unless ``settings.oidc_create_users``.

    Raises
    ------
    AuthenticationError
        No account, a deactivated one, or one bound to another identity (401, audited).
    """

    def refuse(user_id: int | None, message: str) -> AuthenticationError:
        audit_failure(db, ANONYMOUS, "login", "user", user_id, outcome="denied")
        return AuthenticationError(message)

    user = db.scalar(select(User).where(User.oidc_subject == identity.subject))
    if user is None:
        user = db.scalar(select(User).where(User.email == normalise_email(identity.email)))
        if user is not None and user.oidc_subject not in (None, identity.subject):
            raise refuse(
                user.id,
                f"The account {identity.email} is bound to another identity at the provider;"
                " ask an administrator.",
            )
        if user is None:
            if not settings.oidc_create_users:
                raise refuse(
                    None,
                    f"There is no bradyscope account for {identity.email}; ask an administrator"
                    " to create one.",
                )
            user = User(
                email=normalise_email(identity.email),
                password_hash=NO_PASSWORD,
                role="clinician",
                display_name=identity.name,
            )
            db.add(user)
            db.flush()
            audit(db, None, "create", "user", user.id)
        user.oidc_subject = identity.subject
    if not user.is_active:
        raise refuse(user.id, "This account was deactivated; ask an administrator.")
    return open_session(
        db, settings, user, ip=ip, user_agent=user_agent, replace_token=replace_token
    )


def open_session(
    db: Session,
    settings: Settings,
    user: User,
    *,
    ip: str | None = None,
    user_agent: str | None = None,
    replace_token: str | None = None,
    password: str | None = None,
) -> LoginResult:
    """Open a browser session for ``user`` (authenticated by the caller), audit it; commits.

    ``replace_token``: the browser's previous session, ended (no session fixation).
    ``password``: given after a password login, to re-hash an old-parameter hash.
    """
    if replace_token:
        old = db.get(BrowserSession, session_key(replace_token))
        if old is not None:
            db.delete(old)
    if password is not None and needs_rehash(user.password_hash):
        user.password_hash = hash_password(password)
    token = secrets.token_urlsafe(32)
    csrf_token = secrets.token_urlsafe(32)
    now = utcnow()
    db.add(
        BrowserSession(
            id=session_key(token),
            user_id=user.id,
            csrf_token=csrf_token,
            created_at=now,
            expires_at=now + timedelta(seconds=float(settings.session_ttl_s)),
            last_seen_at=now,
            ip=ip,
            user_agent=(user_agent or "")[:300] or None,
        )
    )
    user.last_login_at = now
    actor = Actor(
        type="user",
        id=user.id,
        name=user.email,
        scopes=ROLE_SCOPES.get(user.role, frozenset()),
        role=user.role,
        csrf_token=csrf_token,
    )
    audit(db, actor, "login", "user", user.id)
    db.commit()
    return LoginResult(token=token, csrf_token=csrf_token, user=user, actor=actor)


def set_session_cookie(response: Response, token: str, *, settings: Settings) -> None:
    """Give the browser its session cookie (HttpOnly, SameSite=Lax, Secure behind HTTPS)."""
    response.set_cookie(
        SESSION_COOKIE,
        token,
        max_age=int(settings.session_ttl_s),
        path="/",
        httponly=True,
        samesite="lax",
        secure=bool(settings.secure_cookies),
    )


def logout_user(db: Session, response: Response, *, token: str | None, settings: Settings) -> None:
    """End the browser session of ``token`` (if any), clear the cookie; commits."""
    if token:
        row = db.get(BrowserSession, session_key(token))
        if row is not None:
            db.delete(row)
            audit(
                db,
                Actor(type="user", id=row.user_id, name=""),
                "logout",
                "user",
                row.user_id,
            )
            db.commit()
    response.delete_cookie(
        SESSION_COOKIE,
        path="/",
        httponly=True,
        samesite="lax",
        secure=bool(settings.secure_cookies),
    )


def login_from_request(
    db: Session, request: Request, response: Response, *, email: str, password: str
) -> LoginResult:
    """:func:`login_user` for a request, setting the session cookie on ``response``."""
    settings = request_settings(request)
    result = login_user(
        db,
        settings=settings,
        email=email,
        password=password,
        ip=client_ip(request),
        user_agent=request.headers.get("user-agent"),
        replace_token=request.cookies.get(SESSION_COOKIE),
    )
    set_session_cookie(response, result.token, settings=settings)
    return result


def logout_from_request(db: Session, request: Request, response: Response) -> None:
    """:func:`logout_user` for a request (its cookie), clearing the cookie on ``response``."""
    logout_user(
        db, response, token=request.cookies.get(SESSION_COOKIE), settings=request_settings(request)
    )

"""Authentication and authorisation: API keys for hospital systems, sessions for browsers.

Two kinds of callers, one :class:`Actor`:

- **API clients** send ``Authorization: Bearer bsk_<prefix>_<secret>``
  (:mod:`app.apikeys`). The key is looked up by its prefix and compared by
  hash; a revoked key is refused (401). Each client holds *scopes*; a route
  names the scope it needs with :func:`require_scope` (403 without it). A key
  with an owner acts with at most its owner's role's scopes, checked at each use.
- **Browsers** log in with e-mail and password (argon2, :mod:`app.passwords`)
  and get a server-side session: the cookie holds a random token, the
  database only its SHA-256 (``BrowserSession.id``). The cookie is HttpOnly,
  SameSite=Lax, and Secure when ``settings.secure_cookies``. Every
  state-changing browser request (POST, PUT, PATCH, DELETE) must carry the
  session's CSRF token, in the ``X-CSRF-Token`` header or a ``csrf_token``
  form field (403 otherwise). Users have every data scope; admins also
  ``admin``.
- A browser session ends after ``settings.session_ttl_s`` (absolute) or after
  ``settings.session_idle_s`` without a request (idle).
- Logging in and out (password, single sign-on, re-authentication for
  signing, with the login throttle) is :mod:`app.login`; this module checks
  the credentials a request carries.

Dependencies (``Annotated`` aliases for route signatures): :data:`SessionDep`,
:data:`CurrentActor`, :data:`CurrentUser`, :data:`OptionalUser`, and
``require_scope("patients:read")``.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Callable, Iterable, Iterator
from datetime import timedelta
from typing import Annotated, Any

from fastapi import Depends, Request
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session

from app.actors import ADMIN_SCOPE, ROLE_SCOPES, Actor
from app.apikeys import DATA_SCOPES, SCOPES, parse_api_key, verify_api_key
from app.audit import audit_failure
from app.errors import AppError, AuthenticationError, PermissionDeniedError
from app.models import ApiClient, BrowserSession, User, utcnow
from app.settings import Settings

SESSION_COOKIE = "bradyscope_session"
CSRF_HEADER = "X-CSRF-Token"
CSRF_FORM_FIELD = "csrf_token"
_SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS", "TRACE"})
_TOUCH_INTERVAL = timedelta(minutes=1)  # last_used/last_seen are updated at most this often


# --------------------------------------------------------------------------- database session


def get_db(request: Request) -> Iterator[Session]:
    """One database session per request (the use case commits; the rest is rolled back)."""
    factory = request.app.state.session_factory
    with factory() as db:
        yield db


SessionDep = Annotated[Session, Depends(get_db)]


# --------------------------------------------------------------------------- helpers


def session_key(token: str) -> str:
    """The stored id of a browser session (``BrowserSession.id``): SHA-256 of its cookie token."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def client_ip(request: Request) -> str | None:
    return request.client.host[:45] if request.client else None


def request_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


# --------------------------------------------------------------------------- API keys


def owned_key_scopes(scopes: Iterable[str], owner_role: str) -> frozenset[str]:
    """What an API key owned by a user of ``owner_role`` may do: its own scopes that the
    role holds too. A key never does more than the person answerable for it could."""
    return frozenset(scopes) & ROLE_SCOPES.get(owner_role, frozenset())


def authenticate_api_key(db: Session, token: str) -> Actor:
    """The API client owning ``token``, with its scopes; a key with an owner has only
    those its owner's role holds too (:func:`owned_key_scopes`), read at each use, so a
    change of the owner's role applies at the key's next request.

    Raises :class:`AuthenticationError` if the key is unknown, revoked, expired,
    or its owner's account was deactivated.
    """
    prefix = parse_api_key(token)
    if prefix is None:
        raise AuthenticationError(
            "The API key is malformed; send 'Authorization: Bearer bsk_...' with the key"
            " printed by 'bradyscope admin create-api-key'."
        )
    client = db.scalar(select(ApiClient).where(ApiClient.key_prefix == prefix))
    if client is None or not verify_api_key(token, client.key_hash):
        raise AuthenticationError("The API key is not valid; ask the administrator for a key.")
    if client.revoked_at is not None:
        raise AuthenticationError("The API key was revoked; ask the administrator for a new one.")
    now = utcnow()
    if client.expires_at is not None and client.expires_at <= now:
        raise AuthenticationError(
            f"The API key expired on {client.expires_at:%Y-%m-%d}; ask the administrator for a new one."
        )
    scopes = frozenset(client.scopes or ())
    if client.owner_user_id is not None:
        owner = db.get(User, client.owner_user_id)
        if owner is None or not owner.is_active:
            raise AuthenticationError(
                "The API key's owner no longer has an active account; ask the administrator"
                " for a new key."
            )
        scopes = owned_key_scopes(scopes, owner.role)
    if client.last_used_at is None or now - client.last_used_at > _TOUCH_INTERVAL:
        # Committed at once (nothing else is pending yet): a request that writes nothing
        # else, or writes through its own session (an upload), must count as a use too, or
        # an administrator would see a key in use as "never" used and revoke the wrong one.
        client.last_used_at = now
        db.commit()
    return Actor(type="api_client", id=client.id, name=client.name, scopes=scopes)


# --------------------------------------------------------------------------- browser sessions


def _browser_session(db: Session, token: str, idle_s: float | None) -> BrowserSession | None:
    row = db.get(BrowserSession, session_key(token))
    if row is None:
        return None
    now = utcnow()
    idle = idle_s is not None and now - row.last_seen_at > timedelta(seconds=idle_s)
    if row.expires_at <= now or idle:
        db.delete(row)
        db.commit()
        return None
    if now - row.last_seen_at > _TOUCH_INTERVAL:
        row.last_seen_at = now
        db.commit()  # at once, as a key's last use: the idle timeout reads it
    return row


def authenticate_session_cookie(
    db: Session, token: str, *, idle_s: float | None = None
) -> Actor | None:
    """The logged-in user of a session cookie, or ``None`` if absent, expired or inactive.

    ``idle_s``: a session unused this long has ended too (``settings.session_idle_s``).
    """
    row = _browser_session(db, token, idle_s)
    if row is None:
        return None
    user = db.get(User, row.user_id)
    if user is None or not user.is_active:
        return None
    return Actor(
        type="user",
        id=user.id,
        name=user.email,
        scopes=ROLE_SCOPES.get(user.role, frozenset()),
        role=user.role,
        csrf_token=row.csrf_token,
    )


async def _csrf_token_of(request: Request) -> str | None:
    token = request.headers.get(CSRF_HEADER)
    if token:
        return token
    content_type = request.headers.get("content-type", "")
    # Pages post forms; their body was already parsed by FastAPI (cached). The
    # API's streaming upload routes are never read here: the header is required.
    if not request.url.path.startswith("/api/") and content_type.startswith(
        ("application/x-www-form-urlencoded", "multipart/form-data")
    ):
        form = await request.form()
        value = form.get(CSRF_FORM_FIELD)
        return value if isinstance(value, str) else None
    return None


def csrf_matches(actor: Actor, sent: str | None) -> bool:
    """Whether ``sent`` is the session's CSRF token (constant-time comparison)."""
    return (
        bool(sent)
        and actor.csrf_token is not None
        and hmac.compare_digest(str(sent), actor.csrf_token)
    )


def record_csrf_refusal(db: Session, actor: Actor, path: str) -> None:
    """A request refused for its missing or stale CSRF token, in the audit trail: one of
    the few signs of a forged request (``access route PATH denied``)."""
    audit_failure(db, actor, "access", "route", path[:64], outcome="denied")


def _record_csrf_refusal_alone(request: Request, actor: Actor) -> None:
    with request.app.state.session_factory() as db:
        record_csrf_refusal(db, actor, request.url.path)


async def check_csrf(request: Request, actor: Actor) -> None:
    """Refuse (403, audited) a state-changing browser request without its CSRF token."""
    if actor.type != "user" or request.method in _SAFE_METHODS:
        return
    if not csrf_matches(actor, await _csrf_token_of(request)):
        await run_in_threadpool(_record_csrf_refusal_alone, request, actor)
        raise PermissionDeniedError(
            "The form's security token is missing or out of date; reload the page and retry."
        )


# --------------------------------------------------------------------------- dependencies


def _cookie_actor(request: Request, db: Session) -> Actor | None:
    cookie = request.cookies.get(SESSION_COOKIE)
    if not cookie:
        return None
    return authenticate_session_cookie(
        db, cookie, idle_s=float(request_settings(request).session_idle_s)
    )


def _authenticate(request: Request, db: SessionDep) -> Actor:
    # Synchronous (FastAPI runs it in the thread pool): it queries the database.
    authorization = request.headers.get("authorization")
    if authorization:
        scheme, _, token = authorization.partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            raise AuthenticationError(
                "Use 'Authorization: Bearer <api key>' to call the bradyscope API."
            )
        return authenticate_api_key(db, token.strip())
    actor = _cookie_actor(request, db)
    if actor is None:
        raise AuthenticationError(
            "Authentication required: send an API key ('Authorization: Bearer ...') or log in."
        )
    return actor


async def get_actor(request: Request, actor: Annotated[Actor, Depends(_authenticate)]) -> Actor:
    """The caller of an API route: an API client (Bearer) or a browser user (cookie + CSRF).

    Raises
    ------
    AuthenticationError
        No, malformed, unknown, revoked or expired credentials (401).
    PermissionDeniedError
        A browser's state-changing request without the CSRF token (403).
    """
    await check_csrf(request, actor)
    return actor


CurrentActor = Annotated[Actor, Depends(get_actor)]


def _authenticate_user(request: Request, db: SessionDep) -> Actor:
    actor = _cookie_actor(request, db)
    if actor is None:
        raise AuthenticationError("Please log in.")
    return actor


async def get_current_user(
    request: Request, actor: Annotated[Actor, Depends(_authenticate_user)]
) -> Actor:
    """The logged-in browser user (cookie session, CSRF-checked); 401 otherwise.

    HTML pages answer a 401 with a redirect to ``/login`` (see ``app.main``).
    """
    await check_csrf(request, actor)
    return actor


CurrentUser = Annotated[Actor, Depends(get_current_user)]


def get_optional_user(request: Request, db: SessionDep) -> Actor | None:
    """The logged-in browser user, or ``None`` (for the login page itself)."""
    return _cookie_actor(request, db)


OptionalUser = Annotated[Actor | None, Depends(get_optional_user)]


def get_optional_caller(request: Request, db: SessionDep) -> Actor | None:
    """The authenticated caller (API key or browser session) of a public route such as
    ``/health``, or ``None``: no credentials, wrong ones, or a database that cannot tell.
    Never refuses: the route answers everyone, and tells a caller more."""
    try:
        return _authenticate(request, db)
    except (AppError, SQLAlchemyError):
        db.rollback()
        return None


OptionalCaller = Annotated[Actor | None, Depends(get_optional_caller)]


def require_scope(*scopes: str, refusal: str | None = None) -> Callable[..., Any]:
    """A dependency returning the :class:`Actor` if it holds *every* one of ``scopes``.

    Example::

        @router.get("/patients")
        def list_patients(actor: Annotated[Actor, Depends(require_scope("patients:read"))]): ...

    A refusal is recorded in the audit trail (outcome ``denied``) and answered 403 with
    ``refusal``, or by default a sentence naming the missing scopes (give ``refusal`` for
    ``admin``, which no API key holds and nobody grants: say who does it, and where).
    """
    unknown = set(scopes) - set(SCOPES) - {ADMIN_SCOPE}
    if unknown:
        raise ValueError(f"unknown scopes {sorted(unknown)}; known: {[*SCOPES, ADMIN_SCOPE]}")

    def dependency(actor: CurrentActor, db: SessionDep, request: Request) -> Actor:
        missing = [s for s in scopes if not actor.has_scope(s)]
        if missing:
            audit_failure(db, actor, "access", "route", request.url.path[:64], outcome="denied")
            if refusal is not None:
                raise PermissionDeniedError(refusal)
            raise PermissionDeniedError(
                f"This {'API key' if actor.type == 'api_client' else 'account'} lacks the"
                f" scope {', '.join(missing)}; ask the administrator to grant it."
            )
        return actor

    dependency.__name__ = f"require_{'_'.join(s.replace(':', '_') for s in scopes)}"
    return dependency


def require_any_scope(*scopes: str) -> Callable[..., Any]:
    """A dependency returning the :class:`Actor` if it holds *one* of ``scopes`` (else 403,
    audited as :func:`require_scope`'s refusals)."""
    unknown = set(scopes) - set(SCOPES)
    if unknown:
        raise ValueError(f"unknown scopes {sorted(unknown)}; known: {list(SCOPES)}")

    def dependency(actor: CurrentActor, db: SessionDep, request: Request) -> Actor:
        if not any(actor.has_scope(s) for s in scopes):
            audit_failure(db, actor, "access", "route", request.url.path[:64], outcome="denied")
            raise PermissionDeniedError(
                f"This {'API key' if actor.type == 'api_client' else 'account'} holds none of"
                f" the scopes {', '.join(scopes)}; ask the administrator to grant one."
            )
        return actor

    dependency.__name__ = "require_one_of_" + "_".join(s.replace(":", "_") for s in scopes)
    return dependency


# The actors of the routes, one alias per scope (shared by the API routers).
PatientReader = Annotated[Actor, Depends(require_scope("patients:read"))]
PatientWriter = Annotated[Actor, Depends(require_scope("patients:write"))]
RecordingWriter = Annotated[Actor, Depends(require_scope("recordings:write"))]
ResultReader = Annotated[Actor, Depends(require_scope("results:read"))]
RigWriter = Annotated[Actor, Depends(require_scope("rigs:write"))]
DataReader = Annotated[Actor, Depends(require_any_scope(*DATA_SCOPES))]
"""Rigs, calibrations and job status: any data scope (what the clinical pages' roles hold);
a key or account reading only the audit trail (an auditor) is refused, as on the pages."""

"""Authentication and authorisation: API keys for hospital systems, sessions for browsers.

Two kinds of callers, one :class:`Actor`:

- **API clients** send ``Authorization: Bearer bsk_<prefix>_<secret>``
  (:mod:`app.apikeys`). The key is looked up by its prefix and compared by
  hash; a revoked key is refused (401). Each client holds *scopes*; a route
  names the scope it needs with :func:`require_scope` (403 without it).
- **Browsers** log in with e-mail and password (argon2, :mod:`app.passwords`)
  and get a server-side session: the cookie holds a random token, the
  database only its SHA-256 (``BrowserSession.id``). The cookie is HttpOnly,
  SameSite=Lax, and Secure when ``settings.secure_cookies``. Every
  state-changing browser request (POST, PUT, PATCH, DELETE) must carry the
  session's CSRF token, in the ``X-CSRF-Token`` header or a ``csrf_token``
  form field (403 otherwise). Users have every data scope; admins also
  ``admin``.
- **Login throttling** (:mod:`app.throttle`): growing delays per account and
  per (address, account) pair, counted atomically before the password is
  checked; 429 with ``Retry-After`` while an attempt must wait.
- A browser session ends after ``settings.session_ttl_s`` (absolute) or after
  ``settings.session_idle_s`` without a request (idle).
- :func:`reauthenticate` checks a logged-in user's password again (for
  signing), through the same throttle.

Dependencies (``Annotated`` aliases for route signatures): :data:`SessionDep`,
:data:`CurrentActor`, :data:`CurrentUser`, :data:`OptionalUser`, and
``require_scope("patients:read")``.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import timedelta
from typing import Annotated, Any

from fastapi import Depends, Request, Response
from sqlalchemy import select
from sqlalchemy.orm import Session

from app import throttle
from app.actors import ADMIN_SCOPE, ROLE_SCOPES, Actor
from app.apikeys import SCOPES, parse_api_key, verify_api_key
from app.audit import ANONYMOUS, audit, audit_failure
from app.errors import AuthenticationError, PermissionDeniedError, RateLimitedError
from app.models import ApiClient, BrowserSession, User, utcnow
from app.oidc import Identity
from app.passwords import DUMMY_HASH, NO_PASSWORD, hash_password, needs_rehash, verify_password
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


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


email_hash = throttle.email_hash
normalise_email = throttle.normalise_email


def _client_ip(request: Request) -> str | None:
    return request.client.host[:45] if request.client else None


def _settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


# --------------------------------------------------------------------------- API keys


def authenticate_api_key(db: Session, token: str) -> Actor:
    """The API client owning ``token``.

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
    if client.owner_user_id is not None:
        owner = db.get(User, client.owner_user_id)
        if owner is None or not owner.is_active:
            raise AuthenticationError(
                "The API key's owner no longer has an active account; ask the administrator"
                " for a new key."
            )
    if client.last_used_at is None or now - client.last_used_at > _TOUCH_INTERVAL:
        client.last_used_at = now  # committed with the request's use case, if any
    return Actor(
        type="api_client",
        id=client.id,
        name=client.name,
        scopes=frozenset(client.scopes or ()),
    )


# --------------------------------------------------------------------------- browser sessions


def _browser_session(db: Session, token: str, idle_s: float | None) -> BrowserSession | None:
    row = db.get(BrowserSession, _sha256(token))
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


async def check_csrf(request: Request, actor: Actor) -> None:
    """Refuse (403) a state-changing browser request without its session's CSRF token."""
    if actor.type != "user" or request.method in _SAFE_METHODS:
        return
    sent = await _csrf_token_of(request)
    if not sent or actor.csrf_token is None or not hmac.compare_digest(sent, actor.csrf_token):
        raise PermissionDeniedError(
            "The form's security token is missing or out of date; reload the page and retry."
        )


# --------------------------------------------------------------------------- dependencies


def _cookie_actor(request: Request, db: Session) -> Actor | None:
    cookie = request.cookies.get(SESSION_COOKIE)
    if not cookie:
        return None
    return authenticate_session_cookie(db, cookie, idle_s=float(_settings(request).session_idle_s))


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


def require_scope(*scopes: str) -> Callable[..., Any]:
    """A dependency returning the :class:`Actor` if it holds *every* one of ``scopes``.

    Example::

        @router.get("/patients")
        def list_patients(actor: Annotated[Actor, Depends(require_scope("patients:read"))]): ...

    A refusal is recorded in the audit trail (outcome ``denied``) and answered 403.
    """
    unknown = set(scopes) - set(SCOPES) - {ADMIN_SCOPE}
    if unknown:
        raise ValueError(f"unknown scopes {sorted(unknown)}; known: {[*SCOPES, ADMIN_SCOPE]}")

    def dependency(actor: CurrentActor, db: SessionDep, request: Request) -> Actor:
        missing = [s for s in scopes if not actor.has_scope(s)]
        if missing:
            audit_failure(db, actor, "access", "route", request.url.path[:64], outcome="denied")
            raise PermissionDeniedError(
                f"This {'API key' if actor.type == 'api_client' else 'account'} lacks the"
                f" scope {', '.join(missing)}; ask the administrator to grant it."
            )
        return actor

    dependency.__name__ = f"require_{'_'.join(s.replace(':', '_') for s in scopes)}"
    return dependency


# The actors of the routes, one alias per scope (shared by the API routers).
PatientReader = Annotated[Actor, Depends(require_scope("patients:read"))]
PatientWriter = Annotated[Actor, Depends(require_scope("patients:write"))]
RecordingWriter = Annotated[Actor, Depends(require_scope("recordings:write"))]
ResultReader = Annotated[Actor, Depends(require_scope("results:read"))]
RigWriter = Annotated[Actor, Depends(require_scope("rigs:write"))]


# --------------------------------------------------------------------------- login / logout


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
    ok = verify_password(user.password_hash if user and local else DUMMY_HASH, password)
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
        ``actor`` is not a browser user (API keys cannot re-authenticate).
    RateLimitedError
        Too many wrong passwords (429).
    AuthenticationError
        The password is wrong, or the account was deactivated (401).
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
        raise AuthenticationError("The password is wrong.")
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
        old = db.get(BrowserSession, _sha256(replace_token))
        if old is not None:
            db.delete(old)
    if password is not None and needs_rehash(user.password_hash):
        user.password_hash = hash_password(password)
    token = secrets.token_urlsafe(32)
    csrf_token = secrets.token_urlsafe(32)
    now = utcnow()
    db.add(
        BrowserSession(
            id=_sha256(token),
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
        row = db.get(BrowserSession, _sha256(token))
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
    settings = _settings(request)
    result = login_user(
        db,
        settings=settings,
        email=email,
        password=password,
        ip=_client_ip(request),
        user_agent=request.headers.get("user-agent"),
        replace_token=request.cookies.get(SESSION_COOKIE),
    )
    set_session_cookie(response, result.token, settings=settings)
    return result


def logout_from_request(db: Session, request: Request, response: Response) -> None:
    """:func:`logout_user` for a request (its cookie), clearing the cookie on ``response``."""
    logout_user(
        db, response, token=request.cookies.get(SESSION_COOKIE), settings=_settings(request)
    )

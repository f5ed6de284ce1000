"""Optional single sign-on through OpenID Connect (authorization code flow with PKCE).

For hospitals whose policy is that staff log in at the hospital's identity
provider (with its multi-factor authentication). Off unless
``BRADYSCOPE_OIDC_ISSUER`` and ``BRADYSCOPE_OIDC_CLIENT_ID`` are set; local
accounts stay the embedded default and keep working (unless
``BRADYSCOPE_LOCAL_LOGIN=false``).

1. ``GET /login/oidc`` reads the provider's discovery document, makes a
   ``state``, a ``nonce`` and a PKCE verifier (Authlib), keeps them in a
   short-lived cookie sealed with the instance key, and redirects the
   browser to the provider.
2. ``GET /auth/oidc/callback`` checks ``state`` against the cookie, exchanges
   the code (with the verifier) at the token endpoint, and validates the ID
   token with joserfc: signature against the provider's JWKS, ``iss``,
   ``aud``, ``exp``, ``nonce``.
3. The person is the local account with the token's e-mail address (which
   the provider must mark verified); it must exist and be active, unless
   ``BRADYSCOPE_OIDC_CREATE_USERS`` lets the first login create a clinician
   account (without a local password). The account's ``oidc_subject`` is
   bound at the first login and must match afterwards. Then a browser session
   opens exactly as after a password login, and the login is audited.

Authlib and joserfc (one author, BSD licence) are the well-kept
implementations of the OAuth 2 and JOSE standards in Python; httpx talks to
the provider.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import time
from dataclasses import dataclass
from typing import Any

from app.errors import AuthenticationError, ServiceUnavailableError
from app.settings import Settings

STATE_COOKIE = "bradyscope_oidc"
CALLBACK_PATH = "/auth/oidc/callback"
STATE_MAX_AGE_S = 600
ID_TOKEN_ALGORITHMS = ["RS256", "RS384", "RS512", "PS256", "PS384", "PS512", "ES256", "ES384"]
_TIMEOUT_S = 10.0
# Authlib, joserfc and httpx are imported where they are used: a site without single
# sign-on does not pay for them at start-up.


class OidcError(AuthenticationError):
    """Single sign-on did not succeed (401); the sentence says why."""


def enabled(settings: Settings) -> bool:
    """Whether single sign-on is configured."""
    return bool(settings.oidc_issuer and settings.oidc_client_id)


@dataclass(frozen=True)
class Provider:
    """The endpoints of the identity provider, from its discovery document."""

    issuer: str
    authorization_endpoint: str
    token_endpoint: str
    jwks_uri: str


_providers: dict[str, tuple[float, Provider]] = {}
_DISCOVERY_TTL_S = 3600.0


def _get_json(url: str) -> dict[str, Any]:
    import httpx

    try:
        response = httpx.get(url, timeout=_TIMEOUT_S, follow_redirects=False)
        response.raise_for_status()
        doc = response.json()
    except (httpx.HTTPError, ValueError) as exc:
        raise ServiceUnavailableError(
            f"The identity provider does not answer at {url} ({type(exc).__name__}); log in with"
            " a local account or ask the administrator to check BRADYSCOPE_OIDC_ISSUER."
        ) from exc
    if not isinstance(doc, dict):
        raise ServiceUnavailableError(
            f"The identity provider's answer at {url} is not a JSON object."
        )
    return doc


def provider(settings: Settings) -> Provider:
    """The provider's endpoints (discovery, cached for an hour)."""
    issuer = str(settings.oidc_issuer).rstrip("/")
    cached = _providers.get(issuer)
    if cached is not None and time.monotonic() - cached[0] < _DISCOVERY_TTL_S:
        return cached[1]
    doc = _get_json(f"{issuer}/.well-known/openid-configuration")
    if str(doc.get("issuer", "")).rstrip("/") != issuer:
        raise ServiceUnavailableError(
            f"The identity provider calls itself {doc.get('issuer')!r}, not {issuer!r};"
            " set BRADYSCOPE_OIDC_ISSUER to its exact issuer."
        )
    try:
        found = Provider(
            issuer=str(doc["issuer"]),
            authorization_endpoint=str(doc["authorization_endpoint"]),
            token_endpoint=str(doc["token_endpoint"]),
            jwks_uri=str(doc["jwks_uri"]),
        )
    except KeyError as exc:
        raise ServiceUnavailableError(
            f"The identity provider's discovery document lacks {exc.args[0]}."
        ) from exc
    _providers[issuer] = (time.monotonic(), found)
    return found


# --------------------------------------------------------------------------- the state cookie


def _seal(key: bytes, payload: dict[str, Any]) -> str:
    body = base64.urlsafe_b64encode(json.dumps(payload, separators=(",", ":")).encode()).decode()
    mac = hmac.new(key, b"oidc-state\n" + body.encode(), hashlib.sha256).hexdigest()
    return f"{body}.{mac}"


def _unseal(key: bytes, value: str) -> dict[str, Any]:
    body, _, mac = value.rpartition(".")
    expected = hmac.new(key, b"oidc-state\n" + body.encode(), hashlib.sha256).hexdigest()
    if not body or not hmac.compare_digest(mac, expected):
        raise OidcError("The single sign-on attempt cannot be verified; start the login again.")
    payload = json.loads(base64.urlsafe_b64decode(body.encode()))
    if not isinstance(payload, dict) or time.time() - float(payload.get("at", 0)) > STATE_MAX_AGE_S:
        raise OidcError("The single sign-on attempt took too long; start the login again.")
    return payload


@dataclass(frozen=True)
class Start:
    """Where to send the browser, and the cookie that remembers this attempt."""

    url: str
    cookie: str


def start(settings: Settings, key: bytes, redirect_uri: str, next_url: str) -> Start:
    """Begin a login at the provider: the authorization URL (PKCE S256) and the state cookie."""
    from authlib.common.security import generate_token
    from authlib.common.urls import add_params_to_uri
    from authlib.oauth2.rfc7636 import create_s256_code_challenge

    found = provider(settings)
    state, nonce, verifier = generate_token(32), generate_token(32), generate_token(64)
    url = add_params_to_uri(
        found.authorization_endpoint,
        [
            ("response_type", "code"),
            ("client_id", str(settings.oidc_client_id)),
            ("redirect_uri", redirect_uri),
            ("scope", settings.oidc_scopes),
            ("state", state),
            ("nonce", nonce),
            ("code_challenge", create_s256_code_challenge(verifier)),
            ("code_challenge_method", "S256"),
        ],
    )
    cookie = _seal(
        key,
        {"state": state, "nonce": nonce, "verifier": verifier, "next": next_url, "at": time.time()},
    )
    return Start(url=url, cookie=cookie)


@dataclass(frozen=True)
class Identity:
    """Who the provider says logged in."""

    subject: str
    email: str
    name: str | None
    next_url: str


def finish(
    settings: Settings, key: bytes, *, cookie: str | None, code: str, state: str, redirect_uri: str
) -> Identity:
    """Check the callback, exchange the code, validate the ID token; who logged in.

    Raises
    ------
    OidcError
        A forged or stale state, a refused code, an invalid token, no verified e-mail (401).
    ServiceUnavailableError
        The provider cannot be reached (503).
    """
    import httpx
    from joserfc import jwt
    from joserfc.errors import JoseError
    from joserfc.jwk import KeySet

    if not cookie:
        raise OidcError("The single sign-on attempt was not started here; start the login again.")
    remembered = _unseal(key, cookie)
    if not hmac.compare_digest(str(remembered.get("state", "")), state):
        raise OidcError("The single sign-on answer does not belong to this login; start again.")
    found = provider(settings)
    try:
        response = httpx.post(
            found.token_endpoint,
            data={
                "grant_type": "authorization_code",
                "code": code,
                "redirect_uri": redirect_uri,
                "code_verifier": str(remembered["verifier"]),
            },
            auth=(str(settings.oidc_client_id), str(settings.oidc_client_secret or "")),
            headers={"Accept": "application/json"},
            timeout=_TIMEOUT_S,
        )
    except httpx.HTTPError as exc:
        raise ServiceUnavailableError(
            f"The identity provider's token endpoint does not answer ({type(exc).__name__})."
        ) from exc
    if response.status_code != 200:
        raise OidcError(
            f"The identity provider refused the login (HTTP {response.status_code}); start again."
        )
    try:
        id_token = str(response.json()["id_token"])
    except (ValueError, KeyError, TypeError) as exc:
        raise OidcError("The identity provider sent no ID token; check its client set-up.") from exc
    keys = KeySet.import_key_set(_get_json(found.jwks_uri))  # type: ignore[arg-type]
    try:
        token = jwt.decode(id_token, keys, algorithms=ID_TOKEN_ALGORITHMS)
        jwt.JWTClaimsRegistry(
            iss={"essential": True, "value": found.issuer},
            aud={"essential": True, "value": str(settings.oidc_client_id)},
            sub={"essential": True},
            exp={"essential": True},
            nonce={"essential": True, "value": str(remembered["nonce"])},
        ).validate(token.claims)
    except (JoseError, ValueError) as exc:
        raise OidcError(
            f"The identity provider's ID token is not valid ({exc}); start again."
        ) from exc
    return _identity(settings, token.claims, str(remembered.get("next") or "/patients"))


def _identity(settings: Settings, claims: dict[str, Any], next_url: str) -> Identity:
    """Who the validated ID token's claims name; their e-mail address must be verified."""
    email = str(claims.get(settings.oidc_email_claim) or "").strip().lower()
    if not email:
        raise OidcError(
            f"The identity provider sent no e-mail address ({settings.oidc_email_claim});"
            " ask the administrator to release it to bradyscope."
        )
    verified = claims.get("email_verified")
    if verified is False or (settings.oidc_require_verified_email and verified is not True):
        # the address finds the account at a first login: an unverified one could be anyone's
        raise OidcError(
            f"The identity provider has not confirmed that {email} is verified"
            " (email_verified); ask the administrator."
        )
    name = claims.get("name")
    return Identity(
        subject=str(claims["sub"]),
        email=email,
        name=str(name)[:200] if name else None,
        next_url=next_url,
    )


__all__ = [
    "CALLBACK_PATH",
    "STATE_COOKIE",
    "Identity",
    "OidcError",
    "Start",
    "enabled",
    "finish",
    "start",
]

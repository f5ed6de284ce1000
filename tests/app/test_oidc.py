"""Optional single sign-on through OpenID Connect (issue 18), against a local provider.

The provider is ``oidc-provider-mock`` (a maintained test provider built on
Authlib), started in a thread on 127.0.0.1 by the test itself: discovery, an
authorization form, a token endpoint and RS256-signed ID tokens, no network.
"""

from __future__ import annotations

from collections.abc import Iterator
from urllib.parse import parse_qs, quote, urlsplit

import httpx
import pytest
from api_support import make_user
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.main import create_app
from app.models import AuditEvent, BrowserSession, User
from app.settings import Settings

PASSWORD = "correct horse battery"


@pytest.fixture(scope="module")
def provider() -> Iterator[str]:
    oidc_provider_mock = pytest.importorskip("oidc_provider_mock")
    with oidc_provider_mock.run_server_in_thread(require_nonce=True) as server:
        yield f"http://localhost:{server.server_port}"


def _claims(issuer: str, sub: str, **claims: object) -> None:
    r = httpx.put(f"{issuer}/users/{quote(sub)}", json=claims)
    assert r.status_code == 204, r.text


def _sso_settings(settings: Settings, issuer: str, **extra: object) -> Settings:
    return settings.model_copy(
        update={
            "oidc_issuer": issuer,
            "oidc_client_id": "bradyscope-test",
            "oidc_client_secret": "not-a-secret",
            **extra,
        }
    )


def _sso_login(
    client: TestClient, issuer: str, sub: str, *, next_url: str = "/patients"
) -> httpx.Response:
    """Start at bradyscope, authorise at the provider as ``sub``, come back with the code."""
    start = client.get(f"/login/oidc?next={quote(next_url)}", follow_redirects=False)
    assert start.status_code == 303, start.text
    authorize = start.headers["location"]
    assert authorize.startswith(issuer)
    query = parse_qs(urlsplit(authorize).query)
    assert query["code_challenge_method"] == ["S256"] and query["nonce"]
    consent = httpx.post(authorize, data={"sub": sub}, follow_redirects=False)
    assert consent.is_redirect, consent.text
    back = urlsplit(consent.headers["location"])
    assert back.path == "/auth/oidc/callback"
    return client.get(f"{back.path}?{back.query}", follow_redirects=False)


def test_oidc_login_opens_a_session_for_the_matching_account(
    app_settings: Settings, db_sessionmaker, provider: str
) -> None:
    user_id = make_user(db_sessionmaker, "doc@example.org", PASSWORD)
    _claims(provider, "u-123", email="doc@example.org", email_verified=True, name="Dr Doc")
    app = create_app(_sso_settings(app_settings, provider))
    with TestClient(app) as client:
        page = client.get("/login")
        assert 'href="/login/oidc' in page.text  # the button
        r = _sso_login(client, provider, "u-123", next_url="/rigs")
        assert r.status_code == 303 and r.headers["location"] == "/rigs", r.text
        me = client.get("/api/v1/auth/me")
        assert me.status_code == 200 and me.json()["id"] == user_id
    with db_sessionmaker() as db:
        assert db.scalar(select(User.oidc_subject).where(User.id == user_id)) == "u-123"
        login = db.scalars(select(AuditEvent).where(AuditEvent.action == "login")).all()[-1]
        assert (login.actor_type, login.actor_id, login.outcome) == (
            "user",
            str(user_id),
            "success",
        )
        assert db.scalar(select(BrowserSession.user_id)) == user_id


def test_oidc_refuses_unknown_people_forged_state_and_other_subjects(
    app_settings: Settings, db_sessionmaker, provider: str
) -> None:
    make_user(db_sessionmaker, "doc@example.org", PASSWORD)
    _claims(provider, "stranger", email="stranger@example.org", email_verified=True)
    _claims(provider, "imposter", email="doc@example.org", email_verified=True)
    _claims(provider, "u-doc", email="doc@example.org", email_verified=True)
    app = create_app(_sso_settings(app_settings, provider))
    with TestClient(app) as client:
        r = _sso_login(client, provider, "stranger")
        assert r.status_code == 401 and "no bradyscope account" in r.text
        assert _sso_login(client, provider, "u-doc").status_code == 303  # binds u-doc
        client.cookies.clear()
        r = _sso_login(client, provider, "imposter")  # same e-mail, another subject
        assert r.status_code == 401 and "another identity" in r.text
        # a callback that this browser did not start
        fresh = TestClient(app)
        r = fresh.get("/auth/oidc/callback?code=x&state=y", follow_redirects=False)
        assert r.status_code == 401
        assert fresh.get("/api/v1/auth/me").status_code == 401
    with db_sessionmaker() as db:
        denied = db.scalars(
            select(AuditEvent).where(AuditEvent.action == "login", AuditEvent.outcome == "denied")
        ).all()
    assert len(denied) == 3


def test_first_login_may_create_a_clinician_without_a_local_password(
    app_settings: Settings, db_sessionmaker, provider: str
) -> None:
    _claims(provider, "new-1", email="new@example.org", email_verified=True, name="New Doc")
    app = create_app(_sso_settings(app_settings, provider, oidc_create_users=True))
    with TestClient(app) as client:
        assert _sso_login(client, provider, "new-1").status_code == 303
        assert client.get("/api/v1/auth/me").json()["role"] == "clinician"
        # no password opens this account
        r = client.post(
            "/api/v1/auth/login",
            json={"email": "new@example.org", "password": "!no-local-password"},
        )
        assert r.status_code == 401


def test_local_login_works_without_oidc_and_can_be_switched_off(
    app_settings: Settings, db_sessionmaker, provider: str
) -> None:
    make_user(db_sessionmaker, "doc@example.org", PASSWORD)
    plain = create_app(app_settings)  # OIDC not configured: the embedded default
    with TestClient(plain) as client:
        assert "/login/oidc" not in client.get("/login").text
        assert client.get("/login/oidc", follow_redirects=False).status_code in (303, 404)
        # nothing to log into: anyone's calls to the callback leave the trail alone
        with db_sessionmaker() as db:
            before = len(db.scalars(select(AuditEvent)).all())
        for _ in range(3):
            assert client.get("/auth/oidc/callback?error=x").status_code == 401
        with db_sessionmaker() as db:
            assert len(db.scalars(select(AuditEvent)).all()) == before
        r = client.post(
            "/api/v1/auth/login", json={"email": "doc@example.org", "password": PASSWORD}
        )
        assert r.status_code == 200
    sso_only = create_app(_sso_settings(app_settings, provider, local_login=False))
    with TestClient(sso_only) as client:
        r = client.post(
            "/api/v1/auth/login", json={"email": "doc@example.org", "password": PASSWORD}
        )
        assert r.status_code == 401 and "single sign-on" in r.json()["detail"]


def test_an_address_the_provider_does_not_say_is_verified_opens_no_account(
    app_settings: Settings, db_sessionmaker, provider: str
) -> None:
    """A security review: without ``email_verified`` the address still found, and bound,
    an account (an administrator's that has no SSO subject yet, say). Refused now unless
    the provider is trusted to manage its addresses (BRADYSCOPE_OIDC_REQUIRE_VERIFIED_EMAIL)."""
    make_user(db_sessionmaker, "admin@example.org", PASSWORD)
    _claims(provider, "self-asserted", email="admin@example.org")
    with TestClient(create_app(_sso_settings(app_settings, provider))) as client:
        r = _sso_login(client, provider, "self-asserted")
        assert r.status_code == 401 and "verified" in r.text
    with db_sessionmaker() as db:
        assert db.scalar(select(User.oidc_subject).where(User.email == "admin@example.org")) is None
    trusting = _sso_settings(app_settings, provider, oidc_require_verified_email=False)
    with TestClient(create_app(trusting)) as client:
        assert _sso_login(client, provider, "self-asserted").status_code == 303

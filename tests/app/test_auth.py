# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Authentication and authorisation: every route is closed, keys, scopes, sessions, CSRF, throttling."""

from __future__ import annotations

import re
from datetime import timedelta

import pytest
from api_support import (
    Api,
    api,  # noqa: F401 - pytest fixtures
    make_api_key,
    make_user,
)
from fastapi.routing import iter_route_contexts
from fastapi.testclient import TestClient
from sqlalchemy import select, update

from app.auth import SESSION_COOKIE
from app.main import create_app
from app.models import ApiClient, AuditEvent, BrowserSession, User, utcnow

PASSWORD = "correct horse battery"
# Routes that must answer without credentials: the login page and its form,
# static files, the OpenAPI document, the health check and the empty favicon
# (so the standalone report pages raise no console 404).
ALLOW_LIST = {
    ("GET", "/health"),
    ("GET", "/favicon.ico"),
    ("GET", "/openapi.json"),
    ("GET", "/login"),
    ("POST", "/login"),
    ("POST", "/api/v1/auth/login"),
}


def _all_routes(app) -> list[tuple[str, str]]:
    routes = []
    for rc in iter_route_contexts(app.routes):
        methods = getattr(rc, "methods", None)
        if not methods:  # a mount (static files)
            continue
        for method in sorted(methods - {"HEAD"}):
            routes.append((method, rc.path))
    return routes


def test_every_route_refuses_unauthenticated_callers(api: Api) -> None:
    code = "PD-SECRET-77"
    created = api.client.post("/api/v1/patients", json={"code": code}, headers=api.headers)
    assert created.status_code == 201
    routes = _all_routes(api.app)
    paths = {p for _, p in routes}
    # the walk covers the API and the browser pages (if the web layer has any)
    assert "/api/v1/patients/{patient_id}" in paths and "/api/v1/trials/{trial_id}/fhir" in paths
    checked = 0
    anonymous = TestClient(api.app, follow_redirects=False)
    for method, path in routes:
        if (method, path) in ALLOW_LIST or path.startswith("/static"):
            continue
        url = re.sub(r"\{[^}]+\}", "1", path)
        for accept in ("application/json", "text/html"):
            r = anonymous.request(method, url, headers={"Accept": accept})
            where = f"{method} {url} (Accept: {accept}) -> {r.status_code}"
            hops = 0
            # a redirect to another page (e.g. / -> /patients) must end at the login page
            while r.is_redirect and not r.headers["location"].startswith("/login") and hops < 3:
                assert code not in r.text, where
                r = anonymous.get(r.headers["location"], headers={"Accept": accept})
                where += f" -> {r.request.url.path} {r.status_code}"
                hops += 1
            if r.is_redirect:
                assert r.headers["location"].startswith("/login"), where
            else:
                assert r.status_code in (401, 403), where
            assert code not in r.text, where
        checked += 1
    assert checked >= 25  # the API alone has more routes than this


def test_every_api_route_refuses_a_forged_key(api: Api) -> None:
    forged = {"Authorization": "Bearer bsk_0123456789ab_" + "A" * 43}  # well-formed, unknown
    client = TestClient(api.app, follow_redirects=False)
    for method, path in _all_routes(api.app):
        if not path.startswith("/api/v1/") or (method, path) in ALLOW_LIST:
            continue
        r = client.request(method, re.sub(r"\{[^}]+\}", "1", path), headers=forged)
        assert r.status_code == 401, f"{method} {path} -> {r.status_code}"


def test_a_key_without_scopes_reaches_no_patient_data(api: Api) -> None:
    from test_audit import CASES

    bare = make_api_key(api.sessions, name="no-scopes", scopes=())
    h = {"Authorization": f"Bearer {bare}"}
    for case in CASES:
        url = re.sub(r"\{[^}]+\}", "1", case.route)
        r = api.client.request(case.method, url, headers=h)
        assert r.status_code == 403, f"{case.method} {case.route} -> {r.status_code}"


def test_allow_listed_routes_hold_no_patient_data(api: Api) -> None:
    api.client.post("/api/v1/patients", json={"code": "PD-HIDDEN-1"}, headers=api.headers)
    anonymous = TestClient(api.app)
    for url in ("/health", "/openapi.json", "/login"):
        r = anonymous.get(url)
        assert r.status_code in (200, 404), url
        assert "PD-HIDDEN-1" not in r.text


def test_a_key_s_last_use_is_kept_by_a_request_that_writes_nothing(api: Api) -> None:
    """`admin list-api-keys` showed "never" for keys in use: the time was only saved when
    the request wrote something else."""

    def last_used():
        with api.sessions() as db:
            return db.scalar(select(ApiClient.last_used_at))

    assert last_used() is None
    assert api.client.get("/api/v1/auth/me", headers=api.headers).status_code == 200
    first = last_used()
    assert first is not None
    # at most once a minute: the next request does not write again
    assert api.client.get("/api/v1/auth/me", headers=api.headers).status_code == 200
    assert last_used() == first


def test_malformed_unknown_and_revoked_keys_are_refused(api: Api) -> None:
    c = api.client
    for header in ("Bearer nonsense", "Basic dXNlcjpwdw==", f"Bearer {api.key[:-2]}xx"):
        r = c.get("/api/v1/patients", headers={"Authorization": header})
        assert r.status_code == 401, header
        assert r.headers["www-authenticate"] == "Bearer"
    assert c.get("/api/v1/patients", headers=api.headers).status_code == 200
    with api.sessions() as db:
        db.execute(update(ApiClient).values(revoked_at=utcnow()))
        db.commit()
    r = c.get("/api/v1/patients", headers=api.headers)
    assert r.status_code == 401
    assert "revoked" in r.json()["detail"]


def test_scopes_are_enforced_and_refusals_audited(api: Api) -> None:
    reader = make_api_key(api.sessions, name="reader", scopes=("patients:read",))
    h = {"Authorization": f"Bearer {reader}"}
    assert api.client.get("/api/v1/patients", headers=h).status_code == 200
    r = api.client.post("/api/v1/patients", json={"code": "PD-1"}, headers=h)
    assert r.status_code == 403
    assert "patients:write" in r.json()["detail"]
    assert api.client.get("/api/v1/trials/1/result", headers=h).status_code == 403
    assert api.client.post("/api/v1/rigs", json={"name": "x"}, headers=h).status_code == 403
    with api.sessions() as db:
        denied = list(db.scalars(select(AuditEvent).where(AuditEvent.outcome == "denied")))
    assert len(denied) == 3
    assert all(e.actor_type == "api_client" for e in denied)
    assert api.count(ApiClient) == 2


def _login(client: TestClient, email: str, password: str):
    return client.post("/api/v1/auth/login", json={"email": email, "password": password})


def test_passwords_are_argon2_and_login_sets_a_safe_cookie(api: Api) -> None:
    make_user(api.sessions, "Doc@Example.org", PASSWORD)
    with api.sessions() as db:
        stored = db.scalar(select(User.password_hash))
    assert stored.startswith("$argon2id$") and PASSWORD not in stored
    r = _login(api.client, "doc@example.org", PASSWORD)
    assert r.status_code == 200, r.text
    cookie = r.headers["set-cookie"]
    assert f"{SESSION_COOKIE}=" in cookie
    assert "HttpOnly" in cookie and "samesite=lax" in cookie.lower() and "Path=/" in cookie
    assert "Secure" not in cookie  # plain-HTTP test settings; see the next test
    with api.sessions() as db:
        row = db.scalar(select(BrowserSession))
    token = api.client.cookies[SESSION_COOKIE]
    assert row is not None and token not in (row.id, row.csrf_token)  # only its hash is stored
    me = api.client.get("/api/v1/auth/me")
    assert me.status_code == 200 and me.json()["type"] == "user"


def test_secure_settings_give_secure_cookies_and_hsts(app_settings, db_sessionmaker) -> None:
    settings = app_settings.model_copy(update={"secure_cookies": True})
    make_user(db_sessionmaker, "doc@example.org", PASSWORD)
    with TestClient(create_app(settings), base_url="https://testserver") as client:
        r = _login(client, "doc@example.org", PASSWORD)
        assert r.status_code == 200
        assert "Secure" in r.headers["set-cookie"]
        assert r.headers["strict-transport-security"].startswith("max-age=")


def test_browser_changes_need_the_csrf_token(api: Api) -> None:
    make_user(api.sessions, "doc@example.org", PASSWORD)
    browser = TestClient(api.app)
    csrf = _login(browser, "doc@example.org", PASSWORD).json()["csrf_token"]
    assert browser.get("/api/v1/patients").status_code == 200  # reads need no token
    r = browser.post("/api/v1/patients", json={"code": "PD-CSRF"})
    assert r.status_code == 403
    assert "security token" in r.json()["detail"]
    r = browser.post(
        "/api/v1/patients", json={"code": "PD-CSRF"}, headers={"X-CSRF-Token": "x" * 43}
    )
    assert r.status_code == 403
    assert api.client.get("/api/v1/patients", headers=api.headers).json()["total"] == 0
    r = browser.post("/api/v1/patients", json={"code": "PD-CSRF"}, headers={"X-CSRF-Token": csrf})
    assert r.status_code == 201
    with api.sessions() as db:
        event = db.scalar(select(AuditEvent).where(AuditEvent.action == "create"))
    assert event is not None and event.actor_type == "user"


def test_login_is_throttled_per_account_not_per_ip(app_settings, db_sessionmaker) -> None:
    limit = 2  # failures per address and account (the default is 5; fewer argon2 checks)
    settings = app_settings.model_copy(update={"login_max_failures": limit})
    api = Api(create_app(settings), None, settings, db_sessionmaker, "")  # type: ignore[arg-type]
    api.client = TestClient(api.app)
    make_user(api.sessions, "doc@example.org", PASSWORD)
    make_user(api.sessions, "other@example.org", PASSWORD)
    for _ in range(limit):
        r = _login(api.client, "doc@example.org", "wrong password")
        assert r.status_code == 401
        assert r.json()["detail"] == "The e-mail address or the password is wrong."
    # now even the right password must wait, for this address and account only
    r = _login(api.client, "doc@example.org", PASSWORD)
    assert r.status_code == 429
    assert "Too many failed logins" in r.json()["detail"]
    assert _login(api.client, "other@example.org", PASSWORD).status_code == 200
    # an unknown address answers exactly like a wrong password (no account enumeration)
    r = _login(api.client, "nobody@example.org", "whatever1")
    assert r.status_code == 401
    assert r.json()["detail"] == "The e-mail address or the password is wrong."
    # one IP guessing across many addresses locks nobody else out (issue 18, finding 2):
    # behind a hospital NAT that would be a denial of service for every user
    for i in range(4 * limit):
        _login(api.client, f"guess{i}@example.org", "wrong password")
    assert _login(api.client, "fresh@example.org", "wrong password").status_code == 401
    assert _login(api.client, "other@example.org", PASSWORD).status_code == 200


def test_failed_login_is_audited_as_anonymous(api: Api) -> None:
    user_id = make_user(api.sessions, "doc@example.org", PASSWORD)
    assert _login(api.client, "doc@example.org", "wrong password").status_code == 401
    assert _login(api.client, "nobody@example.org", "wrong password").status_code == 401
    logins = [e for e in api.audit_events() if e.action == "login"]
    assert [(e.actor_type, e.actor_id, e.outcome, e.resource_id) for e in logins] == [
        ("anonymous", None, "denied", str(user_id)),
        ("anonymous", None, "denied", None),
    ]
    assert _login(api.client, "doc@example.org", PASSWORD).status_code == 200
    event = [e for e in api.audit_events() if e.action == "login"][-1]
    assert (event.actor_type, event.actor_id, event.outcome) == ("user", str(user_id), "success")


def test_logout_and_expiry_end_the_session(api: Api) -> None:
    make_user(api.sessions, "doc@example.org", PASSWORD)
    browser = TestClient(api.app)
    csrf = _login(browser, "doc@example.org", PASSWORD).json()["csrf_token"]
    token = browser.cookies[SESSION_COOKIE]
    assert browser.post("/api/v1/auth/logout").status_code == 403  # CSRF applies to logout
    assert browser.post("/api/v1/auth/logout", headers={"X-CSRF-Token": csrf}).status_code == 204
    stale = TestClient(api.app, cookies={SESSION_COOKIE: token})
    assert stale.get("/api/v1/patients").status_code == 401
    # an expired session is refused (and removed)
    browser = TestClient(api.app)
    _login(browser, "doc@example.org", PASSWORD)
    with api.sessions() as db:
        db.execute(update(BrowserSession).values(expires_at=utcnow() - timedelta(seconds=1)))
        db.commit()
    assert browser.get("/api/v1/patients").status_code == 401
    assert api.count(BrowserSession) == 0


def test_inactive_user_cannot_log_in(api: Api) -> None:
    make_user(api.sessions, "gone@example.org", PASSWORD)
    with api.sessions() as db:
        db.execute(update(User).values(is_active=False))
        db.commit()
    assert _login(api.client, "gone@example.org", PASSWORD).status_code == 401


@pytest.mark.parametrize("url", ["/health", "/api/v1/patients"])
def test_security_headers(api: Api, url: str) -> None:
    r = api.client.get(url, headers={**api.headers, "X-Request-ID": "abc-123"})
    assert r.status_code == 200
    csp = r.headers["content-security-policy"]
    assert "frame-ancestors 'none'" in csp and "default-src 'self'" in csp
    assert "http:" not in csp and "https:" not in csp and "*" not in csp  # no external source
    assert r.headers["x-content-type-options"] == "nosniff"
    assert r.headers["referrer-policy"] == "no-referrer"
    assert r.headers["x-frame-options"] == "DENY"
    assert r.headers["x-request-id"] == "abc-123"
    assert "strict-transport-security" not in r.headers  # only behind HTTPS
    assert r.headers["cache-control"] == "no-store"

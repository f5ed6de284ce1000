"""The web application: ``create_app()`` wires settings, database, routers and security.

One exception handler turns every :class:`app.errors.AppError` into its HTTP
status and ``{"detail": "..."}``; a small ASGI middleware adds a request id and
the security headers (a Content-Security-Policy without any external source,
``nosniff``, no framing, no referrer, HSTS when the site is served over HTTPS).
The database schema is *not* migrated here: the ``serve``/``worker``/``admin``
commands migrate once at start-up, under a lock, before any web worker starts.
"""

from __future__ import annotations

import logging
import re
import uuid
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any
from urllib.parse import quote

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, RedirectResponse, Response
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import sessionmaker
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware

from app import db as app_db
from app.api import api_router
from app.audit import client_ip_var, request_id_var
from app.auth import OptionalCaller
from app.errors import AppError, InvalidRequestError, PayloadTooLargeError, RateLimitedError
from app.faults import check_health, storage_fault
from app.settings import Settings, get_settings
from app.storage import Storage
from app.web import router as web_router
from app.web.common import LoginRequired, PageForbidden, error_page, login_redirect
from app.web.error_pages import UNEXPECTED, prefers_html, request_id_of, server_error_page
from core.errors import BradyscopeError

log = logging.getLogger(__name__)

API_PREFIX = "/api/v1"
STATIC_DIR = Path(__file__).resolve().parent / "static"

# No external source anywhere: pages, scripts, styles, fonts and images come
# from this server. Inline <style>/style="" are allowed because matplotlib's
# inline SVG plots use them; scripts stay strictly same-origin.
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; font-src 'self'; connect-src 'self'; object-src 'none'; "
    "base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
_REQUEST_ID_RE = re.compile(r"^[A-Za-z0-9._-]{1,64}$")


class SecurityHeadersMiddleware:
    """Pure ASGI middleware: request id, security headers, no caching of patient data.

    Parameters
    ----------
    app : ASGIApp
    hsts : bool
        Send ``Strict-Transport-Security`` (only when the site is served over HTTPS).
    """

    def __init__(self, app: ASGIApp, *, hsts: bool) -> None:
        self.app = app
        self.hsts = hsts

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        incoming = ""
        for name, value in scope.get("headers", []):
            if name == b"x-request-id":
                incoming = value.decode("latin-1")
                break
        request_id = incoming if _REQUEST_ID_RE.match(incoming) else uuid.uuid4().hex
        scope.setdefault("state", {})["request_id"] = request_id
        token = request_id_var.set(request_id)
        client = scope.get("client")
        ip_token = client_ip_var.set(client[0][:45] if client else None)
        path: str = scope.get("path", "")
        is_static = path.startswith("/static/")

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                present = {name.lower() for name, _ in headers}

                def add(name: str, value: str) -> None:
                    key = name.lower().encode("latin-1")
                    if key not in present:
                        headers.append((key, value.encode("latin-1")))

                add("x-request-id", request_id)
                add("content-security-policy", CONTENT_SECURITY_POLICY)
                add("x-content-type-options", "nosniff")
                add("x-frame-options", "DENY")
                add("referrer-policy", "no-referrer")
                add("cross-origin-opener-policy", "same-origin")
                add("cross-origin-resource-policy", "same-origin")
                add("permissions-policy", "camera=(), microphone=(), geolocation=()")
                if not is_static:
                    add("cache-control", "no-store")
                if self.hsts:
                    add("strict-transport-security", "max-age=63072000; includeSubDomains")
                message["headers"] = headers
            await send(message)

        try:
            await self.app(scope, receive, send_with_headers)
        finally:
            request_id_var.reset(token)
            client_ip_var.reset(ip_token)


MAX_JSON_BODY_BYTES = 1024 * 1024
# The streamed upload routes enforce their own (per-file) limit in app.uploads.
_UPLOAD_ROUTE_RE = re.compile(r"^/api/v1/(sessions/[^/]+/trials|rigs/[^/]+/calibrations)/?$")


class BodyLimitMiddleware:
    """Refuse API request bodies above ``max_bytes`` (HTTP 413), except the upload routes.

    A declared ``Content-Length`` above the limit is answered at once, unread;
    a chunked body is cut off when it passes the limit.
    """

    def __init__(self, app: ASGIApp, *, max_bytes: int = MAX_JSON_BODY_BYTES) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path: str = scope.get("path", "")
        if (
            scope["type"] != "http"
            or not path.startswith(API_PREFIX + "/")
            or (scope.get("method") == "POST" and _UPLOAD_ROUTE_RE.match(path))
        ):
            await self.app(scope, receive, send)
            return
        detail = (
            f"The request body is larger than {self.max_bytes // 1024} KiB;"
            " send recordings to the upload routes."
        )
        for name, value in scope.get("headers", []):
            if name == b"content-length" and value.isdigit() and int(value) > self.max_bytes:
                await _error(413, detail)(scope, receive, send)
                return
        received = 0
        too_large = False
        replaced = False

        async def limited_receive() -> Message:
            nonlocal received, too_large
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    too_large = True
                    raise PayloadTooLargeError(detail)
            return message

        async def checked_send(message: Message) -> None:
            # FastAPI turns any failure while reading a body into its own 400;
            # when the cause was the size, answer 413 instead.
            nonlocal replaced
            if not too_large:
                await send(message)
            elif message["type"] == "http.response.start" and not replaced:
                replaced = True
                await _error(413, detail)(scope, receive, send)

        await self.app(scope, limited_receive, checked_send)


def _error(status: int, detail: str, **extra: Any) -> JSONResponse:
    headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
    return JSONResponse({"detail": detail, **extra}, status_code=status, headers=headers)


def _wants_html_page(request: Request) -> bool:
    """A browser navigating to a page (not an API call): answer 401 with the login page."""
    return (
        request.method in ("GET", "HEAD")
        and not request.url.path.startswith(API_PREFIX)
        and "text/html" in request.headers.get("accept", "")
    )


def _from_a_browser_page(request: Request) -> bool:
    """A browser's request of a page or a page's form (not the API, not a script's call)."""
    return prefers_html(request, api_prefix=API_PREFIX)


def _html_error(request: Request, status: int, message: str) -> Response:
    """The error page (the site's layout, no navigation) for a browser asking for a page;
    a server's fault's with the request id and the way back."""
    if status >= 500:
        return server_error_page(request, status, message)
    return error_page(request, None, status_code=status, message=message)


#: pydantic's error types for a body that is not a JSON object (a string, a list, a number)
_NOT_AN_OBJECT = frozenset({"model_attributes_type", "dict_type", "model_type"})


NO_SUCH_PAGE = "There is no page at this address: check it, or go back to the patient list."
"""Not the address itself: a crafted one would put its words on the page."""


def _page_refusals(app: FastAPI) -> None:
    """A page without a logged-in user redirects to the login; one the user's role does
    not open is a 403 page (both raised by the pages' ``PageUser``)."""

    @app.exception_handler(LoginRequired)
    async def login_required(request: Request, exc: LoginRequired) -> Response:
        return login_redirect(request)

    @app.exception_handler(PageForbidden)
    async def page_forbidden(request: Request, exc: PageForbidden) -> Response:
        return error_page(request, exc.user, status_code=403, message=str(exc))


def _validation_response(request: Request, exc: RequestValidationError) -> Response:
    """The answer to a request whose path, query or body does not validate: the 404 page
    for a browser at an address that is no page, 400 for a body that is not JSON, else
    422 naming the fields."""
    if _wants_html_page(request) and all(
        str(err.get("loc", ("",))[0]) == "path" for err in exc.errors()
    ):  # /trials/abc in the address bar: that page does not exist
        return _html_error(request, 404, NO_SUCH_PAGE)
    issues = [
        {
            "loc": [str(part) for part in err.get("loc", ())],
            "msg": str(err.get("msg", "")),
            "type": str(err.get("type", "")),
        }
        for err in exc.errors()
    ]
    if any(i["type"] == "json_invalid" for i in issues):  # unreadable, not invalid
        where = next(i for i in issues if i["type"] == "json_invalid")["loc"][1:]
        at = f" (at character {where[0]})" if where else ""
        return _error(
            400,
            f"The request body is not valid JSON{at}; send a JSON document (UTF-8) with "
            "Content-Type: application/json.",
        )
    if any(i["loc"] == ["body"] and i["type"] in _NOT_AN_OBJECT for i in issues):
        return _error(
            422,
            "The request body must be a JSON object, sent with Content-Type: application/json.",
            errors=issues,
        )
    parts = [f"{'.'.join(i['loc'][1:] or i['loc'])}: {i['msg']}" for i in issues[:5]]
    detail = "The request is invalid: " + "; ".join(parts) + "."
    return _error(422, detail, errors=issues)


#: The answers any API route with a body of this type can give, whatever the route: an
#: unreadable or oversized body, an upload the storage cannot take.
_BODY_ERRORS = {"application/json": (400, 413), "multipart/form-data": (400, 413, 415, 507)}


def _document_shared_errors(app: FastAPI) -> None:
    """Add to the OpenAPI document the statuses every API route shares, which the routes do
    not list one by one: 400 and 413 where a body is read, 415 and 507 for uploads, and 503
    (the database unreachable, the storage read-only) everywhere (docs/api.md says the
    document lists every status a route can answer)."""
    from app.api.responses import errors

    default = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = default()
        ref = {"$ref": "#/components/schemas/ErrorResponse"}
        for path, operations in schema.get("paths", {}).items():
            if not path.startswith(API_PREFIX):
                continue
            for op in operations.values():
                content = (op.get("requestBody") or {}).get("content", {})
                statuses = {503} | {s for t in content for s in _BODY_ERRORS.get(t, ())}
                for status, entry in errors(*sorted(statuses)).items():
                    op["responses"].setdefault(
                        str(status),
                        {
                            "description": entry["description"],
                            "content": {"application/json": {"schema": ref}},
                        },
                    )
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


PUBLIC_API_PATHS = frozenset({API_PREFIX + "/auth/login"})
"""The API's routes that need no credentials (docs/api.md, Authentication)."""

BEARER_SCHEME = {
    "type": "http",
    "scheme": "bearer",
    "bearerFormat": "bsk_<12 hex>_<43 characters>",
    "description": "An API key, created by an administrator with `bradyscope admin"
    " create-api-key NAME [--scopes ...]`. (The browser pages send their session cookie"
    " and, on changes, its X-CSRF-Token instead.)",
}


def _document_security(app: FastAPI) -> None:
    """Add to the OpenAPI document how to authenticate: the Bearer scheme, required by every
    API route but the login (so that generated clients send the key)."""
    default = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = default()
        schema.setdefault("components", {}).setdefault("securitySchemes", {})["bearerAuth"] = (
            BEARER_SCHEME
        )
        for path, operations in schema.get("paths", {}).items():
            if path.startswith(API_PREFIX) and path not in PUBLIC_API_PATHS:
                for op in operations.values():
                    op["security"] = [{"bearerAuth": []}]
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def _install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(AppError)
    async def app_error(request: Request, exc: AppError) -> Response:
        status = int(getattr(exc, "http_status", 400))
        if status == 401 and _wants_html_page(request):
            target = quote(
                request.url.path + (f"?{request.url.query}" if request.url.query else "")
            )
            return RedirectResponse(f"/login?next={target}", status_code=303)
        if status >= 500:
            log.error("request %s failed: %s", request_id_var.get(), exc, exc_info=exc)
        message = str(exc) or type(exc).__name__
        # The invalid fields, as a validation error names them (docs/api.md, Errors).
        issues = exc.issues if isinstance(exc, InvalidRequestError) else []
        response = (  # a page, or a form posted without the page's script: the error page
            _html_error(request, status, message)
            if _from_a_browser_page(request)
            else _error(status, message, **({"errors": issues} if issues else {}))
        )
        retry_after = getattr(exc, "retry_after_s", None)
        if isinstance(exc, RateLimitedError) and retry_after is not None:
            response.headers["Retry-After"] = str(int(retry_after))
        return response

    @app.exception_handler(BradyscopeError)
    async def domain_error(request: Request, exc: BradyscopeError) -> JSONResponse:
        return _error(422, str(exc))

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> Response:
        return _validation_response(request, exc)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        if exc.status_code == 404 and _wants_html_page(request):
            return _html_error(request, 404, NO_SUCH_PAGE)
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        if exc.status_code == 400 and detail == "There was an error parsing the body":
            detail = "The request body could not be read; send valid JSON (UTF-8) or a valid form."
        response = _error(exc.status_code, detail)
        for name, value in (exc.headers or {}).items():
            response.headers[name] = value
        return response

    @app.exception_handler(RecursionError)
    async def too_deep(request: Request, exc: RecursionError) -> JSONResponse:
        # Python's JSON parser recurses once per nesting level: 50,000 '[' end here.
        return _error(
            400, "The request body is nested too deeply to be read; send a flat JSON document."
        )

    async def storage_or_unexpected(request: Request, exc: Exception) -> Response:
        fault = storage_fault(exc)
        if fault is None:
            return await unexpected(request, exc)
        log.error("request %s failed on storage: %s", request_id_var.get(), exc)
        return await app_error(request, fault)

    app.add_exception_handler(OSError, storage_or_unexpected)
    app.add_exception_handler(DBAPIError, storage_or_unexpected)

    @app.exception_handler(Exception)
    async def unexpected(request: Request, exc: Exception) -> Response:
        # Runs in Starlette's outermost middleware, after ours: read the id from the scope,
        # and add the headers our middleware adds to every other answer.
        request_id = request_id_of(request)
        log.exception("unhandled error in request %s", request_id)
        response = (
            server_error_page(request, 500, UNEXPECTED)
            if _from_a_browser_page(request)
            else _error(500, f"Internal error; quote request id {request_id} to the administrator.")
        )
        response.headers.update(
            {"x-request-id": request_id, "content-security-policy": CONTENT_SECURITY_POLICY,
             "x-content-type-options": "nosniff", "x-frame-options": "DENY",
             "referrer-policy": "no-referrer", "cache-control": "no-store"}
        )  # fmt: skip
        return response


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the bradyscope web application.

    Parameters
    ----------
    settings : app.settings.Settings, optional
        Defaults to the settings read from the ``BRADYSCOPE_*`` environment.

    Returns
    -------
    FastAPI
        With the REST API under ``/api/v1``, the browser pages, ``/static`` and
        ``/health``. The database must already be migrated.
    """
    if settings is None:
        settings = get_settings()
    engine = app_db.make_engine(settings)
    session_factory = sessionmaker(bind=engine, expire_on_commit=False)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield
        engine.dispose()

    app = FastAPI(
        title="bradyscope",
        version="1",
        summary="3D finger-tapping measurement: REST API for hospital systems.",
        description=(
            "Authenticate with `Authorization: Bearer <api key>` (keys are created with"
            ' `bradyscope admin create-api-key`). Errors are `{"detail": "..."}` with a 4xx'
            " status. Every read, change or export of patient data is audited."
        ),
        docs_url=None,  # Swagger UI loads from a CDN, which the CSP forbids
        redoc_url=None,
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.engine = engine
    app.state.session_factory = session_factory
    app.state.storage = Storage.from_settings(settings)

    _install_error_handlers(app)
    app.add_middleware(BodyLimitMiddleware)
    app.add_middleware(SecurityHeadersMiddleware, hsts=settings.secure_cookies)
    if settings.trusted_proxy_list:
        # Outermost: the client address every layer sees (throttle, audit) is the one the
        # trusted proxy forwarded. From any other peer, X-Forwarded-* headers are ignored.
        app.add_middleware(ProxyHeadersMiddleware, trusted_hosts=settings.trusted_proxy_list)

    app.include_router(api_router, prefix=API_PREFIX)

    @app.get(
        "/health",
        tags=["service"],
        summary="The database answers and the data directory takes a file (no authentication)",
        responses={503: {"description": "A check failed; `detail` says which and why."}},
    )
    def health(caller: OptionalCaller) -> JSONResponse:
        result = check_health(engine, settings.data_dir)
        document = result.as_document(free_bytes=caller is not None)
        return JSONResponse(document, status_code=200 if result.ok else 503)

    @app.get("/favicon.ico", include_in_schema=False)
    def favicon() -> Response:
        # Standalone pages (the HTML reports) link no icon: answer browsers' implicit request.
        return Response(status_code=204)

    app.include_router(web_router)
    _document_shared_errors(app)
    _document_security(app)

    _page_refusals(app)
    if STATIC_DIR.is_dir():
        app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    return app

"""The neurologist's browser pages (mounted by ``app.main.create_app``).

Server-rendered Jinja2 pages (``templates/``) with a little JavaScript
(``app/static/app.js``: upload progress, job polling). Every page needs a
logged-in browser session except ``/login``; every form carries the session's
CSRF token. The pages are left out of the OpenAPI schema (it documents the
REST API for hospital systems).
"""

from fastapi import APIRouter

from app.web import (
    admin,
    auth_pages,
    capture,
    patients,
    record,
    recordings,
    results,
    review,
    rigs,
    signing,
)

router = APIRouter(include_in_schema=False)
for _module in (
    auth_pages,
    capture,
    patients,
    record,
    recordings,
    results,
    review,
    rigs,
    signing,
    admin,
):
    router.include_router(_module.router)

__all__ = ["router"]

"""The REST API for hospital systems, mounted at ``/api/v1`` (INTERFACES.md).

Thin routes: each parses its input, calls one use case in :mod:`app.services`,
and shapes the answer. Every status a route can answer is listed in its
``responses=`` so that the OpenAPI document is complete.
"""

from fastapi import APIRouter

from app.api.audit import router as audit_router
from app.api.auth import router as auth_router
from app.api.patients import router as patients_router
from app.api.results import router as results_router
from app.api.revisions import router as revisions_router
from app.api.rigs import router as rigs_router
from app.api.sessions import router as sessions_router
from app.api.trials import router as trials_router

api_router = APIRouter()
for _router in (
    auth_router,
    patients_router,
    rigs_router,
    sessions_router,
    trials_router,
    results_router,
    revisions_router,
    audit_router,
):
    api_router.include_router(_router)

__all__ = ["api_router"]

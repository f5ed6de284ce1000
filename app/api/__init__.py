"""The REST API for hospital systems, mounted at ``/api/v1`` (INTERFACES.md).

Thin routes: each parses its input, calls one use case in :mod:`app.services`,
and shapes the answer. Every status a route can answer is listed in its
``responses=`` so that the OpenAPI document is complete.
"""

from fastapi import APIRouter

from app.api import auth, patients, results, rigs, sessions, trials

api_router = APIRouter()
for module in (auth, patients, rigs, sessions, trials, results):
    api_router.include_router(module.router)

__all__ = ["api_router"]

"""The administrator's page of the audit trail (``/admin/audit``), with filters and pages.

Only users holding ``audit:read`` (admins) see it; anyone else gets 403, and
the refusal is audited like an API refusal. Reading the page is audited too.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import HTMLResponse

from app.apikeys import AUDIT_READ
from app.audit import audit_failure
from app.auth import SessionDep
from app.errors import AppError
from app.services import audit_log
from app.web.common import AnyPageUser, error_page, render, status_of

router = APIRouter()

PAGE_SIZE = 50


def _time(text: str | None, name: str) -> datetime | None:
    return audit_log.parse_time(text, name) if text else None


@router.get("/admin/audit", response_class=HTMLResponse)
def audit_page(
    request: Request,
    db: SessionDep,
    user: AnyPageUser,
    patient_id: Annotated[str | None, Query(max_length=20)] = None,
    actor: Annotated[str | None, Query(max_length=80)] = None,
    since: Annotated[str | None, Query(max_length=40)] = None,
    until: Annotated[str | None, Query(max_length=40)] = None,
    page: Annotated[int, Query(ge=1, le=100_000)] = 1,
) -> HTMLResponse:
    if not user.has_scope(AUDIT_READ):
        audit_failure(db, user, "access", "route", "/admin/audit", outcome="denied")
        return error_page(
            request, user, status_code=403, message="Only administrators can read the audit trail."
        )
    form = {"patient_id": patient_id or "", "actor": actor or "", "since": since or "",
            "until": until or ""}  # fmt: skip
    try:
        pid = int(patient_id) if patient_id else None
        f = audit_log.make_filter(
            patient_id=pid, actor=actor, since=_time(since, "From"), until=_time(until, "Until")
        )
    except ValueError:
        return error_page(request, user, status_code=422, message="Patient id must be a number.")
    except AppError as exc:
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    events, total = audit_log.list_events(
        db, user, f, limit=PAGE_SIZE, offset=(page - 1) * PAGE_SIZE
    )
    pages = max(1, -(-total // PAGE_SIZE))
    return render(
        request,
        "audit.html",
        user,
        active="audit",
        title="Audit trail",
        events=events,
        total=total,
        page=page,
        pages=pages,
        form=form,
    )

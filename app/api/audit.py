"""``/audit``: the audit trail for hospital systems and auditors (scope ``audit:read``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query

from app.actors import Actor
from app.api.responses import AUTH, Limit, Offset, errors, page
from app.apikeys import AUDIT_READ
from app.auth import SessionDep, require_scope
from app.schemas import MAX_ID, AuditEventRead, Page, UtcDateTime
from app.services import audit_log

router = APIRouter(prefix="/audit", tags=["audit"])

AuditReader = Annotated[Actor, Depends(require_scope(AUDIT_READ))]


@router.get(
    "",
    response_model=Page[AuditEventRead],
    responses=errors(*AUTH),
    summary="Read the audit trail, newest first (filters by patient, actor and time)",
)
def list_audit_events(
    actor: AuditReader,
    db: SessionDep,
    patient_id: Annotated[
        int | None, Query(ge=1, le=MAX_ID, description="Only events about this patient.")
    ] = None,
    actor_filter: Annotated[
        str | None,
        Query(
            alias="actor",
            max_length=80,
            description="user:ID, api_client:ID, system[:NAME] or anonymous.",
        ),
    ] = None,
    since: Annotated[
        UtcDateTime | None, Query(description="At or after this time (ISO 8601; UTC if no zone).")
    ] = None,
    until: Annotated[UtcDateTime | None, Query(description="Before this time.")] = None,
    limit: Limit = 50,
    offset: Offset = 0,
) -> Page[AuditEventRead]:
    f = audit_log.make_filter(patient_id=patient_id, actor=actor_filter, since=since, until=until)
    items, total = audit_log.list_events(db, actor, f, limit=limit, offset=offset)
    return page(AuditEventRead, items, total, limit=limit, offset=offset)

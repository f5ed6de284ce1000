"""``/audit``: the audit trail for hospital systems and auditors (scope ``audit:read``)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request
from pydantic import Field

from app.actors import Actor
from app.api.responses import AUTH, Limit, Offset, errors
from app.apikeys import AUDIT_READ
from app.audit import audit_values_shown
from app.auth import SessionDep, require_scope
from app.schemas import MAX_ID, AuditEventRead, Page, UtcDateTime
from app.services import audit_log

router = APIRouter(prefix="/audit", tags=["audit"])

AuditReader = Annotated[Actor, Depends(require_scope(AUDIT_READ))]


MAX_SEQ = 2**63 - 1  # a BigInteger


class AuditItem(AuditEventRead):
    """An event of the trail, with what it concerns beyond its columns."""

    details: dict[str, Any] | None = Field(
        default=None,
        description="Sealed with the event: an update's changed fields (fields) and the"
        " digest of their values (values_sha256); the patients a list returned, or"
        " whose kept values a read of the trail showed (patient_ids, on a read of"
        " field_changes). Identifiers and names only.",
    )
    changes: dict[str, list[Any]] | None = Field(
        default=None,
        description="An update's previous and new value of each changed field, as"
        " {field: [previous, new]}: for a reader who also holds patients:read (the values"
        " are the patient's data; the read is then recorded as a read of field_changes"
        " naming each patient whose values it shows); null for others, and once the"
        " patient was erased.",
    )


class AuditPage(Page[AuditItem]):
    """A page of the trail; follow ``next`` for the following one (stable while events
    are added: it names the sequence number to continue from)."""

    next: str | None = Field(
        default=None,
        description="The address (path and query) of the next page, by sequence number;"
        " null after the last page.",
        examples=["/api/v1/audit?limit=50&before_seq=1234"],
    )


def _link(request: Request, cursor: dict[str, int] | None) -> str | None:
    if cursor is None:
        return None
    url = request.url.remove_query_params(["offset", "before_seq", "after_seq"])
    url = url.include_query_params(**cursor)
    return f"{url.path}?{url.query}"


@router.get(
    "",
    response_model=AuditPage,
    responses=errors(*AUTH),
    summary="Read the audit trail, newest first (filters by patient, actor and time)",
)
def list_audit_events(
    actor: AuditReader,
    db: SessionDep,
    request: Request,
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
    before_seq: Annotated[
        int | None,
        Query(
            ge=1,
            le=MAX_SEQ,
            description="Only events numbered below this (older), newest first: the next"
            " page of a page whose last item has this seq.",
        ),
    ] = None,
    after_seq: Annotated[
        int | None,
        Query(
            ge=0,
            le=MAX_SEQ,
            description="Only events numbered above this (newer), oldest first: to read"
            " what was added since the event with this seq.",
        ),
    ] = None,
    limit: Limit = 50,
    offset: Offset = 0,
) -> AuditPage:
    f = audit_log.make_filter(patient_id=patient_id, actor=actor_filter, since=since, until=until)
    trail = audit_log.read_trail(
        db, actor, f, limit=limit, offset=offset, before_seq=before_seq, after_seq=after_seq
    )
    items = [AuditItem.model_validate(e) for e in trail.items]
    kept = audit_log.changes_for(db, actor, trail.items)
    audit_values_shown(db, actor, trail.items, kept)  # whose values these are, on record
    for item in items:
        item.changes = kept.get(item.id)
    return AuditPage(
        items=items,
        total=trail.total,
        limit=limit,
        offset=offset,
        next=_link(request, trail.next),
    )

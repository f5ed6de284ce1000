"""Reading the audit trail: the API (``GET /audit``), the admin page and ``export-audit``.

Reading the trail is itself audited (``list`` of ``audit``, with the patient
filter as its patient), so that who looked at whose history is on record too.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import Select, select
from sqlalchemy.orm import Session

from app.audit import AnyActor, audit
from app.errors import InvalidRequestError
from app.models import ACTOR_TYPES, AuditEvent
from app.services.common import paginate

_ACTOR_RE = re.compile(r"^(user|api_client|system|anonymous)(?::(.{1,64}))?$")


@dataclass(frozen=True)
class AuditFilter:
    """Which events to read; every field is optional (None: no condition)."""

    patient_id: int | None = None
    actor_type: str | None = None
    actor_id: str | None = None
    since: datetime | None = None
    until: datetime | None = None


def parse_actor(text: str | None) -> tuple[str | None, str | None]:
    """``"user:3"`` -> ``("user", "3")``; ``"system"`` -> ``("system", None)``; None -> no filter."""
    if text is None or text == "":
        return None, None
    match = _ACTOR_RE.match(text.strip())
    if match is None:
        raise InvalidRequestError(
            f"actor must be one of {', '.join(ACTOR_TYPES)}, optionally with ':id'"
            " (e.g. user:3, api_client:2, system:cli:root)."
        )
    return match.group(1), match.group(2)


def parse_time(text: str, name: str) -> datetime:
    """An ISO 8601 date or time from a user (UTC when it has no zone)."""
    try:
        value = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise InvalidRequestError(
            f"{name} must be an ISO 8601 date or time such as 2026-01-31 or"
            f" 2026-01-31T08:00:00Z, not {text[:40]!r}."
        ) from None
    return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


def make_filter(
    *,
    patient_id: int | None = None,
    actor: str | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
) -> AuditFilter:
    actor_type, actor_id = parse_actor(actor)
    if since is not None and until is not None and until < since:
        raise InvalidRequestError("until is before since; swap them.")
    return AuditFilter(patient_id, actor_type, actor_id, since, until)


def _query(f: AuditFilter) -> Select[Any]:
    query = select(AuditEvent)
    if f.patient_id is not None:
        query = query.where(AuditEvent.patient_id == f.patient_id)
    if f.actor_type is not None:
        query = query.where(AuditEvent.actor_type == f.actor_type)
    if f.actor_id is not None:
        query = query.where(AuditEvent.actor_id == f.actor_id)
    if f.since is not None:
        query = query.where(AuditEvent.at >= f.since)
    if f.until is not None:
        query = query.where(AuditEvent.at < f.until)
    return query


def list_events(
    db: Session, actor: AnyActor, f: AuditFilter, *, limit: int, offset: int
) -> tuple[list[AuditEvent], int]:
    """One page of events, newest first, and how many match; audited, committed."""
    items, total = paginate(db, _query(f), AuditEvent.id.desc(), limit=limit, offset=offset)
    audit(db, actor, "list", "audit", None, f.patient_id)
    db.commit()
    return items, total


def iter_events(db: Session, f: AuditFilter) -> Iterator[AuditEvent]:
    """Every matching event, oldest first (for the export), read in batches."""
    query = _query(f).order_by(AuditEvent.id).execution_options(yield_per=2000)
    yield from db.scalars(query)


def as_document(event: AuditEvent) -> dict[str, Any]:
    """One event as the JSON object of the export and the API."""
    return {
        "id": event.id,
        "seq": event.seq,
        "at": event.at.isoformat().replace("+00:00", "Z"),
        "actor_type": event.actor_type,
        "actor_id": event.actor_id,
        "action": event.action,
        "resource_type": event.resource_type,
        "resource_id": event.resource_id,
        "patient_id": event.patient_id,
        "outcome": event.outcome,
        "ip": event.ip,
        "request_id": event.request_id,
        "hash": event.hash,
    }

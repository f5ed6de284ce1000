"""Reading the audit trail: the API (``GET /audit``), the admin page and ``export-audit``.

Reading the trail is itself audited (``list`` of ``audit``, with the patient
filter as its patient), so that who looked at whose history is on record too.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import Select, func, or_, select
from sqlalchemy.orm import Session

from app.actors import Actor
from app.audit import AnyActor, audit
from app.errors import InvalidRequestError
from app.models import ACTOR_TYPES, AuditEvent, AuditEventPatient
from app.services import changes
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
            " (e.g. user:3, api_client:2, system:cli:root).",
            field="actor",
            where="query",
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
        raise InvalidRequestError("until is before since; swap them.", field="until", where="query")
    return AuditFilter(patient_id, actor_type, actor_id, since, until)


def _query(f: AuditFilter) -> Select[Any]:
    query = select(AuditEvent)
    if f.patient_id is not None:  # its own events, and the lists that returned it
        listed = select(AuditEventPatient.event_id).where(
            AuditEventPatient.patient_id == f.patient_id
        )
        query = query.where(or_(AuditEvent.patient_id == f.patient_id, AuditEvent.id.in_(listed)))
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


@dataclass(frozen=True)
class TrailPage:
    """A page of the trail read by sequence number, and where the next page starts.

    ``next`` holds the query parameters of the next page (``before_seq`` or ``after_seq``,
    and ``offset`` among the events older than the chain), None after the last page.
    """

    items: list[AuditEvent]
    total: int
    next: dict[str, int] | None


def read_trail(
    db: Session,
    actor: AnyActor,
    f: AuditFilter,
    *,
    limit: int,
    offset: int = 0,
    before_seq: int | None = None,
    after_seq: int | None = None,
) -> TrailPage:
    """One page of events by their number ``seq``, audited, committed: newest first and
    older than ``before_seq`` (the first page without it), or oldest first and newer than
    ``after_seq``. A page read so does not move when events are added meanwhile (each read
    of the trail adds one). ``total`` counts the events matching the filter and the cursor.

    Events from before the chain existed (revision 0010) have no number; they are older
    than every numbered one, come after them newest first and never after ``after_seq``.
    """
    if before_seq is not None and after_seq is not None:
        raise InvalidRequestError(
            "Give before_seq (older events, newest first) or after_seq (newer events, oldest"
            " first), not both.",
            field="after_seq",
            where="query",
        )
    query = _query(f)
    if after_seq is not None:
        query = query.where(AuditEvent.seq > after_seq)
        order: tuple[Any, ...] = (AuditEvent.seq.asc(),)
    else:
        if before_seq is not None:
            query = query.where(or_(AuditEvent.seq < before_seq, AuditEvent.seq.is_(None)))
        order = (AuditEvent.seq.is_(None), AuditEvent.seq.desc(), AuditEvent.id.desc())
    items, total = paginate(db, query, *order, limit=limit, offset=offset)
    following = None
    if offset + len(items) < total:
        following = _next_cursor(db, query, items[-1], offset + len(items), after_seq is not None)
    audit(db, actor, "list", "audit", None, f.patient_id)
    db.commit()
    return TrailPage(items, total, following)


def _next_cursor(
    db: Session, query: Select[Any], last: AuditEvent, read: int, forward: bool
) -> dict[str, int]:
    """Where the page after ``last`` starts (``read``: events of ``query`` read so far)."""
    if last.seq is not None:
        return {"after_seq" if forward else "before_seq": int(last.seq)}
    # Among the unnumbered events, which no new event joins: an offset is stable there.
    numbered = select(func.count()).select_from(query.where(AuditEvent.seq.is_not(None)).subquery())
    return {"before_seq": 1, "offset": read - int(db.scalar(numbered) or 0)}


VALUES_SCOPE = "patients:read"
"""Who also reads the previous and new values of an update: they are the patient's data."""


def changes_for(
    db: Session, reader: Actor, events: Iterable[AuditEvent]
) -> dict[int, changes.Changed]:
    """The previous and new values of the updates among ``events``, by event id, for a
    reader who holds ``patients:read``; none for any other reader (an auditor), and none
    for an erased patient's update (:func:`app.services.changes.changes_of`). The API
    (``GET /audit``'s ``changes``) and the page ``/admin/audit`` both ask here."""
    if not reader.has_scope(VALUES_SCOPE):
        return {}
    return changes.changes_of(db, [e.id for e in events if e.action == "update"])


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
        "details": event.details,
    }

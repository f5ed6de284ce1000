"""``verify-audit`` beyond the chain: the rows kept beside the trail, against what it sealed.

Two tables hold what an event concerns outside the hash chain, and the event seals a
summary of them in its ``details``, which :mod:`app.chain` checks with the rest:

- ``field_changes``: an update's previous and new values (:mod:`app.services.changes`).
  The event seals ``values_sha256``, the digest of the row's nonce and values, so the
  row must still give that digest; and an event naming values must still have its row,
  unless its patient was erased (the erasure removes the row by design, and the digest
  left in the trail then names nothing). A row belongs to its event's patient, or an
  erasure of that patient would miss it.
- ``audit_event_patients``: the patients a list returned, or whose kept values a read of
  the trail showed, the index the trail's patient filter reads
  (:func:`app.audit.audit_listed`, :func:`app.audit.audit_values_shown`). The event seals
  the same ids as ``patient_ids``: a row deleted hides the listing from that patient's
  trail, a row added shows a listing that did not happen.

The tables are read in windows of event ids, so memory stays bounded by a window
whatever the trail's length.
"""

from __future__ import annotations

import hmac
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.chain import ChainReport, verify_chain
from app.models import AuditEvent, AuditEventPatient, FieldChange, Patient
from app.services.changes import values_sha256

WINDOW = 1000
"""Event ids read at a time."""


@dataclass(frozen=True)
class _Event:
    id: int
    seq: int | None
    patient_id: int | None
    details: dict[str, Any]
    patient_erased_at: datetime | None

    @property
    def name(self) -> str:
        return f"event {self.seq} (id {self.id})" if self.seq is not None else f"event id {self.id}"


def verify_trail(db: Session, *, max_problems: int = 20) -> ChainReport:
    """:func:`app.chain.verify_chain`, then the rows beside the trail against its events.

    Every problem is a sentence naming the event (its number, and its id); at most
    ``max_problems`` in all.
    """
    report = verify_chain(db, max_problems=max_problems)
    for text in _problems_beside(db):
        if len(report.problems) >= max_problems:
            break
        report.problems.append(text)
    return report


def _problems_beside(db: Session) -> Iterator[str]:
    top = max(
        db.scalar(select(func.max(AuditEvent.id))) or 0,
        db.scalar(select(func.max(FieldChange.event_id))) or 0,
        db.scalar(select(func.max(AuditEventPatient.event_id))) or 0,
    )
    for low in range(0, top + 1, WINDOW):
        events = _events_with_details(db, low, low + WINDOW)
        yield from _check_field_changes(db, events, low, low + WINDOW)
        yield from _check_listed(db, events, low, low + WINDOW)


def _events_with_details(db: Session, low: int, high: int) -> dict[int, _Event]:
    rows = db.execute(
        select(
            AuditEvent.id,
            AuditEvent.seq,
            AuditEvent.patient_id,
            AuditEvent.details,
            Patient.erased_at,
        )
        .outerjoin(Patient, Patient.id == AuditEvent.patient_id)
        .where(AuditEvent.id >= low, AuditEvent.id < high, AuditEvent.details.is_not(None))
    )
    return {
        row.id: _Event(row.id, row.seq, row.patient_id, row.details, row.erased_at)
        for row in rows
        if isinstance(row.details, dict)  # a JSON null reads as None
    }


def _check_field_changes(
    db: Session, events: dict[int, _Event], low: int, high: int
) -> Iterator[str]:
    rows = db.execute(
        select(FieldChange)
        .where(FieldChange.event_id >= low, FieldChange.event_id < high)
        .order_by(FieldChange.id)
    ).scalars()
    kept: set[int] = set()
    for row in rows:
        event = events.get(row.event_id)
        sealed = event.details.get("values_sha256") if event is not None else None
        if event is None or not isinstance(sealed, str):
            what = "names no changed values" if event is not None else "has no sealed details"
            yield (
                f"field_changes row {row.id} belongs to event id {row.event_id}, which {what}:"
                " the row was added, or moved from another event."
            )
            continue
        if row.event_id in kept:
            yield f"{event.name} has a second field_changes row ({row.id}): it was added."
            continue
        kept.add(row.event_id)
        if not hmac.compare_digest(values_sha256(row.nonce, row.changes), sealed):
            yield (
                f"the values kept for {event.name} (field_changes row {row.id}) do not match"
                " the digest it sealed: they were altered."
            )
        elif row.patient_id != event.patient_id:
            yield (
                f"the values kept for {event.name} (field_changes row {row.id}) are filed under"
                f" patient {row.patient_id}, not its patient {event.patient_id}: erasing"
                " the patient would leave them behind."
            )
        elif event.patient_erased_at is not None:
            yield (
                f"the values kept for {event.name} (field_changes row {row.id}) outlived the"
                f" erasure of patient {event.patient_id}: erase them."
            )
    for event in events.values():
        if (
            isinstance(event.details.get("values_sha256"), str)
            and event.id not in kept
            and event.patient_erased_at is None
        ):
            fields = ", ".join(map(str, event.details.get("fields") or [])) or "?"
            yield (
                f"the values {event.name} changed ({fields}) are gone, but patient"
                f" {event.patient_id} was not erased: its field_changes row was deleted."
            )


def _check_listed(db: Session, events: dict[int, _Event], low: int, high: int) -> Iterator[str]:
    listed: dict[int, set[int]] = {}
    for event_id, patient_id in db.execute(
        select(AuditEventPatient.event_id, AuditEventPatient.patient_id).where(
            AuditEventPatient.event_id >= low, AuditEventPatient.event_id < high
        )
    ):
        listed.setdefault(event_id, set()).add(patient_id)
    for event_id, patient_ids in sorted(listed.items()):
        event = events.get(event_id)
        if event is None or not isinstance(event.details.get("patient_ids"), list):
            what = "returned no list of patients" if event is not None else "has no sealed details"
            yield (
                f"audit_event_patients credits event id {event_id}, which {what}, with patients"
                f" {_ids(patient_ids)}: the rows were added, or moved from another event."
            )
    for event in sorted(events.values(), key=lambda e: e.id):
        sealed = event.details.get("patient_ids")
        if not isinstance(sealed, list):
            continue
        got = listed.get(event.id, set())
        missing, extra = set(sealed) - got, got - set(sealed)
        if missing:
            yield (
                f"{event.name} returned patients {_ids(missing)}, but audit_event_patients lacks"
                " them (rows deleted): their trails no longer show the listing."
            )
        if extra:
            yield (
                f"audit_event_patients credits {event.name} with patients {_ids(extra)}, which"
                " it did not return: the rows were added."
            )


def _ids(ids: set[int]) -> str:
    ordered = sorted(ids)
    shown = ", ".join(map(str, ordered[:10]))
    return shown if len(ordered) <= 10 else f"{shown} and {len(ordered) - 10} more"


__all__ = ["verify_trail"]

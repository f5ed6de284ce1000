"""What an update changed, field by field: named in the audit trail, kept for the patient.

An update of a patient, a session or a trial (its rating) is audited as one
``update`` event whose ``details`` name the fields that changed and seal the
SHA-256 of their values; the previous and new values themselves are kept in a
:class:`app.models.FieldChange` row beside the event. The split keeps the
trail's promise (identifiers and verbs, no clinical values: an auditor reads
it, and it outlives an erasure) while every change stays answerable: who
changed what, when, from which value to which. The values belong to the
patient and go with their erasure; the digest left in the trail is salted by
the row's nonce, so it tells nothing once the row is gone.
"""

from __future__ import annotations

import hashlib
import json
import secrets
from collections.abc import Iterable, Mapping
from datetime import date, datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.audit import AnyActor, audit
from app.models import AuditEvent, FieldChange

Changed = dict[str, list[Any]]
"""``{field: [previous, new]}`` of the fields an update really changed."""


def _plain(value: Any) -> Any:
    """A value as JSON holds it (dates as ISO 8601)."""
    if isinstance(value, datetime | date):
        return value.isoformat()
    return value


def changed_fields(
    row: Any, changes: Mapping[str, Any], *, columns: Mapping[str, str] | None = None
) -> Changed:
    """Set ``changes`` on ``row`` and return those whose value differs from the row's.

    ``columns`` maps an API field to the row's attribute when they are named apart
    (``comment`` -> ``rating_comment``). Fields sent with the value they hold already
    are not changes.
    """
    out: Changed = {}
    for name, value in changes.items():
        attribute = (columns or {}).get(name, name)
        before = getattr(row, attribute)
        if before != value:
            out[name] = [_plain(before), _plain(value)]
            setattr(row, attribute, value)
    return out


def values_sha256(nonce: str, changed: Changed) -> str:
    """The digest an update's event seals: SHA-256 of the nonce and the canonical values."""
    payload = json.dumps(changed, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(f"{nonce}\n{payload}".encode()).hexdigest()


def audit_update(
    db: Session,
    actor: AnyActor,
    resource_type: str,
    resource_id: int,
    patient_id: int,
    changed: Changed,
) -> AuditEvent:
    """Audit an update (in ``db``'s transaction): the event names the changed fields (none:
    an update that changed nothing), a :class:`FieldChange` keeps their values."""
    if not changed:
        return audit(db, actor, "update", resource_type, resource_id, patient_id,
                     details={"fields": []})  # fmt: skip
    nonce = secrets.token_hex(16)
    details = {"fields": sorted(changed), "values_sha256": values_sha256(nonce, changed)}
    event = audit(db, actor, "update", resource_type, resource_id, patient_id, details=details)
    db.add(FieldChange(event=event, patient_id=patient_id, changes=changed, nonce=nonce))
    return event


def changes_of(db: Session, event_ids: Iterable[int]) -> dict[int, Changed]:
    """The kept values of the updates among ``event_ids`` (none for an erased patient's),
    each checked against its event's sealed digest: a row altered since is left out."""
    ids = list(event_ids)
    if not ids:
        return {}
    out: dict[int, Changed] = {}
    rows = db.execute(
        select(FieldChange, AuditEvent.details)
        .join(AuditEvent, AuditEvent.id == FieldChange.event_id)
        .where(FieldChange.event_id.in_(ids))
    ).all()
    for row, details in rows:
        sealed = (details or {}).get("values_sha256")
        if sealed == values_sha256(row.nonce, row.changes):
            out[row.event_id] = row.changes
    return out

"""The audit trail: who read, changed or exported which patient's data, when, with what outcome.

Every use case that touches patient data calls :func:`audit` on the session of
its own unit of work, so the event is committed together with the change (or
read) it describes, and rolled back with it. A refused or failed request is
recorded by :func:`audit_failure`, which rolls the request's pending changes
back and commits the event alone.

Audit rows hold identifiers and verbs only, never clinical values (no
metrics, notes, ratings, names); ``app.models.AuditEvent`` has no foreign keys
so that the trail outlives what it describes. An update's event names the
fields it changed (``details``); their previous and new values are kept beside
it in ``field_changes`` (:mod:`app.services.changes`), which belongs to the
patient and is erased with them, and the event seals their digest. The table is append-only: no
code path updates or deletes its rows, and every event is numbered and sealed
into a keyed hash chain (:mod:`app.chain`) that ``bradyscope admin
verify-audit`` checks.
"""

from __future__ import annotations

from collections.abc import Container, Iterable
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any, Literal

from sqlalchemy.orm import Session

from app import chain
from app.actors import Actor
from app.models import ACTOR_ANONYMOUS, AuditEvent, AuditEventPatient, utcnow

# Set per request by ``app.main.SecurityHeadersMiddleware``.
request_id_var: ContextVar[str | None] = ContextVar("request_id", default=None)
client_ip_var: ContextVar[str | None] = ContextVar("client_ip", default=None)

Action = Literal[
    "list", "read", "create", "update", "delete", "export", "login", "logout", "access"
]
Outcome = Literal["success", "denied", "not_found", "invalid", "error", "throttled"]

ANONYMOUS: Literal["anonymous"] = ACTOR_ANONYMOUS
"""Pass as the actor when nobody is authenticated (e.g. a failed login); no ``actor_id``."""


@dataclass(frozen=True)
class SystemActor:
    """The system acting for a named operator (e.g. ``cli:root`` for an ``admin`` command).

    Recorded with the actor type ``system`` and ``name`` as its ``actor_id``.
    """

    name: str


AnyActor = Actor | SystemActor | Literal["anonymous"] | None


def _event(
    actor: AnyActor,
    action: str,
    resource_type: str,
    resource_id: Any,
    patient_id: int | None,
    outcome: str,
    details: dict[str, Any] | None = None,
) -> AuditEvent:
    actor_type: str
    actor_id: str | None
    if actor is None:
        actor_type, actor_id = "system", None
    elif isinstance(actor, SystemActor):
        actor_type, actor_id = "system", actor.name[:64]
    elif actor == ANONYMOUS:
        actor_type, actor_id = ANONYMOUS, None
    else:
        actor_type, actor_id = actor.type, str(actor.id)
    return AuditEvent(
        at=utcnow(),
        actor_type=actor_type,
        actor_id=actor_id,
        action=action,
        resource_type=resource_type,
        resource_id=None if resource_id is None else str(resource_id),
        patient_id=patient_id,
        outcome=outcome,
        ip=client_ip_var.get(),
        request_id=request_id_var.get(),
        details=details,
    )


def audit(
    db: Session,
    actor: AnyActor,
    action: Action | str,
    resource_type: str,
    resource_id: Any = None,
    patient_id: int | None = None,
    outcome: Outcome | str = "success",
    *,
    details: dict[str, Any] | None = None,
) -> AuditEvent:
    """Add one audit event to ``db``'s current transaction (committed with the use case).

    Parameters
    ----------
    db : Session
        The session of the use case; the caller commits.
    actor : Actor, ANONYMOUS or None
        Who acts: ``None`` = the system (e.g. the worker); :data:`ANONYMOUS` =
        nobody authenticated (e.g. a failed login).
    action : str
        ``list``, ``read``, ``create``, ``update``, ``delete``, ``export``...
    resource_type : str
        ``patient``, ``session``, ``trial``, ``result``, ``rig``, ``calibration``...
    resource_id : int or str, optional
        The resource's id (stored as text); ``None`` for lists.
    patient_id : int, optional
        The patient whose data this is, when there is one.
    outcome : str
        ``success`` (default), ``denied``, ``not_found``, ``invalid``, ``error``.
    details : dict, optional
        What the event concerns beyond its columns, sealed with them: identifiers and field
        names only (e.g. ``{"fields": [...]}`` of an update, made by
        :mod:`app.services.changes`), never a clinical value.

    Returns
    -------
    AuditEvent
        The pending row.
    """
    event = _event(actor, action, resource_type, resource_id, patient_id, outcome, details)
    return chain.append(db, event)


def audit_listed(
    db: Session,
    actor: AnyActor,
    resource_type: str,
    patient_ids: Iterable[int],
    *,
    action: Action | str = "list",
) -> AuditEvent:
    """Audit a list that returned the data of the patients ``patient_ids`` (e.g. the patient
    list): one ``list`` event (or ``action``) whose ``details`` name them (sealed), and a
    row per patient in ``audit_event_patients``, where the trail's patient filter finds
    it. One event and a few bytes per patient, not an event (and a link of the chain) per
    patient."""
    ids = sorted(set(patient_ids))
    event = audit(db, actor, action, resource_type, details={"patient_ids": ids})
    db.add_all([AuditEventPatient(event=event, patient_id=i) for i in ids])
    return event


VALUES_SHOWN = "field_changes"
"""The resource type of :func:`audit_values_shown`'s event: the values kept beside the trail."""


def audit_values_shown(
    db: Session, actor: AnyActor, events: Iterable[AuditEvent], shown: Container[int]
) -> AuditEvent | None:
    """Record that a read of the trail showed the previous and new values of the updates
    among ``events`` whose ids are in ``shown``, and commit it; nothing when none was shown.

    The read's own event (``list`` ``audit``) names at most the patient it was filtered
    by, while the values it shows belong to each update's patient: one ``read``
    ``field_changes`` event names those patients as a list does (:func:`audit_listed`),
    so each one's trail tells who saw their values. Committed before the values are
    answered (the read's event is committed already, by the read): values leave only on
    record. The API (``GET /audit``) and the page ``/admin/audit`` both call it.
    """
    ids = {e.patient_id for e in events if e.id in shown and e.patient_id is not None}
    if not ids:
        return None
    event = audit_listed(db, actor, VALUES_SHOWN, ids, action="read")
    db.commit()
    return event


def audit_failure(
    db: Session,
    actor: AnyActor,
    action: Action | str,
    resource_type: str,
    resource_id: Any = None,
    patient_id: int | None = None,
    outcome: Outcome | str = "denied",
) -> None:
    """Record a refused or failed request, and commit it.

    The request's pending changes are rolled back first (a refused request
    changes nothing), then the event is committed on the same session, so no
    second connection competes for SQLite's single writer. Call it before the
    use case wrote anything of its own.
    """
    db.rollback()
    chain.append(db, _event(actor, action, resource_type, resource_id, patient_id, outcome))
    db.commit()

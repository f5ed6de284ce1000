"""Rigs (two-camera set-ups): create, list, read. Rigs hold no patient data."""

from __future__ import annotations

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.actors import Actor
from app.audit import audit
from app.errors import ConflictError
from app.models import Rig
from app.schemas import RigCreate
from app.services.common import load_rig, paginate


def create_rig(db: Session, actor: Actor, data: RigCreate) -> Rig:
    """Create a rig (409 if the name exists). Audited as a configuration change."""
    if db.scalars(select(Rig.id).where(func.lower(Rig.name) == data.name.lower())).first():
        raise ConflictError(f"A rig named {data.name} exists already; choose another name.")
    rig = Rig(name=data.name, description=data.description)
    db.add(rig)
    try:
        db.flush()
    except IntegrityError as exc:
        db.rollback()
        raise ConflictError(f"A rig named {data.name} exists already.") from exc
    audit(db, actor, "create", "rig", rig.id)
    db.commit()
    return rig


def list_rigs(db: Session, actor: Actor, *, limit: int, offset: int) -> tuple[list[Rig], int]:
    items, total = paginate(db, select(Rig), Rig.name, Rig.id, limit=limit, offset=offset)
    db.rollback()
    return items, total


def get_rig(db: Session, actor: Actor, rig_id: int) -> Rig:
    rig = load_rig(db, actor, rig_id, "read")
    db.rollback()
    return rig

"""Rigs (two-camera set-ups): create, list, read. Rigs hold no patient data."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.actors import Actor
from app.audit import audit
from app.errors import ConflictError, NotFoundError
from app.models import Calibration, Rig
from app.schemas import RigCreate
from app.services.calibrations import CalibrationRow, calibration_rows, current_calibration
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


# --------------------------------------------------------------------------- pages


def all_rigs(db: Session) -> list[Rig]:
    """Every rig, by name (for the rig list and the new-session form)."""
    return list(db.scalars(select(Rig).order_by(Rig.name)))


@dataclass(frozen=True)
class RigOverview:
    """A rig on the rig list, with its current calibration (None: not calibrated yet)."""

    rig: Rig
    current: Calibration | None


def rig_overviews(db: Session, actor: Actor) -> list[RigOverview]:
    """The rig list page (rigs hold no patient data: not audited)."""
    views = [RigOverview(rig, current_calibration(rig)) for rig in all_rigs(db)]
    db.rollback()
    return views


def rig_with_calibrations(
    db: Session, actor: Actor, rig_id: int
) -> tuple[Rig, list[CalibrationRow]]:
    """The rig page: the rig and its calibrations, newest first (404 if it does not exist)."""
    rig = db.get(Rig, rig_id)
    if rig is None:
        raise NotFoundError(f"Rig {rig_id} does not exist.")
    rows = calibration_rows(db, rig)
    db.rollback()
    return rig, rows


def check_calibration_target(db: Session, actor: Actor, rig_id: int) -> None:
    """Fail fast before receiving a large body: the rig must exist (404)."""
    exists = db.get(Rig, rig_id) is not None
    db.rollback()
    if not exists:
        raise NotFoundError(f"Rig {rig_id} does not exist.")

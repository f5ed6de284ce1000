"""``/sessions``: create, list per patient, read, update, delete (soft)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response, status

from app.api.responses import AUTH, IdPath, Limit, Offset, errors, page
from app.auth import PatientReader as Reader
from app.auth import PatientWriter as Writer
from app.auth import SessionDep
from app.schemas import MAX_ID, Page, SessionCreate, SessionRead, SessionUpdate
from app.services import sessions as service

router = APIRouter(prefix="/sessions", tags=["sessions"])


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=SessionRead,
    responses=errors(*AUTH, 404, 400, 413),
    summary="Create a session (patient, rig, date, medication state)",
)
def create_session(data: SessionCreate, actor: Writer, db: SessionDep) -> SessionRead:
    return SessionRead.model_validate(service.create_session(db, actor, data))


@router.get(
    "",
    response_model=Page[SessionRead],
    responses=errors(*AUTH, 404),
    summary="List the sessions of one patient, newest first",
)
def list_sessions(
    actor: Reader,
    db: SessionDep,
    patient_id: Annotated[int, Query(ge=1, le=MAX_ID, description="The patient.")],
    limit: Limit = 50,
    offset: Offset = 0,
) -> Page[SessionRead]:
    items, total = service.list_sessions(
        db, actor, patient_id=patient_id, limit=limit, offset=offset
    )
    return page(SessionRead, items, total, limit=limit, offset=offset)


@router.get(
    "/{session_id}",
    response_model=SessionRead,
    responses=errors(*AUTH, 404),
    summary="Read a session",
)
def get_session(session_id: IdPath, actor: Reader, db: SessionDep) -> SessionRead:
    return SessionRead.model_validate(service.get_session(db, actor, session_id))


@router.patch(
    "/{session_id}",
    response_model=SessionRead,
    responses=errors(*AUTH, 404, 400, 413),
    summary="Change a session's states, notes, rating or calibration choice",
)
def update_session(
    session_id: IdPath, data: SessionUpdate, actor: Writer, db: SessionDep
) -> SessionRead:
    return SessionRead.model_validate(service.update_session(db, actor, session_id, data))


@router.delete(
    "/{session_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=errors(*AUTH, 404),
    summary="Delete a session (soft: kept for the audit trail)",
)
def delete_session(session_id: IdPath, actor: Writer, db: SessionDep) -> Response:
    service.delete_session(db, actor, session_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)

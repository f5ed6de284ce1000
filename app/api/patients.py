"""``/patients``: create, list (search, pagination), read, update, delete (soft)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response, status

from app.api.responses import AUTH, IdPath, Limit, Offset, errors, page
from app.auth import PatientReader as Reader
from app.auth import PatientWriter as Writer
from app.auth import SessionDep
from app.schemas import Page, PatientCreate, PatientRead, PatientUpdate, SessionRead
from app.services import patients as service
from app.services import sessions as session_service

router = APIRouter(prefix="/patients", tags=["patients"])


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=PatientRead,
    responses=errors(*AUTH, 409, 400, 413),
    summary="Create a patient (pseudonymous code)",
)
def create_patient(data: PatientCreate, actor: Writer, db: SessionDep) -> PatientRead:
    return PatientRead.model_validate(service.create_patient(db, actor, data))


@router.get(
    "",
    response_model=Page[PatientRead],
    responses=errors(*AUTH),
    summary="List patients, optionally searching the code",
)
def list_patients(
    actor: Reader,
    db: SessionDep,
    q: Annotated[
        str | None, Query(max_length=64, description="Part of the patient code (any case).")
    ] = None,
    limit: Limit = 50,
    offset: Offset = 0,
) -> Page[PatientRead]:
    items, total = service.list_patients(db, actor, q=q, limit=limit, offset=offset)
    return page(PatientRead, items, total, limit=limit, offset=offset)


@router.get(
    "/{patient_id}",
    response_model=PatientRead,
    responses=errors(*AUTH, 404),
    summary="Read a patient",
)
def get_patient(patient_id: IdPath, actor: Reader, db: SessionDep) -> PatientRead:
    return PatientRead.model_validate(service.get_patient(db, actor, patient_id))


@router.patch(
    "/{patient_id}",
    response_model=PatientRead,
    responses=errors(*AUTH, 404, 409, 400, 413),
    summary="Change a patient's code or optional fields",
)
def update_patient(
    patient_id: IdPath, data: PatientUpdate, actor: Writer, db: SessionDep
) -> PatientRead:
    return PatientRead.model_validate(service.update_patient(db, actor, patient_id, data))


@router.delete(
    "/{patient_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=errors(*AUTH, 404),
    summary="Delete a patient (soft: kept for the audit trail, code stays reserved)",
)
def delete_patient(patient_id: IdPath, actor: Writer, db: SessionDep) -> Response:
    service.delete_patient(db, actor, patient_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get(
    "/{patient_id}/sessions",
    response_model=Page[SessionRead],
    responses=errors(*AUTH, 404),
    summary="List a patient's sessions, newest first",
)
def list_patient_sessions(
    patient_id: IdPath, actor: Reader, db: SessionDep, limit: Limit = 50, offset: Offset = 0
) -> Page[SessionRead]:
    items, total = session_service.list_sessions(
        db, actor, patient_id=patient_id, limit=limit, offset=offset
    )
    return page(SessionRead, items, total, limit=limit, offset=offset)

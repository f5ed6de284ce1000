"""Result revisions of a trial: corrections and re-analyses (``/trials/{id}/revisions``)."""

from __future__ import annotations

from fastapi import APIRouter, Request, status

from app.api.responses import AUTH, IdPath, errors
from app.auth import PatientWriter as Writer
from app.auth import ResultReader, SessionDep
from app.schemas import RevisionCreate, RevisionCreated, RevisionRead
from app.services import revisions as service

router = APIRouter(prefix="/trials/{trial_id}/revisions", tags=["results"])


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=RevisionCreated,
    responses=errors(*AUTH, 400, 404, 409, 413),
    summary="Correct a trial's result (a new revision) or measure it again (a job)",
)
def create_revision(
    trial_id: IdPath, data: RevisionCreate, actor: Writer, db: SessionDep, request: Request
) -> RevisionCreated:
    out = service.create_revision(db, actor, trial_id, data, request.app.state.storage)
    return RevisionCreated(trial_id=out.trial_id, revision=out.revision, job_id=out.job_id)


@router.get(
    "",
    response_model=list[RevisionRead],
    responses=errors(*AUTH, 404),
    summary="Every revision of a trial's result, newest first (who, when, why, what)",
)
def list_revisions(trial_id: IdPath, actor: ResultReader, db: SessionDep) -> list[RevisionRead]:
    return [RevisionRead(**vars(info)) for info in service.list_revisions(db, actor, trial_id)]

"""Trials (upload two videos of one hand) and jobs (the analysis' progress)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request, Response, status

from app.actors import ADMIN_SCOPE, Actor
from app.api.responses import AUTH, IdPath, errors
from app.api.uploads import BINARY, multipart_body, run_api_upload
from app.auth import DataReader, SessionDep, require_scope
from app.auth import PatientReader as Reader
from app.auth import PatientWriter as Deleter
from app.auth import PatientWriter as Rater
from app.auth import RecordingWriter as Uploader
from app.schemas import JobRead, TrialCreated, TrialRatingUpdate, TrialRead
from app.services import trials as service
from app.uploads import ParsedUpload
from core.tasks import TASKS

router = APIRouter(tags=["trials"])
Restorer = Annotated[
    Actor,
    Depends(
        require_scope(
            ADMIN_SCOPE,
            refusal="Restoring a hidden trial is done by an administrator, logged in to the"
            " browser: the trial's session page lists its hidden trials, each with a Restore"
            " button. No API key can do it (none holds the scope admin).",
        )
    ),
]

TRIAL_BODY = multipart_body(
    {
        "hand": {
            "type": "string",
            "enum": ["left", "right"],
            "description": "The side: the hand, or the foot for toe tapping, or the leg for"
            " leg agility.",
        },
        "task": {
            "type": "string",
            "enum": list(TASKS),
            "default": "finger_tapping",
            "description": "The MDS-UPDRS item recorded: finger_tapping (3.4, the default),"
            " hand_movements (3.5), pronation_supination (3.6), toe_tapping (3.7) or"
            " leg_agility (3.8).",
        },
        "rig_id": {
            "type": "integer",
            "description": "The rig that recorded the trial, when not the session's: another"
            " placement of the cameras, calibrated as a rig of its own (toe tapping and leg"
            " agility film the foot and leg from elsewhere). Its calibration measures the"
            " trial. Omit it for the session's rig.",
        },
        "take_id": {
            "type": "string",
            "description": "Your key of this take (8 to 64 letters, digits, '-' or '_'), to"
            " send it again safely after a lost answer: a take_id the session holds already"
            " answers with that trial (stored_before: true) and stores nothing new.",
        },
        "left_video": {**BINARY, "description": "Video of the left camera."},
        "right_video": {**BINARY, "description": "Video of the right camera."},
        "offset_frames": {
            "type": "number",
            "description": "Known offset: right frame j was taken with left frame j + K."
            " Omit it to estimate the offset from the marker motion.",
        },
        "left_times": {
            **BINARY,
            "description": "Optional timestamps file of the left video: CSV with the header"
            " frame,time_s and one row per frame (its capture time in seconds on that"
            " camera's clock). The analysis then uses these times.",
        },
        "right_times": {**BINARY, "description": "Likewise for the right video."},
    },
    ["hand", "left_video", "right_video"],
    "One recording of one task on one side by the two cameras of the session's rig (or of"
    " the rig named by rig_id).",
)


@router.post(
    "/sessions/{session_id}/trials",
    status_code=status.HTTP_201_CREATED,
    response_model=TrialCreated,
    responses=errors(*AUTH, 400, 404, 409, 413, 415),
    openapi_extra=TRIAL_BODY,
    summary="Upload a trial (two videos); queues its analysis",
)
async def create_trial(
    session_id: IdPath, request: Request, actor: Uploader, db: SessionDep
) -> TrialCreated:
    def use_case(upload: ParsedUpload) -> TrialCreated:
        out = service.create_trial(db, actor, session_id, upload)
        return TrialCreated.model_validate(
            {
                "id": out.trial.id,
                "job_id": out.job_id,
                "warnings": out.warnings,
                "take": out.take,
                "stored_before": out.stored_before,
            }
        )

    return await run_api_upload(
        request,
        file_fields=service.TRIAL_FILE_FIELDS,
        text_fields=service.TRIAL_TEXT_FIELDS,
        check=lambda: service.check_trial_target(db, actor, session_id),
        use_case=use_case,
        on_rejected=lambda exc: service.audit_rejected_upload(db, actor, session_id),
    )


@router.get(
    "/sessions/{session_id}/trials",
    response_model=list[TrialRead],
    responses=errors(*AUTH, 404),
    summary="List a session's trials",
)
def list_trials(session_id: IdPath, actor: Reader, db: SessionDep) -> list[TrialRead]:
    return [TrialRead(**v) for v in service.list_trials(db, actor, session_id)]


@router.get(
    "/trials/{trial_id}",
    response_model=TrialRead,
    responses=errors(*AUTH, 404),
    summary="Read a trial (videos, status, job)",
)
def get_trial(trial_id: IdPath, actor: Reader, db: SessionDep) -> TrialRead:
    return TrialRead(**service.get_trial(db, actor, trial_id))


@router.patch(
    "/trials/{trial_id}",
    response_model=TrialRead,
    responses=errors(*AUTH, 404, 400),
    summary="Set the clinician's rating (0-4) and comment of a trial (one hand)",
)
def rate_trial(
    trial_id: IdPath, data: TrialRatingUpdate, actor: Rater, db: SessionDep
) -> TrialRead:
    trial = service.rate_trial(db, actor, trial_id, data)
    return TrialRead(**service.trial_view(db, trial))


@router.delete(
    "/trials/{trial_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=errors(*AUTH, 404),
    summary="Hide a trial (soft delete, kept for the audit trail; an admin can restore it)",
)
def delete_trial(
    trial_id: IdPath,
    actor: Deleter,
    db: SessionDep,
    reason: Annotated[
        str | None, Query(max_length=2000, description="Why the trial is hidden (kept).")
    ] = None,
) -> Response:
    service.delete_trial(db, actor, trial_id, reason)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.post(
    "/trials/{trial_id}/restore",
    response_model=TrialRead,
    responses=errors(*AUTH, 404),
    summary="Restore a hidden trial (administrators only)",
)
def restore_trial(trial_id: IdPath, actor: Restorer, db: SessionDep) -> TrialRead:
    trial = service.restore_trial(db, actor, trial_id)
    return TrialRead(**service.trial_view(db, trial))


@router.get(
    "/jobs/{job_id}",
    response_model=JobRead,
    responses=errors(*AUTH, 404),
    summary="A job's status, progress (0-1), stage and error",
    description="A trial's job needs the scope results:read and is recorded as a read of"
    " the trial (404 when the trial is hidden); a calibration's job, any data scope.",
)
def get_job(job_id: IdPath, actor: DataReader, db: SessionDep) -> JobRead:
    return JobRead.model_validate(service.get_job(db, actor, job_id))

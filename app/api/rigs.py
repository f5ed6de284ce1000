"""``/rigs`` and their calibrations (a rig file, or board videos computed by a job)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, status

from app.api.responses import AUTH, IdPath, Limit, Offset, errors, page
from app.api.uploads import BINARY, multipart_body, run_api_upload
from app.auth import DataReader, RigWriter, SessionDep
from app.schemas import CalibrationCreated, CalibrationRead, Page, RigCreate, RigRead
from app.services import calibrations
from app.services import rigs as service
from app.uploads import ParsedUpload

router = APIRouter(tags=["rigs"])

CALIBRATION_BODY = multipart_body(
    {
        "rig_json": {**BINARY, "description": "A rig file (bradyscope.rig/1)."},
        "left_video": {**BINARY, "description": "Board recording of the left camera."},
        "right_video": {**BINARY, "description": "Board recording of the right camera."},
        "board": {"type": "string", "enum": ["chessboard", "charuco"]},
        "cols": {"type": "integer", "description": "Chessboard: inner corners; ChArUco: squares."},
        "rows": {"type": "integer", "description": "Chessboard: inner corners; ChArUco: squares."},
        "square_mm": {"type": "number", "description": "Square side, mm."},
        "marker_mm": {"type": "number", "description": "ChArUco marker side, mm."},
        "dictionary": {"type": "string", "description": "ArUco dictionary, e.g. DICT_4X4_1000."},
        "legacy": {
            "type": "boolean",
            "description": "ChArUco: a board printed with OpenCV before 4.6 (its layout with an"
            " even number of rows).",
        },
        "valid_from": {
            "type": "string",
            "format": "date-time",
            "description": "Sessions from this time on use it (default: now; a rig's first"
            " calibration: all sessions).",
        },
    },
    [],
    "Either rig_json, or left_video + right_video + board, cols, rows, square_mm"
    " [, marker_mm, dictionary, legacy].",
)


@router.post(
    "/rigs",
    status_code=status.HTTP_201_CREATED,
    response_model=RigRead,
    responses=errors(*AUTH, 409, 400, 413),
    summary="Create a rig (a two-camera set-up)",
)
def create_rig(data: RigCreate, actor: RigWriter, db: SessionDep) -> RigRead:
    return RigRead.model_validate(service.create_rig(db, actor, data))


@router.get("/rigs", response_model=Page[RigRead], responses=errors(*AUTH), summary="List rigs")
def list_rigs(
    actor: DataReader, db: SessionDep, limit: Limit = 50, offset: Offset = 0
) -> Page[RigRead]:
    items, total = service.list_rigs(db, actor, limit=limit, offset=offset)
    return page(RigRead, items, total, limit=limit, offset=offset)


@router.get(
    "/rigs/{rig_id}", response_model=RigRead, responses=errors(*AUTH, 404), summary="Read a rig"
)
def get_rig(rig_id: IdPath, actor: DataReader, db: SessionDep) -> RigRead:
    return RigRead.model_validate(service.get_rig(db, actor, rig_id))


@router.post(
    "/rigs/{rig_id}/calibrations",
    status_code=status.HTTP_201_CREATED,
    response_model=CalibrationCreated,
    responses=errors(*AUTH, 400, 404, 409, 413, 415),
    openapi_extra=CALIBRATION_BODY,
    summary="Add a calibration: a rig file (ready at once) or board videos (a job)",
)
async def create_calibration(
    rig_id: IdPath, request: Request, actor: RigWriter, db: SessionDep
) -> CalibrationCreated:
    def use_case(upload: ParsedUpload) -> CalibrationCreated:
        cal, job_id = calibrations.create_calibration(db, actor, rig_id, upload)
        return CalibrationCreated.model_validate(
            {"id": cal.id, "job_id": job_id, "status": cal.status}
        )

    return await run_api_upload(
        request,
        file_fields=calibrations.CALIBRATION_FILE_FIELDS,
        text_fields=calibrations.CALIBRATION_TEXT_FIELDS,
        check=lambda: service.get_rig(db, actor, rig_id),  # 404 before the body
        use_case=use_case,
        on_rejected=lambda exc: calibrations.audit_rejected_upload(db, actor, rig_id),
    )


@router.get(
    "/rigs/{rig_id}/calibrations",
    response_model=list[CalibrationRead],
    responses=errors(*AUTH, 404),
    summary="List a rig's calibrations, oldest version first",
)
def list_calibrations(rig_id: IdPath, actor: DataReader, db: SessionDep) -> list[CalibrationRead]:
    return [CalibrationRead(**v) for v in calibrations.list_calibrations(db, actor, rig_id)]


@router.get(
    "/calibrations/{calibration_id}",
    response_model=CalibrationRead,
    responses=errors(*AUTH, 404),
    summary="Read a calibration (status, quality, its job)",
)
def get_calibration(calibration_id: IdPath, actor: DataReader, db: SessionDep) -> CalibrationRead:
    return CalibrationRead(**calibrations.get_calibration(db, actor, calibration_id))


@router.get(
    "/calibrations/{calibration_id}/rig.json",
    response_model=dict[str, Any],
    responses=errors(*AUTH, 404, 409),
    summary="The rig file (bradyscope.rig/1) of a ready calibration",
)
def get_calibration_rig_file(
    calibration_id: IdPath, actor: DataReader, db: SessionDep
) -> dict[str, Any]:
    return calibrations.rig_file_of(db, actor, calibration_id)

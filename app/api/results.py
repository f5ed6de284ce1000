"""A trial's result and its exports: result.json, markers.csv/.c3d/.trc, report.html/.pdf, FHIR."""

from __future__ import annotations

from hashlib import sha256
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response

from app.api.responses import (
    AUTH,
    IdPath,
    attachment,
    errors,
    file_responses,
    head_attachment,
    json_errors,
    not_modified,
)
from app.auth import ResultReader, SessionDep
from app.services import results as service
from app.services import trajectories

router = APIRouter(prefix="/trials/{trial_id}", tags=["results"])

EXPORT_ERRORS = json_errors(*AUTH, 404, 409)


class FhirJSONResponse(JSONResponse):
    """A FHIR resource as JSON: ``application/fhir+json``, the FHIR R4 media type (the
    OpenAPI document then lists this type alone for the route's 200)."""

    media_type = "application/fhir+json"


RevisionQuery = Annotated[
    int | None,
    Query(
        ge=1,
        le=100_000,
        description="A result revision (1 = the first analysis); default: the newest.",
    ),
]


def _tz(request: Request) -> str:
    """The clinic's time zone (``BRADYSCOPE_TIMEZONE``), in which reports show dates."""
    return str(request.app.state.settings.timezone)


@router.get(
    "/result",
    response_model=dict[str, Any],
    responses=errors(*AUTH, 404, 409),
    summary="The result.json document (format bradyscope.result/1)",
)
def get_result(
    trial_id: IdPath, actor: ResultReader, db: SessionDep, revision: RevisionQuery = None
) -> dict[str, Any]:
    return service.get_result(db, actor, trial_id, revision)


@router.head("/markers.csv", include_in_schema=False)  # the GET's headers (docs/api.md)
@router.get(
    "/markers.csv",
    response_class=FileResponse,
    responses={
        200: {"content": {"text/csv": {"schema": {"type": "string"}}}, "description": "CSV"},
        304: {"description": "Not modified: If-None-Match names the file's ETag."},
        **EXPORT_ERRORS,
    },
    summary="The markers.csv document (one row per frame and marker)",
)
def get_markers_csv(
    trial_id: IdPath,
    actor: ResultReader,
    db: SessionDep,
    request: Request,
    revision: RevisionQuery = None,
) -> Response:
    path = service.markers_csv_path(db, actor, trial_id, request.app.state.storage, revision)
    stat = path.stat()
    # The file of one revision: its stored name, time and size (a new revision's is another).
    version = f"{path.name}:{stat.st_mtime_ns}:{stat.st_size}".encode()
    etag = f'"{sha256(version).hexdigest()[:32]}"'
    if not_modified(request, etag):
        return Response(status_code=304, headers={"ETag": etag})
    return FileResponse(
        path,
        media_type="text/csv; charset=utf-8",
        filename=f"trial-{trial_id}-markers.csv",
        stat_result=stat,
        headers={"ETag": etag},
    )


@router.get(
    "/report.html",
    response_class=HTMLResponse,
    responses={
        200: {"content": {"text/html": {"schema": {"type": "string"}}}, "description": "HTML"},
        **EXPORT_ERRORS,
    },
    summary="The trial's report as a standalone HTML page",
)
def get_report_html(
    trial_id: IdPath,
    actor: ResultReader,
    db: SessionDep,
    request: Request,
    revision: RevisionQuery = None,
) -> HTMLResponse:
    return HTMLResponse(
        service.report_html(
            db, actor, trial_id, request.app.state.storage, revision, timezone=_tz(request)
        )
    )


@router.head("/report.pdf", include_in_schema=False)  # the GET's headers (docs/api.md)
@router.get(
    "/report.pdf",
    response_class=Response,
    responses={
        200: {
            "content": {"application/pdf": {"schema": {"type": "string", "format": "binary"}}},
            "description": "PDF",
        },
        **EXPORT_ERRORS,
    },
    summary="The trial's report as PDF",
)
def get_report_pdf(
    trial_id: IdPath,
    actor: ResultReader,
    db: SessionDep,
    request: Request,
    revision: RevisionQuery = None,
) -> Response:
    storage, name = request.app.state.storage, f"trial-{trial_id}-report.pdf"
    if request.method == "HEAD":  # a report not made yet is not made for a HEAD (seconds of CPU)
        kept = service.kept_report_pdf(db, actor, trial_id, storage, revision, _tz(request))
        return head_attachment(kept, "application/pdf", name)
    pdf = service.report_pdf(db, actor, trial_id, storage, revision, timezone=_tz(request))
    return attachment(pdf, "application/pdf", name)


@router.get(
    "/fhir",
    response_class=FhirJSONResponse,
    responses={
        200: {
            "content": {"application/fhir+json": {"schema": {"type": "object"}}},
            "description": "A FHIR R4 Bundle (DiagnosticReport + Observations, PDF attached).",
        },
        **EXPORT_ERRORS,
    },
    summary="The trial's result as a FHIR R4 Bundle",
)
def get_fhir(
    trial_id: IdPath,
    actor: ResultReader,
    db: SessionDep,
    request: Request,
    revision: RevisionQuery = None,
) -> Response:
    bundle = service.fhir_bundle(
        db, actor, trial_id, request.app.state.storage, revision, timezone=_tz(request)
    )
    return FhirJSONResponse(bundle)


@router.head("/markers.c3d", include_in_schema=False)
@router.get(
    "/markers.c3d",
    response_class=Response,
    responses=file_responses(
        "application/octet-stream", "C3D (mm, the rig's frame; docs/reports.md, Exports)"
    ),
    summary="The marker trajectories as a C3D file (motion-capture tools)",
)
def get_markers_c3d(
    trial_id: IdPath,
    actor: ResultReader,
    db: SessionDep,
    request: Request,
    revision: RevisionQuery = None,
) -> Response:
    storage = request.app.state.storage
    body = trajectories.trajectory_file(db, actor, trial_id, "c3d", storage, revision)
    return attachment(body, "application/octet-stream", f"trial-{trial_id}-markers.c3d")


@router.head("/markers.trc", include_in_schema=False)
@router.get(
    "/markers.trc",
    response_class=Response,
    responses=file_responses("text/plain", "OpenSim TRC (tab separated, mm)"),
    summary="The marker trajectories as an OpenSim TRC file",
)
def get_markers_trc(
    trial_id: IdPath,
    actor: ResultReader,
    db: SessionDep,
    request: Request,
    revision: RevisionQuery = None,
) -> Response:
    storage = request.app.state.storage
    body = trajectories.trajectory_file(db, actor, trial_id, "trc", storage, revision)
    return attachment(body, "text/plain; charset=utf-8", f"trial-{trial_id}-markers.trc")

"""``/sessions``: create, list per patient, read, update, delete (soft)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status
from fastapi.responses import HTMLResponse
from pydantic import Field

from app.api.responses import (
    AUTH,
    IdPath,
    Limit,
    Offset,
    attachment,
    errors,
    head_attachment,
    json_errors,
    page,
)
from app.auth import CurrentActor, ResultReader, SessionDep
from app.auth import PatientReader as Reader
from app.auth import PatientWriter as Writer
from app.schemas import (
    MAX_ID,
    Page,
    SessionCreate,
    SessionRead,
    SessionUpdate,
    SignatureRead,
    SignRequest,
    VisitSignaturesRead,
)
from app.services import sessions as service
from app.services import signatures, visits

router = APIRouter(prefix="/sessions", tags=["sessions"])

_WARNINGS = (
    "What the clinician should know before signing, in words, as the session page's sign"
    " form says it: trials that failed (the signed report lists them as not measured),"
    " trials still being measured, measured trials without the clinician's rating. Signing"
    " is not refused for them."
)


class SignedRead(SignatureRead):
    """The signature just made, and what the clinician was told before it."""

    warnings: list[str] = Field(description=_WARNINGS + " As they stood when signing.")


class VisitSigningRead(VisitSignaturesRead):
    """The visit's signatures, whether an amendment is pending, and what to show first."""

    warnings: list[str] = Field(
        description=_WARNINGS
        + " Empty when there is none, and when there is nothing to sign: the visit is signed"
        " and nothing changed since, or no trial of it has a result yet (signing is refused"
        " then, 409)."
    )


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


@router.get(
    "/{session_id}/report.html",
    response_class=HTMLResponse,
    responses={
        200: {"content": {"text/html": {"schema": {"type": "string"}}}, "description": "HTML"},
        **json_errors(*AUTH, 404),
    },
    summary="The visit report (every trial of the session's day) as a standalone HTML page",
)
def get_visit_report_html(
    session_id: IdPath, actor: ResultReader, db: SessionDep, request: Request
) -> HTMLResponse:
    settings = request.app.state.settings
    return HTMLResponse(
        visits.visit_report_html(
            db, actor, session_id, request.app.state.storage, timezone=settings.timezone
        )
    )


@router.head("/{session_id}/report.pdf", include_in_schema=False)  # the GET's headers
@router.get(
    "/{session_id}/report.pdf",
    response_class=Response,
    responses={
        200: {
            "content": {"application/pdf": {"schema": {"type": "string", "format": "binary"}}},
            "description": "PDF; page 1 is the one-page visit summary.",
        },
        # 409: signed=true and the stored signed report no longer matches its SHA-256
        **json_errors(*AUTH, 404, 409),
    },
    summary="The visit report (every trial of the session's day) as PDF",
)
def get_visit_report_pdf(
    session_id: IdPath,
    actor: ResultReader,
    db: SessionDep,
    request: Request,
    signed: Annotated[
        bool, Query(description="The signed report, byte for byte, instead of a fresh one.")
    ] = False,
    signature: Annotated[
        int | None,
        Query(ge=1, le=100_000, description="With signed=true: this signature (default newest)."),
    ] = None,
) -> Response:
    settings = request.app.state.settings
    storage = request.app.state.storage
    if signed:
        row, pdf = signatures.signed_report(
            db, actor, session_id, storage, timezone=settings.timezone, number=signature
        )
        name = visits.visit_file_name(db, session_id, settings.timezone, f"signed-{row.number}")
        return attachment(pdf, "application/pdf", name, **{"X-Content-SHA256": row.sha256})
    if request.method == "HEAD":  # a report not made yet is not made for a HEAD (seconds of CPU)
        kept = visits.kept_visit_report_pdf(
            db, actor, session_id, storage, timezone=settings.timezone
        )
        name = visits.visit_file_name(db, session_id, settings.timezone)
        return head_attachment(kept, "application/pdf", name)
    pdf = visits.visit_report_pdf(db, actor, session_id, storage, timezone=settings.timezone)
    return attachment(
        pdf, "application/pdf", visits.visit_file_name(db, session_id, settings.timezone)
    )


@router.post(
    "/{session_id}/sign",
    status_code=status.HTTP_201_CREATED,
    response_model=SignedRead,
    responses=errors(*AUTH, 404, 409, 429),
    summary="Sign the visit report (a clinician, with the password again); kept unchanged",
)
def sign_visit(
    session_id: IdPath, data: SignRequest, actor: CurrentActor, db: SessionDep, request: Request
) -> SignedRead:
    signed = signatures.sign_visit(
        db,
        actor,
        session_id,
        data.password,
        request.app.state.storage,
        settings=request.app.state.settings,
        ip=request.client.host[:45] if request.client else None,
    )
    row = SignatureRead.model_validate(signed.signature)
    return SignedRead(**row.model_dump(), warnings=list(signed.warnings))


@router.get(
    "/{session_id}/signatures",
    response_model=VisitSigningRead,
    responses=errors(*AUTH, 404),
    summary="The visit's signatures, whether an amendment is pending, what to know before signing",
)
def list_signatures(
    session_id: IdPath, actor: ResultReader, db: SessionDep, request: Request
) -> VisitSigningRead:
    state = signatures.signing_state(
        db, actor, session_id, timezone=request.app.state.settings.timezone
    )
    return VisitSigningRead(
        status=state.status,
        changes=state.changes,
        signatures=[SignatureRead.model_validate(s) for s in state.signatures],
        warnings=list(state.warnings),  # only while there is something to sign (the page's)
    )

"""Signing a visit from the session page, and downloading its signed reports.

``POST /sessions/{id}/sign`` asks for the clinician's password again
(``app.services.signatures.sign_visit``); ``/sessions/{id}/signed/{n}.pdf``
serves signed report ``n`` byte for byte. One audit event each (signing also
records the re-authentication). A refused signature (a wrong password, too many
attempts, nothing changed since the last signature) brings the clinician back to the
session page with the reason next to the password field, not to a page with no way on.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response

from app.auth import SessionDep
from app.errors import AppError, AuthenticationError, NotFoundError
from app.schemas import IdPath
from app.services import signatures, visits
from app.web.common import CSRF_MESSAGE, PageUser, csrf_refused, error_page, status_of
from app.web.recordings import session_response

router = APIRouter()


@router.post("/sessions/{session_id}/sign", response_class=HTMLResponse)
def sign_visit(
    request: Request,
    db: SessionDep,
    user: PageUser,
    session_id: IdPath,
    password: Annotated[str, Form(max_length=1024)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
) -> Response:
    if csrf_refused(db, user, csrf_token, request):
        return error_page(request, user, status_code=403, message=CSRF_MESSAGE)
    try:
        row = signatures.sign_visit(
            db,
            user,
            session_id,
            password,
            request.app.state.storage,
            settings=request.app.state.settings,
            ip=request.client.host[:45] if request.client else None,
        ).signature
    except (NotFoundError, AuthenticationError) as exc:  # no session to go back to; logged out
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    except AppError as exc:
        db.rollback()
        return session_response(
            request, db, user, session_id, status=status_of(exc), sign_error=str(exc)
        )
    return RedirectResponse(
        f"/sessions/{session_id}?msg=Visit+signed+(signature+{row.number}).", status_code=303
    )


@router.get("/sessions/{session_id}/signed/{number}.pdf")
def signed_pdf(
    request: Request, db: SessionDep, user: PageUser, session_id: IdPath, number: IdPath
) -> Response:
    try:
        row, body = signatures.signed_report(
            db,
            user,
            session_id,
            request.app.state.storage,
            timezone=request.app.state.settings.timezone,
            number=number,
        )
    except AppError as exc:
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    name = visits.visit_file_name(
        db, session_id, request.app.state.settings.timezone, f"signed-{row.number}"
    )
    return Response(
        body,
        media_type="application/pdf",
        headers={
            "Content-Disposition": f'attachment; filename="{name}"',
            "X-Content-SHA256": row.sha256,
        },
    )

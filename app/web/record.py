"""Managing the record from the pages: edit a session, hide a trial (with a reason), restore it.

Each is a plain form post with the session's CSRF token, through the same use
cases as the REST API (``PATCH /sessions/{id}``, ``DELETE /trials/{id}``,
``POST /trials/{id}/restore``), so each is one audit event there.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from pydantic import ValidationError

from app.auth import SessionDep
from app.errors import AppError
from app.schemas import IdPath, SessionUpdate
from app.services import sessions, trials
from app.services.common import visible_trial
from app.web.common import (
    CSRF_MESSAGE,
    SESSION_LABELS,
    PageUser,
    csrf_refused,
    error_page,
    status_of,
    validation_message,
)

router = APIRouter()


@router.post("/sessions/{session_id}/edit", response_class=HTMLResponse)
def session_edit(
    request: Request,
    db: SessionDep,
    user: PageUser,
    session_id: IdPath,
    medication_state: Annotated[str, Form(max_length=20)] = "",
    dbs_state: Annotated[str, Form(max_length=20)] = "",
    time_since_levodopa_min: Annotated[str, Form(max_length=10)] = "",
    more_affected_side: Annotated[str, Form(max_length=10)] = "",
    dominant_hand: Annotated[str, Form(max_length=10)] = "",
    notes: Annotated[str, Form(max_length=5000)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
) -> Response:
    if csrf_refused(db, user, csrf_token, request):
        return error_page(request, user, status_code=403, message=CSRF_MESSAGE)
    try:
        data = SessionUpdate.model_validate(
            {
                "medication_state": medication_state or None,
                "dbs_state": dbs_state or None,
                "time_since_levodopa_min": int(time_since_levodopa_min)
                if time_since_levodopa_min.strip()
                else None,
                "more_affected_side": more_affected_side or None,
                "dominant_hand": dominant_hand or None,
                "notes": notes.strip() or None,
            }
        )
        sessions.update_session(db, user, session_id, data)
    except ValidationError as exc:
        return error_page(
            request, user, status_code=422, message=validation_message(exc, SESSION_LABELS)
        )
    except ValueError:
        return error_page(
            request,
            user,
            status_code=422,
            message="Time since the last levodopa dose: give a whole number of minutes, or nothing.",
        )
    except AppError as exc:
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    return RedirectResponse(f"/sessions/{session_id}?msg=Session+updated.", status_code=303)


@router.post("/trials/{trial_id}/hide", response_class=HTMLResponse)
def trial_hide(
    request: Request,
    db: SessionDep,
    user: PageUser,
    trial_id: IdPath,
    reason: Annotated[str, Form(max_length=2000)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
) -> Response:
    if csrf_refused(db, user, csrf_token, request):
        return error_page(request, user, status_code=403, message=CSRF_MESSAGE)
    if len(reason.strip()) < 3:
        return error_page(
            request, user, status_code=422, message="Say why the trial is hidden (a reason)."
        )
    trial = visible_trial(db, trial_id)
    session_id = trial.session_id if trial is not None else None
    try:
        trials.delete_trial(db, user, trial_id, reason)
    except AppError as exc:
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    return RedirectResponse(f"/sessions/{session_id}?msg=Trial+hidden.", status_code=303)


@router.post("/trials/{trial_id}/restore", response_class=HTMLResponse)
def trial_restore(
    request: Request,
    db: SessionDep,
    user: PageUser,
    trial_id: IdPath,
    csrf_token: Annotated[str, Form(max_length=200)] = "",
) -> Response:
    if csrf_refused(db, user, csrf_token, request):
        return error_page(request, user, status_code=403, message=CSRF_MESSAGE)
    try:
        trial = trials.restore_trial(db, user, trial_id)
    except AppError as exc:
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    return RedirectResponse(f"/sessions/{trial.session_id}?msg=Trial+restored.", status_code=303)

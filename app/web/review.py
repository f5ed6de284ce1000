"""The review view of a trial: both videos with the markers, the aperture, corrections.

``GET /trials/{id}/review[?revision=N]`` is one ``read review`` audit event;
the page embeds what the player draws (a JSON data block, not a script) and
plays the videos' browser proxies from ``/trials/{id}/video/{side}`` (range
requests, part of that view). Corrections and re-analyses are form posts to
``/trials/{id}/revisions`` (the same use case as the REST API); each is one
``create revision`` event.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Form, Request
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse, Response
from pydantic import ValidationError

from app.auth import SessionDep
from app.errors import AppError
from app.reports.visit import trial_time
from app.schemas import IdPath, RevisionCreate
from app.services import review, revisions
from app.web.common import (
    CSRF_MESSAGE,
    PageUser,
    csrf_refused,
    error_page,
    render,
    settings_of,
    status_of,
    validation_message,
)
from core.tasks import parse_task

router = APIRouter()

REANALYSE = "reanalyse"


@router.get("/trials/{trial_id}/review", response_class=HTMLResponse)
def review_page(
    request: Request, db: SessionDep, user: PageUser, trial_id: IdPath, revision: int | None = None
) -> Response:
    try:
        page = review.review_page(db, user, trial_id, request.app.state.storage, revision=revision)
    except AppError as exc:
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    trial = page.trial
    patient = trial.session.patient
    return render(
        request,
        "review.html",
        user,
        active="patients",
        title=(
            f"Review {patient.code}: trial {trial.id}, {parse_task(trial.task).label.lower()},"
            f" {trial.hand} {parse_task(trial.task).limb},"
            f" medication {trial.session.medication_state}"
        ),
        trial=trial,
        patient=patient,
        page=page,
        result=page.result,
        data=page.data,
        corrections=page.corrections,
        # the heading names the trial by its own time, as the reports do (the crumbs: the
        # session's time)
        when=trial_time(
            page.uploaded_at,
            trial.session.recorded_at,
            settings_of(request).timezone,
            with_day=True,
        ),
    )


@router.get("/trials/{trial_id}/video/{side}")
def trial_video(
    request: Request, db: SessionDep, user: PageUser, trial_id: IdPath, side: str
) -> Response:
    if side not in ("left", "right"):
        return error_page(request, user, status_code=404, message=f"There is no {side!r} video.")
    try:
        path = review.proxy_file(
            db, user, trial_id, side, request.app.state.storage, first=_from_first_byte(request)
        )
    except AppError as exc:
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    return FileResponse(path, media_type="video/mp4")


def _from_first_byte(request: Request) -> bool:
    """Whether the request asks for the file from its start (no range, or one from byte 0)."""
    ranges = request.headers.get("range", "").strip().lower()
    return not ranges or ranges.replace(" ", "").startswith("bytes=0-")


def _taps(values: list[str]) -> list[int]:
    return [int(v) for v in values if v.strip()]


def _window(start: str, end: str) -> tuple[float, float] | None:
    if not start.strip() and not end.strip():
        return None
    return float(start), float(end)


@router.post("/trials/{trial_id}/revisions", response_class=HTMLResponse)
def revision_create(
    request: Request,
    db: SessionDep,
    user: PageUser,
    trial_id: IdPath,
    reason: Annotated[str, Form(max_length=2000)] = "",
    kind: Annotated[str, Form(max_length=20)] = "correct",
    exclude_taps: Annotated[list[str] | None, Form()] = None,
    dismiss_pauses: Annotated[list[str] | None, Form()] = None,
    window_start_s: Annotated[str, Form(max_length=20)] = "",
    window_end_s: Annotated[str, Form(max_length=20)] = "",
    swap_labels: Annotated[str, Form(max_length=5)] = "",
    offset_frames: Annotated[str, Form(max_length=20)] = "",
    swap_cameras: Annotated[str, Form(max_length=10)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
) -> Response:
    if csrf_refused(db, user, csrf_token, request):
        return error_page(request, user, status_code=403, message=CSRF_MESSAGE)
    try:
        if kind == REANALYSE:
            data = RevisionCreate(
                reason=reason,
                offset_frames=float(offset_frames) if offset_frames.strip() else None,
                # the form says how to measure the videos: as stored, or swapped
                swap_cameras={"swapped": True, "as-stored": False}.get(swap_cameras),
            )
        else:
            data = RevisionCreate(
                reason=reason,
                exclude_taps=_taps(exclude_taps or []),
                dismiss_pauses=_taps(dismiss_pauses or []),
                window_s=_window(window_start_s, window_end_s),
                swap_labels=bool(swap_labels),
            )
        out = revisions.create_revision(db, user, trial_id, data, request.app.state.storage)
    except ValidationError as exc:
        return error_page(request, user, status_code=422, message=validation_message(exc))
    except ValueError:
        return error_page(
            request,
            user,
            status_code=422,
            message="Tap numbers, the window and the offset must be numbers.",
        )
    except AppError as exc:
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    if out.job_id is not None:
        return RedirectResponse(f"/jobs/{out.job_id}", status_code=303)
    return RedirectResponse(
        f"/trials/{trial_id}/review?msg=Revision+{out.revision}+stored.", status_code=303
    )

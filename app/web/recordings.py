"""Session page, trial upload (left and right hand) and the live job view.

The upload form works without JavaScript (a plain multipart POST, then a
redirect to the job page). With JavaScript (``/static/app.js``) it is sent by
XMLHttpRequest so that a progress bar shows the bytes sent; the answer is
then JSON and the script goes to the job page itself.

Uploads are streamed to storage by :func:`app.uploads.receive_multipart`; the
CSRF token comes in the ``X-CSRF-Token`` header (script) or as the form's
``csrf_token`` field (plain form), checked before anything is stored for good.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from sqlalchemy.orm import Session

from app import job_views
from app.actors import ADMIN_SCOPE, Actor
from app.auth import SessionDep
from app.errors import AppError, NotFoundError
from app.models import Job, Trial
from app.schemas import IdPath
from app.services import sessions, signatures, trials, visits
from app.services.rigs import all_rigs
from app.timezones import local_date
from app.uploads import ParsedUpload
from app.web.common import (
    PATIENT_PAGES_SCOPE,
    PageUser,
    error_page,
    not_found_page,
    page_user,
    render,
    run_page_upload,
    scope_refusal,
    settings_of,
    status_of,
    wants_json,
    with_own_db,
)
from core.tasks import Task

router = APIRouter()


def _takes(n: int, what: str) -> str:
    """``"1 failed take"``, ``"2 failed takes"``; ``what`` with ``{}`` for the noun."""
    return f"{n} " + what.format("take" if n == 1 else "takes")


@dataclass(frozen=True)
class SideCell:
    """What the task grid says of one side of one task.

    ``state``: measured (a trial has a result: its newest is linked, whatever came after),
    measuring (none has a result, one is queued or running), failed (every take failed),
    hidden (every take was hidden) or "not recorded". ``notes``: the side's other takes
    in words ("1 failed take"), so that a failed retry neither hides a good measurement
    nor goes unmentioned.
    """

    state: str
    trial: Trial | None = None
    notes: tuple[str, ...] = ()


def _side_cell(visible: list[Trial], hidden: list[Trial]) -> SideCell:
    """The cell of one side from its visible and hidden trials (of one task)."""
    measured = [t for t in visible if t.result is not None]
    pending = [t for t in visible if t.result is None and t.status in ("queued", "running")]
    failed = [t for t in visible if t.result is None and t.status == "failed"]
    again = [t for t in measured if t.status in ("queued", "running")]
    counts: tuple[tuple[int, str], ...] = (
        (len(failed), "failed {}"),
        (len(pending), "{} being measured"),
        (len(again), "{} being measured again"),
        (len(hidden), "hidden {}"),
    )
    if measured:
        shown, state = max(measured, key=lambda t: t.id), "measured"
    elif pending:
        shown, state = max(pending, key=lambda t: t.id), "measuring"
        counts = counts[:1] + counts[3:]
    elif failed:
        shown, state = max(failed, key=lambda t: t.id), "failed"
        counts = ((len(failed) - 1, "other failed {}"), counts[3])
    elif hidden:
        return SideCell("hidden", max(hidden, key=lambda t: t.id))
    else:
        return SideCell("not recorded")
    return SideCell(state, shown, tuple(_takes(n, what) for n, what in counts if n))


def _task_grid(trials: list[Trial], hidden: list[Trial]) -> list[dict[str, Any]]:
    """One row per task (MDS-UPDRS 3.4–3.8): each side's :class:`SideCell`, and the
    right–left comparison of the task when both sides are measured (the two trials their
    cells link to: the newest with a result of each side)."""
    rows = []
    for task in Task:
        sides = {
            side: _side_cell(
                [t for t in trials if t.task == task.value and t.hand == side],
                [t for t in hidden if t.task == task.value and t.hand == side],
            )
            for side in ("right", "left")
        }
        right, left = sides["right"].trial, sides["left"].trial
        both = all(cell.state == "measured" for cell in sides.values())
        rows.append(
            {
                "title": task.heading,
                "sides": sides,
                "pair": (right.id, left.id) if both and right and left else None,
            }
        )
    return rows


def session_response(
    request: Request,
    db: Session,
    user: Actor,
    session_id: IdPath,
    *,
    status: int = 200,
    error: str | None = None,
    sign_error: str | None = None,
) -> Response:
    """The session page (audited as a read of the session); ``error`` at the top of the
    page, ``sign_error`` next to the signing form's password (a refused signature)."""
    try:
        overview = sessions.session_overview(db, user, session_id)
    except NotFoundError as exc:
        if error is not None:  # an upload refused while its session was deleted
            return error_page(request, user, status_code=status, message=error)
        return not_found_page(request, user, exc)
    session = overview.session
    trials = [row.trial for row in overview.trials]
    tz = str(settings_of(request).timezone)
    return render(
        request,
        "session.html",
        user,
        status_code=status,
        active="patients",
        title=f"Session {local_date(session.recorded_at, tz):%Y-%m-%d} — {session.patient.code}",
        error=error,
        sign_error=sign_error,
        session=session,
        patient=session.patient,
        trials=[
            {"trial": row.trial, "job": row.job, "retry_with": row.retry_with}
            for row in overview.trials
        ],
        hidden_trials=overview.hidden,
        can_restore=user.has_scope(ADMIN_SCOPE),
        signing=signatures.visit_signing(db, session, tz, warnings=True),
        calibration=overview.calibration,
        calibration_problem=overview.calibration_problem,
        hands=("left", "right"),
        done_hands={t.hand for t in trials if t.status != "failed"},
        task_grid=_task_grid(trials, overview.hidden),
        task_labels={task.value: task.label for task in Task},
        task_choices=[(task.value, task.heading) for task in Task],
        other_rigs=[r for r in all_rigs(db) if r.id != session.rig_id],
    )


@router.get("/sessions/{session_id}", response_class=HTMLResponse)
def session_page(request: Request, db: SessionDep, user: PageUser, session_id: IdPath) -> Response:
    return session_response(request, db, user, session_id)


@router.get("/sessions/{session_id}/visit-report.{kind}")
def visit_report(
    request: Request, db: SessionDep, user: PageUser, session_id: IdPath, kind: str
) -> Response:
    """The visit report of the session's day, as PDF (a download) or HTML."""
    if kind not in ("pdf", "html"):
        return error_page(request, user, status_code=404, message=f"There is no {kind!r} report.")
    storage, tz = request.app.state.storage, settings_of(request).timezone
    try:
        if kind == "html":
            return HTMLResponse(
                visits.visit_report_html(db, user, session_id, storage, timezone=tz)
            )
        pdf = visits.visit_report_pdf(db, user, session_id, storage, timezone=tz)
    except AppError as exc:
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    name = visits.visit_file_name(db, session_id, tz)
    return Response(
        pdf,
        media_type="application/pdf",
        headers={"Content-Disposition": f'attachment; filename="{name}"'},
    )


def _user_and_target(
    db: Session, request: Request, session_id: int
) -> tuple[Actor | None, AppError | None]:
    """The logged-in user, and why the session cannot take a trial (before the body is read)."""
    user = page_user(request, db)
    if user is None:
        return None, None
    refused = scope_refusal(db, user, request, "recordings:write")
    if refused is not None:
        return user, refused
    try:
        trials.check_trial_target(db, user, session_id)  # 404 unknown session
    except AppError as exc:
        return user, exc
    return user, None


def _create_trial(
    db: Session, request: Request, user: Actor, session_id: int, upload: ParsedUpload
) -> Response:
    out = trials.create_trial(db, user, session_id, upload)
    job_url = f"/jobs/{out.job_id}"
    if wants_json(request):
        return JSONResponse(
            {
                "trial_id": out.trial.id,
                "job_id": out.job_id,
                "job_url": job_url,
                "warnings": out.warnings,
                "take": out.take,
                "stored_before": out.stored_before,
            },
            status_code=200 if out.stored_before else 201,
        )
    return RedirectResponse(job_url, status_code=303)


@router.post("/sessions/{session_id}/trials")
async def trial_upload(request: Request, session_id: IdPath) -> Response:
    user, refusal = await run_in_threadpool(
        with_own_db, request, _user_and_target, request, session_id
    )
    return await run_page_upload(
        request,
        user,
        refusal=refusal,
        file_fields=trials.TRIAL_FILE_FIELDS,
        text_fields=trials.PAGE_TRIAL_TEXT_FIELDS,
        fail=lambda db, actor, status, message: session_response(
            request, db, actor, session_id, status=status, error=message
        ),
        use_case=lambda db, actor, upload: _create_trial(db, request, actor, session_id, upload),
        rejected=lambda db, actor: trials.audit_rejected_upload(db, actor, session_id),
    )


# --------------------------------------------------------------------------- jobs


def _job_view(db: Session, job: Job) -> dict[str, Any]:
    """What the job page and its polling script show of a job."""
    view = job_views.job_status(db, job.id) or {}
    out = {
        key: view.get(key)
        for key in (
            "id",
            "kind",
            "status",
            "progress",
            "stage",
            "error",
            "attempts",
            "max_attempts",
        )
    }
    error = out["error"]
    if error:  # shown after "The analysis could not be completed."
        out["error"] = error[:1].upper() + error[1:]
    out["stage_label"] = _stage_label(job.stage, job.status)
    position = trials.queue_position(db, job)
    out["queue_position"] = position
    if position is not None:
        out["stage_label"] = f"Waiting for a worker: number {position} in the queue"
    out["title"] = _job_title(job)
    if job.kind == "calibrate" and job.stage == "detection" and job.status == "running":
        out["stage_label"] = "Finding the calibration board"
    if job.trial_id is not None:
        out["trial_url"] = f"/trials/{job.trial_id}"
    if job.calibration_id is not None and job.calibration is not None:
        out["rig_url"] = f"/rigs/{job.calibration.rig_id}"
    return out


_STAGES = {
    "queued": "Waiting for a worker",
    "claimed": "Starting",
    "detection": "Finding the markers in the videos",
    "markers": "Finding the markers in the videos",
    "sync": "Synchronising the two cameras",
    "synchronisation": "Synchronising the two cameras",
    "tracking": "Following the fingertips",
    "matching": "Matching the markers between the cameras",
    "triangulation": "Computing 3D positions",
    "tracks": "Following the fingertips",
    "metrics": "Computing the tapping measurements",
    "board": "Finding the calibration board",
    "calibration": "Computing the calibration",
}


def _job_title(job: Job) -> str:
    """The page title: what the job does and, once it ended, how it ended."""
    what = f"Analysis {job.id}" if job.trial_id is not None else f"Calibration job {job.id}"
    ended = {"succeeded": "finished", "failed": "failed"}.get(job.status)
    if ended is None:
        return f"{what}: {'queued' if job.status == 'queued' else 'running'}"
    return f"{what}: {ended}"


def _stage_label(stage: str | None, status: str) -> str:
    if status == "succeeded":
        return "Finished"
    if status == "failed":
        return "Stopped with an error"
    if status == "queued" and not stage:
        return _STAGES["queued"]
    if not stage:
        return "Working"
    return _STAGES.get(stage, stage.replace("_", " ").capitalize())


@router.get("/jobs/{job_id}", response_class=HTMLResponse)
def job_page(request: Request, db: SessionDep, user: PageUser, job_id: IdPath) -> Response:
    try:
        job = trials.job_page(db, user, job_id)
    except NotFoundError as exc:
        return error_page(request, user, status_code=404, message=str(exc))
    trial = job.trial
    return render(
        request,
        "job.html",
        user,
        active="patients" if trial is not None else "rigs",
        title=_job_title(job),
        job=_job_view(db, job),
        trial=trial,
        patient=trial.session.patient if trial is not None else None,
    )


@router.get("/jobs/{job_id}/status")
def job_status_json(request: Request, db: SessionDep, job_id: IdPath) -> Response:
    """The job's status for the page's polling script (browser session; not audited)."""
    user = page_user(request, db)
    if user is None:
        return JSONResponse({"detail": "Please log in again."}, status_code=401)
    refused = scope_refusal(db, user, request, PATIENT_PAGES_SCOPE)
    if refused is not None:
        return JSONResponse({"detail": str(refused)}, status_code=403)
    try:
        job = trials.job_progress(db, user, job_id)
    except NotFoundError as exc:
        return JSONResponse({"detail": str(exc)}, status_code=404)
    return JSONResponse(_job_view(db, job))

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

from typing import Any

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from sqlalchemy import select

from app.audit import audit
from app.auth import SessionDep
from app.errors import AppError
from app.models import Job, RecordingSession, Trial, calibration_for
from app.services.common import trial_is_visible, visible_session
from app.web.common import (
    PageUser,
    error_page,
    missing_page,
    page_user,
    render,
    run_page_upload,
    wants_json,
    with_own_db,
)

router = APIRouter()


def _latest_job(db: Any, trial_id: int) -> Job | None:
    return db.scalars(
        select(Job).where(Job.trial_id == trial_id).order_by(Job.id.desc()).limit(1)
    ).first()


def _session_context(db: Any, session: RecordingSession) -> dict[str, Any]:
    trials = [t for t in session.trials if t.deleted_at is None]
    calibration = None
    calibration_problem = None
    try:
        calibration = calibration_for(db, session)
    except AppError as exc:
        calibration_problem = str(exc)
    return {
        "session": session,
        "patient": session.patient,
        "trials": [{"trial": t, "job": _latest_job(db, t.id)} for t in trials],
        "calibration": calibration,
        "calibration_problem": calibration_problem,
        "hands": ("left", "right"),
        "done_hands": {t.hand for t in trials if t.status != "failed"},
        "hand_pair": _hand_pair(trials),
    }


def _hand_pair(trials: list[Trial]) -> tuple[int, int] | None:
    """(right, left) trial ids with results, newest of each hand, for a left/right comparison."""
    newest: dict[str, Trial] = {}
    for t in trials:
        if t.result is not None and (t.hand not in newest or t.id > newest[t.hand].id):
            newest[t.hand] = t
    if "right" in newest and "left" in newest:
        return newest["right"].id, newest["left"].id
    return None


def _session_response(
    request: Request,
    db: Any,
    user: Any,
    session: RecordingSession,
    *,
    status: int = 200,
    error: str | None = None,
) -> Response:
    """The session page (audited as a read of the session)."""
    context = _session_context(db, session)
    audit(db, user, "read", "session", session.id, session.patient_id)
    db.commit()
    return render(
        request,
        "session.html",
        user,
        status_code=status,
        active="patients",
        title=f"Session {session.recorded_at:%Y-%m-%d} — {session.patient.code}",
        error=error,
        **context,
    )


@router.get("/sessions/{session_id}", response_class=HTMLResponse)
def session_page(request: Request, db: SessionDep, user: PageUser, session_id: int) -> Response:
    session = visible_session(db, session_id)
    if session is None:
        return missing_page(request, db, user, "read", "session", session_id)
    return _session_response(request, db, user, session)


def _upload_error(
    db: Any, request: Request, user: Any, session_id: int, status: int, message: str
) -> Response:
    """The session page (or an error page) showing why the upload was refused."""
    session = visible_session(db, session_id)
    if session is None:
        return error_page(request, user, status_code=status, message=message)
    return _session_response(request, db, user, session, status=status, error=message)


def _user_and_target(db: Any, request: Request, session_id: int) -> tuple[Any, AppError | None]:
    """The logged-in user, and why the session cannot take a trial (before the body is read)."""
    from app.services.recordings import check_trial_target

    user = page_user(request, db)
    if user is None:
        return None, None
    try:
        check_trial_target(db, user, session_id)  # 404 unknown session, 409 no calibration
    except AppError as exc:
        return user, exc
    return user, None


def _create_trial(db: Any, request: Request, user: Any, session_id: int, upload: Any) -> Response:
    from app.services.recordings import create_trial

    out = create_trial(db, user, session_id, upload)
    job_url = f"/jobs/{out.job_id}"
    if wants_json(request):
        return JSONResponse(
            {
                "trial_id": out.trial.id,
                "job_id": out.job_id,
                "job_url": job_url,
                "warnings": out.warnings,
            },
            status_code=201,
        )
    return RedirectResponse(job_url, status_code=303)


@router.post("/sessions/{session_id}/trials")
async def trial_upload(request: Request, session_id: int) -> Response:
    from app.services.recordings import TRIAL_FILE_FIELDS, TRIAL_TEXT_FIELDS

    user, refusal = await run_in_threadpool(
        with_own_db, request, _user_and_target, request, session_id
    )
    return await run_page_upload(
        request,
        user,
        refusal=refusal,
        file_fields=TRIAL_FILE_FIELDS,
        text_fields=TRIAL_TEXT_FIELDS,
        fail=lambda db, status, message: _upload_error(
            db, request, user, session_id, status, message
        ),
        use_case=lambda db, upload: _create_trial(db, request, user, session_id, upload),
    )


# --------------------------------------------------------------------------- jobs


def _job_view(db: Any, job: Job) -> dict[str, Any]:
    from app.jobs import job_status

    view = job_status(db, job.id) or {}
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
    out["stage_label"] = _stage_label(job.stage, job.status)
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


def _visible_job(db: Any, job_id: int) -> Job | None:
    job = db.get(Job, job_id)
    if job is None:
        return None
    if job.trial is not None and not trial_is_visible(job.trial):
        return None
    return job


@router.get("/jobs/{job_id}", response_class=HTMLResponse)
def job_page(request: Request, db: SessionDep, user: PageUser, job_id: int) -> Response:
    job = _visible_job(db, job_id)
    if job is None:
        return error_page(request, user, status_code=404, message=f"Job {job_id} does not exist.")
    view = _job_view(db, job)
    trial = job.trial
    patient = trial.session.patient if trial is not None else None
    if patient is not None:
        audit(db, user, "read", "trial", trial.id, patient.id)  # type: ignore[union-attr]
    db.commit()
    return render(
        request,
        "job.html",
        user,
        active="patients" if trial is not None else "rigs",
        title=f"Analysis {job.id}" if trial is not None else f"Calibration job {job.id}",
        job=view,
        trial=trial,
        patient=patient,
    )


@router.get("/jobs/{job_id}/status")
def job_status_json(request: Request, db: SessionDep, job_id: int) -> Response:
    """The job's status for the page's polling script (browser session; not audited)."""
    user = page_user(request, db)
    if user is None:
        return JSONResponse({"detail": "Please log in again."}, status_code=401)
    job = _visible_job(db, job_id)
    if job is None:
        return JSONResponse({"detail": f"Job {job_id} does not exist."}, status_code=404)
    view = _job_view(db, job)
    db.rollback()
    return JSONResponse(view)

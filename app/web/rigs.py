"""Calibration management: rigs, their calibration versions and quality verdicts, uploads.

A calibration is uploaded either as a rig file (ready at once) or as two
board recordings (computed by a ``calibrate`` job, followed on the job page).
Rigs and calibrations are not patient data; their creation is audited by the
services as configuration changes.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Form, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from pydantic import ValidationError
from sqlalchemy import select

from app.auth import SessionDep
from app.errors import AppError
from app.models import Calibration, Job, Rig
from app.reports import quality_verdict
from app.web.common import (
    csrf_from_header,
    csrf_ok,
    error_page,
    login_redirect,
    open_db,
    page_user,
    render,
    settings_of,
    status_of,
    wants_json,
)
from app.web.patients import validation_message

router = APIRouter()

_CSRF_MESSAGE = "The form's security token was missing or out of date; reload the page and retry."

# Quality figures shown on the calibration report, in this order, with labels and units.
QUALITY_LABELS: dict[str, tuple[str, str]] = {
    "rms_px": ("RMS reprojection error (stereo)", "px"),
    "rms_left_px": ("RMS reprojection error, left camera", "px"),
    "rms_right_px": ("RMS reprojection error, right camera", "px"),
    "epipolar_px_mean": ("Mean epipolar error", "px"),
    "epipolar_px_max": ("Largest epipolar error", "px"),
    "n_pairs": ("Board views used (pairs)", ""),
    "n_frames_used": ("Frames used", ""),
    "coverage_left": ("Image coverage, left", ""),
    "coverage_right": ("Image coverage, right", ""),
    "baseline_mm": ("Baseline between the cameras", "mm"),
}


def _quality_items(quality: dict[str, Any] | None) -> list[tuple[str, str]]:
    items = []
    for key, value in (quality or {}).items():
        if isinstance(value, bool) or not isinstance(value, int | float | str):
            continue
        label, unit = QUALITY_LABELS.get(key, (key.replace("_", " ").capitalize(), ""))
        if isinstance(value, float):
            text = f"{value:.3g}"
        else:
            text = str(value)
        items.append((label, f"{text} {unit}".strip()))
    order = list(QUALITY_LABELS.values())
    items.sort(
        key=lambda kv: next((i for i, (lab, _) in enumerate(order) if lab == kv[0]), len(order))
    )
    return items


def _calibration_rows(db: Any, rig: Rig) -> list[dict[str, Any]]:
    rows = []
    for cal in sorted(rig.calibrations, key=lambda c: c.version, reverse=True):
        job = db.scalars(
            select(Job).where(Job.calibration_id == cal.id).order_by(Job.id.desc()).limit(1)
        ).first()
        verdict: str | None = None
        reasons: list[str] = []
        if cal.status == "ready":
            verdict, reasons = quality_verdict(cal.quality, cal.rms_px)
        rows.append(
            {
                "cal": cal,
                "job": job,
                "verdict": verdict,
                "reasons": reasons,
                "quality_items": _quality_items(cal.quality),
            }
        )
    return rows


@router.get("/rigs", response_class=HTMLResponse)
def rig_list(request: Request, db: SessionDep) -> Response:
    user = page_user(request, db)
    if user is None:
        return login_redirect(request)
    return _rig_list(request, db, user)


def _rig_list(
    request: Request,
    db: Any,
    user: Any,
    *,
    error: str | None = None,
    status_code: int = 200,
    form: dict[str, str] | None = None,
) -> Response:
    rigs = list(db.scalars(select(Rig).order_by(Rig.name)))
    latest = {}
    for rig in rigs:
        ready = [c for c in rig.calibrations if c.status == "ready"]
        if ready:
            cal = max(ready, key=lambda c: (c.valid_from, c.version))
            verdict, _ = quality_verdict(cal.quality, cal.rms_px)
            latest[rig.id] = {"cal": cal, "verdict": verdict}
    db.rollback()
    return render(
        request,
        "rigs.html",
        user,
        status_code=status_code,
        active="rigs",
        title="Rigs and calibration",
        rigs=rigs,
        latest=latest,
        error=error,
        form=form or {},
    )


@router.post("/rigs", response_class=HTMLResponse)
def rig_create(
    request: Request,
    db: SessionDep,
    name: Annotated[str, Form(max_length=200)] = "",
    description: Annotated[str, Form(max_length=5000)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
) -> Response:
    from app.schemas import RigCreate
    from app.services.rigs import create_rig

    user = page_user(request, db)
    if user is None:
        return login_redirect(request)
    form = {"name": name, "description": description}
    if not csrf_ok(user, csrf_token):
        return _rig_list(request, db, user, error=_CSRF_MESSAGE, status_code=403, form=form)
    try:
        rig = create_rig(
            db, user, RigCreate(name=name.strip(), description=description.strip() or None)
        )
    except ValidationError as exc:
        db.rollback()
        return _rig_list(
            request, db, user, error=validation_message(exc), status_code=422, form=form
        )
    except AppError as exc:
        db.rollback()
        return _rig_list(request, db, user, error=str(exc), status_code=status_of(exc), form=form)
    return RedirectResponse(f"/rigs/{rig.id}?msg=Rig+created.", status_code=303)


@router.get("/rigs/{rig_id}", response_class=HTMLResponse)
def rig_page(request: Request, db: SessionDep, rig_id: int) -> Response:
    user = page_user(request, db)
    if user is None:
        return login_redirect(request)
    return _rig_page(request, db, user, rig_id)


def _rig_page(
    request: Request,
    db: Any,
    user: Any,
    rig_id: int,
    *,
    error: str | None = None,
    status_code: int = 200,
) -> Response:
    rig = db.get(Rig, rig_id)
    if rig is None:
        return error_page(request, user, status_code=404, message=f"Rig {rig_id} does not exist.")
    rows = _calibration_rows(db, rig)
    db.rollback()
    return render(
        request,
        "rig.html",
        user,
        status_code=status_code,
        active="rigs",
        title=f"Rig {rig.name}",
        rig=rig,
        rows=rows,
        error=error,
    )


def _upload_error(request: Request, user: Any, rig_id: int, status: int, message: str) -> Response:
    if wants_json(request):
        return JSONResponse({"detail": message}, status_code=status)
    db = open_db(request)
    try:
        return _rig_page(request, db, user, rig_id, error=message, status_code=status)
    finally:
        db.close()


def _user_and_rig(request: Request, rig_id: int) -> tuple[Any, bool]:
    db = open_db(request)
    try:
        user = page_user(request, db)
        exists = db.get(Rig, rig_id) is not None
        db.rollback()
        return user, exists
    finally:
        db.close()


def _create(
    request: Request, user: Any, rig_id: int, upload: Any
) -> tuple[Calibration, int | None]:
    from app.services.recordings import create_calibration

    db = open_db(request)
    try:
        return create_calibration(db, user, rig_id, upload)
    finally:
        db.close()


@router.post("/rigs/{rig_id}/calibrations")
async def calibration_upload(request: Request, rig_id: int) -> Response:
    from app.services.recordings import CALIBRATION_FILE_FIELDS, CALIBRATION_TEXT_FIELDS
    from app.storage import Storage
    from app.uploads import receive_multipart
    from core.errors import BradyscopeError

    user, exists = await run_in_threadpool(_user_and_rig, request, rig_id)
    if user is None:
        if wants_json(request):
            return JSONResponse({"detail": "Please log in again."}, status_code=401)
        return login_redirect(request)
    header_token = csrf_from_header(request)
    if header_token is not None and not csrf_ok(user, header_token):
        return await run_in_threadpool(_upload_error, request, user, rig_id, 403, _CSRF_MESSAGE)
    if not exists:
        return await run_in_threadpool(
            _upload_error, request, user, rig_id, 404, f"Rig {rig_id} does not exist."
        )
    settings = settings_of(request)
    try:
        upload = await receive_multipart(
            request,
            storage=Storage.from_settings(settings),
            file_fields=CALIBRATION_FILE_FIELDS,
            text_fields=frozenset(CALIBRATION_TEXT_FIELDS) | {"csrf_token", "kind"},
            max_file_bytes=int(settings.max_upload_bytes),
        )
    except AppError as exc:
        return await run_in_threadpool(
            _upload_error, request, user, rig_id, status_of(exc), str(exc)
        )
    try:
        if header_token is None and not csrf_ok(user, upload.fields.get("csrf_token")):
            upload.discard()
            return await run_in_threadpool(_upload_error, request, user, rig_id, 403, _CSRF_MESSAGE)
        # Empty file inputs of the form that was not used arrive as empty parts: drop them.
        for name in list(upload.files):
            staged = upload.files[name]
            if staged.size_bytes == 0 and not (staged.filename or ""):
                staged.incoming.abort()
                upload.files.pop(name)
        for name in ("valid_from",):
            if not (upload.fields.get(name) or "").strip():
                upload.fields.pop(name, None)
        try:
            cal, job_id = await run_in_threadpool(_create, request, user, rig_id, upload)
        except (AppError, BradyscopeError) as exc:
            upload.discard()
            return await run_in_threadpool(
                _upload_error,
                request,
                user,
                rig_id,
                status_of(exc) if isinstance(exc, AppError) else 422,
                str(exc),
            )
    finally:
        upload.close()
    target = (
        f"/jobs/{job_id}"
        if job_id is not None
        else f"/rigs/{rig_id}?msg=Calibration+v{cal.version}+saved."
    )
    if wants_json(request):
        return JSONResponse(
            {"calibration_id": cal.id, "job_id": job_id, "job_url": target}, status_code=201
        )
    return RedirectResponse(target, status_code=303)

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
from app.errors import AppError, NotFoundError
from app.models import Job, Rig
from app.reports import quality_verdict
from app.web.common import (
    CSRF_MESSAGE,
    PageUser,
    csrf_ok,
    error_page,
    page_user,
    render,
    run_page_upload,
    status_of,
    validation_message,
    wants_json,
    with_own_db,
)

router = APIRouter()

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
def rig_list(request: Request, db: SessionDep, user: PageUser) -> Response:
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
    user: PageUser,
    name: Annotated[str, Form(max_length=200)] = "",
    description: Annotated[str, Form(max_length=5000)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
) -> Response:
    from app.schemas import RigCreate
    from app.services.rigs import create_rig

    form = {"name": name, "description": description}
    if not csrf_ok(user, csrf_token):
        return _rig_list(request, db, user, error=CSRF_MESSAGE, status_code=403, form=form)
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
def rig_page(request: Request, db: SessionDep, user: PageUser, rig_id: int) -> Response:
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


def _user_and_rig(db: Any, request: Request, rig_id: int) -> tuple[Any, AppError | None]:
    """The logged-in user, and a 404 if the rig does not exist (before the body is read)."""
    user = page_user(request, db)
    exists = db.get(Rig, rig_id) is not None
    db.rollback()
    return user, None if exists else NotFoundError(f"Rig {rig_id} does not exist.")


def _create(db: Any, request: Request, user: Any, rig_id: int, upload: Any) -> Response:
    from app.services.recordings import create_calibration

    cal, job_id = create_calibration(db, user, rig_id, upload)
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


def _drop_unused_parts(upload: Any) -> None:
    """The form has a rig-file and a board-video part: the one not used arrives empty."""
    for name in list(upload.files):
        staged = upload.files[name]
        if staged.size_bytes == 0 and not (staged.filename or ""):
            staged.incoming.abort()
            upload.files.pop(name)
    for name in ("valid_from",):
        if not (upload.fields.get(name) or "").strip():
            upload.fields.pop(name, None)


@router.post("/rigs/{rig_id}/calibrations")
async def calibration_upload(request: Request, rig_id: int) -> Response:
    from app.services.recordings import CALIBRATION_FILE_FIELDS, CALIBRATION_TEXT_FIELDS

    user, refusal = await run_in_threadpool(with_own_db, request, _user_and_rig, request, rig_id)
    return await run_page_upload(
        request,
        user,
        refusal=refusal,
        file_fields=CALIBRATION_FILE_FIELDS,
        text_fields=CALIBRATION_TEXT_FIELDS | {"kind"},
        fail=lambda db, status, message: _rig_page(
            request, db, user, rig_id, error=message, status_code=status
        ),
        use_case=lambda db, upload: _create(db, request, user, rig_id, upload),
        prepare=_drop_unused_parts,
    )

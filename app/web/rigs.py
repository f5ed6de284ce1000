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
from sqlalchemy.orm import Session

from app.actors import Actor
from app.auth import SessionDep
from app.errors import AppError, NotFoundError
from app.schemas import IdPath, RigCreate
from app.services import calibrations, rigs
from app.uploads import ParsedUpload
from app.web.common import (
    CSRF_MESSAGE,
    PageUser,
    csrf_refused,
    error_page,
    page_user,
    render,
    run_page_upload,
    scope_refusal,
    status_of,
    validation_message,
    wants_json,
    with_own_db,
)

router = APIRouter()

# Quality figures shown on the calibration report, in this order, with labels and units.
QUALITY_LABELS: dict[str, tuple[str, str]] = {
    "rms_px": ("RMS reprojection error (stereo)", "px"),
    "rms_px_left": ("RMS reprojection error, left camera", "px"),
    "rms_px_right": ("RMS reprojection error, right camera", "px"),
    "view_rms_px_max": ("Worst board view, RMS error", "px"),
    "epipolar_px_mean": ("Mean epipolar error", "px"),
    "epipolar_px_max": ("Largest epipolar error", "px"),
    "epipolar_px_mean_check": ("Mean epipolar error, held-out views", "px"),
    "square_mm": ("Board square, given", "mm"),
    "square_mm_measured": ("Board square, measured in 3D", "mm"),
    "square_error_mm_mean": ("Square size error, mean", "mm"),
    "square_error_mm_rms": ("Square size error, RMS", "mm"),
    "square_check_views": ("Views used for the square check", ""),
    "square_check_method": ("Square check method", ""),
    "coverage_left": ("Image coverage, left camera", "%"),
    "coverage_right": ("Image coverage, right camera", "%"),
    "views_used": ("Board views used", ""),
    "views_rejected": ("Board views rejected", ""),
    "views_blurred": ("Blurred views skipped", ""),
    "views_duplicate": ("Near-duplicate views skipped", ""),
    "views_held_out": ("Views held out for checking", ""),
    "views_both_detected": ("Views with the board in both cameras", ""),
    "frames_tried": ("Frames searched", ""),
    "frames_total": ("Frames in the videos", ""),
    "frames_left_detected": ("Frames with the board, left camera", ""),
    "frames_right_detected": ("Frames with the board, right camera", ""),
    "baseline_mm": ("Baseline between the cameras", "mm"),
    "n_pairs": ("Board views used (pairs)", ""),
    "n_frames_used": ("Frames used", ""),
}
"""Labels and units of ``core.calibration``'s quality figures; others are not shown."""


def _quality_items(quality: dict[str, Any] | None) -> list[tuple[str, str]]:
    items = []
    for key, value in (quality or {}).items():
        if isinstance(value, bool) or not isinstance(value, int | float | str):
            continue
        if key not in QUALITY_LABELS:
            continue  # internal or structured figures (per_view, board, method...)
        label, unit = QUALITY_LABELS[key]
        if unit == "%" and isinstance(value, int | float):
            text = f"{100 * float(value):.0f}"
        elif isinstance(value, float):
            text = f"{value:.3g}"
        else:
            text = str(value)
        items.append((label, f"{text} {unit}".strip()))
    order = list(QUALITY_LABELS.values())
    items.sort(
        key=lambda kv: next((i for i, (lab, _) in enumerate(order) if lab == kv[0]), len(order))
    )
    sync = (quality or {}).get("sync")
    if isinstance(sync, dict) and sync.get("method") in ("estimated", "synchronous"):
        offset_s, frames = sync.get("offset_s"), sync.get("offset_frames")
        if sync["method"] == "synchronous":
            text = "none: the two videos are synchronous"
        elif isinstance(offset_s, int | float) and isinstance(frames, int | float):
            when = "after" if offset_s >= 0 else "before"
            text = (
                f"the right video starts {abs(offset_s):.3f} s ({abs(frames):.2f} frames) {when}"
                " the left; found from the board's motion"
            )
        else:
            text = "found from the board's motion"
        items.append(("Time offset between the cameras", text))
    for warning in (quality or {}).get("warnings") or []:
        if isinstance(warning, str):
            items.append(("Warning", warning))
    return items


@router.get("/rigs", response_class=HTMLResponse)
def rig_list(request: Request, db: SessionDep, user: PageUser) -> Response:
    return _rig_list(request, db, user)


def _rig_list(
    request: Request,
    db: Session,
    user: Actor,
    *,
    error: str | None = None,
    status_code: int = 200,
    form: dict[str, str] | None = None,
) -> Response:
    overviews = rigs.rig_overviews(db, user)
    return render(
        request,
        "rigs.html",
        user,
        status_code=status_code,
        active="rigs",
        title="Rigs and calibration",
        rigs=[o.rig for o in overviews],
        latest={
            o.rig.id: {"cal": o.current, "verdict": o.current.verdict}
            for o in overviews
            if o.current is not None
        },
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
    form = {"name": name, "description": description}
    if csrf_refused(db, user, csrf_token, request):
        return _rig_list(request, db, user, error=CSRF_MESSAGE, status_code=403, form=form)
    try:
        rig = rigs.create_rig(
            db, user, RigCreate(name=name.strip(), description=description.strip() or None)
        )
    except ValidationError as exc:
        db.rollback()
        return _rig_list(
            request,
            db,
            user,
            error=validation_message(exc, {"name": "Name", "description": "Description"}),
            status_code=422,
            form=form,
        )
    except AppError as exc:
        db.rollback()
        return _rig_list(request, db, user, error=str(exc), status_code=status_of(exc), form=form)
    return RedirectResponse(f"/rigs/{rig.id}?msg=Rig+created.", status_code=303)


@router.get("/rigs/{rig_id}", response_class=HTMLResponse)
def rig_page(request: Request, db: SessionDep, user: PageUser, rig_id: IdPath) -> Response:
    return _rig_page(request, db, user, rig_id)


def _rig_page(
    request: Request,
    db: Session,
    user: Actor,
    rig_id: IdPath,
    *,
    error: str | None = None,
    status_code: int = 200,
) -> Response:
    try:
        rig, rows = rigs.rig_with_calibrations(db, user, rig_id)
    except NotFoundError as exc:
        return error_page(request, user, status_code=404, message=str(exc))
    return render(
        request,
        "rig.html",
        user,
        status_code=status_code,
        active="rigs",
        title=f"Rig {rig.name}",
        rig=rig,
        rows=[
            {
                "cal": row.cal,
                "job": row.job,
                "verdict": row.verdict,
                "reasons": row.reasons,
                "quality_items": _quality_items(row.cal.quality),
            }
            for row in rows
        ],
        error=error,
    )


def _user_and_rig(
    db: Session, request: Request, rig_id: IdPath
) -> tuple[Actor | None, AppError | None]:
    """The logged-in user, and a 404 if the rig does not exist (before the body is read)."""
    user = page_user(request, db)
    if user is None:
        return None, None
    refused = scope_refusal(db, user, request, "rigs:write")
    if refused is not None:
        return user, refused
    try:
        rigs.check_calibration_target(db, user, rig_id)
    except NotFoundError as exc:
        return user, exc
    return user, None


def _create(
    db: Session, request: Request, user: Actor, rig_id: IdPath, upload: ParsedUpload
) -> Response:
    cal, job_id = calibrations.create_calibration(db, user, rig_id, upload)
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


CALIBRATION_FORM_LABELS = {
    "rig_json": "Rig file (rig.json)",
    "left_video": "Board video, left camera",
    "right_video": "Board video, right camera",
    "board": "Board",
    "dictionary": "ArUco dictionary",
    "legacy": "Printed with OpenCV before 4.6",
    "cols": "Columns",
    "rows": "Rows",
    "square_mm": "Square size (mm)",
    "marker_mm": "Marker size (mm)",
    "valid_from": "Valid from",
}
"""The calibration forms' labels (templates/rig.html), named by their error messages."""


def _drop_unused_parts(upload: ParsedUpload) -> None:
    """The form has a rig-file and a board-video part: the one not used arrives empty.

    Errors then name the form's labels, not the field names.
    """
    upload.labels.update(CALIBRATION_FORM_LABELS)
    for name in list(upload.files):
        staged = upload.files[name]
        if staged.size_bytes == 0 and not (staged.filename or ""):
            staged.incoming.abort()
            upload.files.pop(name)
    for name in ("valid_from",):
        if not (upload.fields.get(name) or "").strip():
            upload.fields.pop(name, None)


@router.post("/rigs/{rig_id}/calibrations")
async def calibration_upload(request: Request, rig_id: IdPath) -> Response:
    user, refusal = await run_in_threadpool(with_own_db, request, _user_and_rig, request, rig_id)
    return await run_page_upload(
        request,
        user,
        refusal=refusal,
        file_fields=calibrations.CALIBRATION_FILE_FIELDS,
        text_fields=calibrations.CALIBRATION_TEXT_FIELDS | {"kind"},
        fail=lambda db, actor, status, message: _rig_page(
            request, db, actor, rig_id, error=message, status_code=status
        ),
        use_case=lambda db, actor, upload: _create(db, request, actor, rig_id, upload),
        prepare=_drop_unused_parts,
        rejected=lambda db, actor: calibrations.audit_rejected_upload(db, actor, rig_id),
    )

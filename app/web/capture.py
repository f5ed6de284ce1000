"""The capture station: record a trial (or a rig's board videos) with two cameras.

``/sessions/{id}/capture`` records a trial of the session; ``/rigs/{id}/capture``
records a board video pair and starts the rig's calibration. Both render
``templates/capture.html``; the work happens in the browser
(``app/static/capture.js`` and ``capture_gate.js``: camera choice and set-up,
the live quality gate, recording, per-frame capture times, upload), which
posts to the ordinary upload routes (``POST /sessions/{id}/trials``,
``POST /rigs/{id}/calibrations``). docs/capture.md describes the page.

Only these pages may use the cameras: their ``Permissions-Policy`` allows the
camera to this origin, every other page keeps ``camera=()``.
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse, Response

from app.auth import SessionDep
from app.errors import CalibrationMissingError, NotFoundError
from app.schemas import IdPath
from app.services import capture
from app.services.calibrations import rig_to_check_against
from app.services.rigs import all_rigs
from app.web.common import PageUser, error_page, render
from core.camera import StereoRig
from core.errors import InputError
from core.protocols import protocol_for
from core.tasks import DEFAULT_TASK, Task, parse_task
from core.video import HOLE_FRAMES, HOLE_S

router = APIRouter()

CAMERA_PERMISSION = "camera=(self), microphone=(), geolocation=()"
MARKERS_PER_VIEW: dict[Task, int] = {task: len(protocol_for(task).labels) for task in Task}
"""Markers each camera must see for the gate to call its view ready, per task: the task's
marker protocol (core.protocols; finger tapping: thumb and index)."""
COUNTDOWN_S = 3
DEFAULT_DURATION_S = 15
CALIBRATION_SIZES = ((640, 480), (640, 512), (1280, 720), (1280, 1024), (1920, 1080))
"""Resolutions offered for a board recording when the rig has no calibration yet (px)."""


def _allow_camera(response: Response) -> Response:
    response.headers["permissions-policy"] = CAMERA_PERMISSION
    return response


def _task_choices() -> list[dict[str, object]]:
    """The tasks the page offers, with what the gate and the page need to know of each."""
    return [
        {
            "value": task.value,
            "heading": task.heading,
            "limb": task.limb,
            "markers": MARKERS_PER_VIEW.get(task, 0),
        }
        for task in Task
    ]


def _geometry(rig: StereoRig | None) -> dict[str, dict[str, object]] | None:
    """What the page needs of the rig's calibration to tell swapped cameras (docs/capture.md):
    each camera's ``K``, ``dist``, ``R`` (``R_cam_from_world``) and ``t`` (mm)."""
    if rig is None:
        return None
    return {
        side: {
            "K": cam.K.tolist(),
            "dist": cam.dist.tolist(),
            "R": cam.R_cam_from_world.tolist(),
            "t": cam.t_cam_from_world_mm.tolist(),
        }
        for side, cam in (("left", rig.left), ("right", rig.right))
    }


def _size_text(size: tuple[int, int] | None) -> str:
    return f"{size[0]}x{size[1]}" if size is not None else ""


@router.get("/sessions/{session_id}/capture", response_class=HTMLResponse)
def session_capture_page(
    request: Request,
    db: SessionDep,
    user: PageUser,
    session_id: IdPath,
    task: str = "",
    rig: str = "",
) -> Response:
    """The capture page of a session; ``?task=`` chooses the task first (default: finger tapping;
    an unknown value is ignored), ``?rig=`` the rig the cameras are placed as (default the
    session's; the take's trial then names it: ``Trial.rig_id``)."""
    if rig and not (rig.isascii() and rig.isdigit() and len(rig) <= 9):
        return error_page(request, user, status_code=404, message="The rig was not found.")
    try:
        target = capture.session_capture(db, user, session_id, int(rig) if rig else None)
    except NotFoundError as exc:
        return error_page(request, user, status_code=404, message=str(exc))
    try:
        chosen = parse_task(task)
    except InputError:
        chosen = DEFAULT_TASK
    session = target.session
    assert session is not None
    try:
        checked = rig_to_check_against(db, session, target.rig.id)
    except CalibrationMissingError:
        checked = None
    return _allow_camera(
        render(
            request,
            "capture.html",
            user,
            active="patients",
            title=f"Record — {session.patient.code}",
            mode="trial",
            target=target,
            session=session,
            patient=session.patient,
            rig=target.rig,
            trial_rig_id=target.rig.id if target.rig.id != session.rig_id else "",
            other_rigs=[r for r in all_rigs(db) if r.id != target.rig.id],
            left_size=_size_text(target.left_size),
            right_size=_size_text(target.right_size),
            upload_url=f"/sessions/{session.id}/trials",
            geometry=_geometry(checked),
            markers=MARKERS_PER_VIEW.get(chosen, 0),
            tasks=_task_choices(),
            task=chosen.value,
            countdown_s=COUNTDOWN_S,
            hole_s=HOLE_S,
            hole_frames=HOLE_FRAMES,
            duration_s=DEFAULT_DURATION_S,
            sizes=(),
        )
    )


@router.get("/rigs/{rig_id}/capture", response_class=HTMLResponse)
def rig_capture_page(request: Request, db: SessionDep, user: PageUser, rig_id: IdPath) -> Response:
    try:
        target = capture.rig_capture(db, user, rig_id)
    except NotFoundError as exc:
        return error_page(request, user, status_code=404, message=str(exc))
    return _allow_camera(
        render(
            request,
            "capture.html",
            user,
            active="rigs",
            title=f"Record the calibration board — {target.rig.name}",
            mode="calibration",
            target=target,
            session=None,
            patient=None,
            rig=target.rig,
            trial_rig_id="",
            other_rigs=[],
            left_size=_size_text(target.left_size),
            right_size=_size_text(target.right_size),
            upload_url=f"/rigs/{target.rig.id}/calibrations",
            geometry=None,
            markers=0,
            tasks=(),
            task="",
            countdown_s=COUNTDOWN_S,
            hole_s=HOLE_S,
            hole_frames=HOLE_FRAMES,
            duration_s=30,
            sizes=[f"{w}x{h}" for w, h in CALIBRATION_SIZES],
        )
    )

"""The capture page's use cases: what a recording made in the browser must fit.

The capture page (``/sessions/{id}/capture``, docs/capture.md) records a
trial with two cameras; in calibration mode (``/rigs/{id}/capture``) it
records a board video pair for a rig. Both ask the cameras for the image size
the rig was calibrated at, and refuse to record at another: a
:class:`CaptureTarget` says which size each camera must deliver. The
recordings themselves are uploaded through the ordinary trial and calibration
uploads (:mod:`app.services.trials`, :mod:`app.services.calibrations`).
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy.orm import Session

from app.actors import Actor
from app.audit import audit
from app.errors import CalibrationMissingError
from app.models import RecordingSession, Rig
from app.services.calibrations import current_calibration, rig_to_check_against
from app.services.common import load_rig, load_session
from core.camera import ImageSize, StereoRig, rig_from_dict


@dataclass(frozen=True)
class CaptureTarget:
    """Where a take goes and what the cameras must deliver.

    Attributes
    ----------
    rig : Rig
    session : RecordingSession or None
        The session a trial is recorded for; None in calibration mode.
    left_size, right_size : core.camera.ImageSize or None
        The image size each camera was calibrated at (``(width, height)``
        px); None when the rig has no calibration to check against yet.
    problem : str or None
        Why a trial cannot be uploaded now (no usable calibration), in words.
    """

    rig: Rig
    session: RecordingSession | None
    left_size: ImageSize | None
    right_size: ImageSize | None
    problem: str | None = None


def _sizes(rig: StereoRig | None) -> tuple[ImageSize | None, ImageSize | None]:
    if rig is None:
        return None, None
    return rig.left.image_size, rig.right.image_size


def session_capture(
    db: Session, actor: Actor, session_id: int, rig_id: int | None = None
) -> CaptureTarget:
    """The capture page of a session (audited as a read of the session: it names the patient),
    recording with rig ``rig_id`` (default the session's: another placement of the cameras,
    ``Trial.rig_id``).

    Raises
    ------
    app.errors.NotFoundError
        Unknown or deleted session, or unknown rig.
    """
    session = load_session(db, actor, session_id, "read")
    rig = session.rig if rig_id is None else load_rig(db, actor, rig_id, "read")
    problem = None
    try:
        checked = rig_to_check_against(db, session, rig.id)
    except CalibrationMissingError as exc:
        checked, problem = None, str(exc)
    left, right = _sizes(checked)
    audit(db, actor, "read", "session", session.id, session.patient_id)
    db.commit()
    return CaptureTarget(rig, session, left, right, problem)


def rig_capture(db: Session, actor: Actor, rig_id: int) -> CaptureTarget:
    """The capture page of a rig in calibration mode: the sizes of its current calibration.

    Rigs hold no patient data (not audited, as the rig page).
    """
    rig = load_rig(db, actor, rig_id, "read")
    cal = current_calibration(rig)
    checked = (
        rig_from_dict(cal.rig_json, source=f"calibration {cal.id}")
        if cal is not None and cal.rig_json
        else None
    )
    left, right = _sizes(checked)
    db.rollback()
    return CaptureTarget(rig, None, left, right)

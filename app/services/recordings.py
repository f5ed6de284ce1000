"""Recordings: trials (two videos of one hand) and calibrations (a rig file or board videos).

Both arrive as streamed multipart uploads (:mod:`app.uploads`). A use case
here checks every file by decoding it, publishes the files into storage, and
commits the rows that reference them together with the job that will process
them. If anything fails before the commit, the transaction is rolled back and
every file of the upload removed: a rejected upload leaves nothing behind; an
accepted one is referenced by committed rows only.
"""

from __future__ import annotations

import logging
import math
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import jobs
from app.actors import Actor
from app.audit import audit
from app.errors import CalibrationMissingError, ConflictError, InvalidRequestError
from app.models import Calibration, Job, Trial, Video, next_calibration_version, utcnow
from app.services.common import cancel_trial_jobs, load_rig, load_session, load_trial
from app.uploads import (
    InvalidUpload,
    ParsedUpload,
    validate_rig_file,
    validate_stereo_pair,
    validate_video,
)

log = logging.getLogger(__name__)

TRIAL_FILE_FIELDS = {"left_video": ".video", "right_video": ".video"}
TRIAL_TEXT_FIELDS = frozenset({"hand", "offset_frames"})
CALIBRATION_FILE_FIELDS = {"rig_json": ".json", "left_video": ".video", "right_video": ".video"}
CALIBRATION_TEXT_FIELDS = frozenset(
    {"board", "cols", "rows", "square_mm", "marker_mm", "dictionary", "valid_from"}
)
BOARDS = ("chessboard", "charuco")
DEFAULT_DICTIONARY = "DICT_4X4_1000"


def _video_row(upload: ParsedUpload, name: str, info: Any, side: str) -> Video:
    stored = upload.publish(name)
    staged = upload.files[name]
    return Video(
        side=side,
        path=stored.path,
        original_filename=(staged.filename or None) and staged.filename[:255],
        size_bytes=stored.size_bytes,
        sha256=stored.sha256,
        fps=float(info.fps),
        frame_count=int(info.frame_count),
        width=int(info.image_size.width),
        height=int(info.image_size.height),
        codec=(info.fourcc or None) and str(info.fourcc)[:16],
    )


def _add_videos(
    db: Session,
    upload: ParsedUpload,
    left: Any,
    right: Any,
    *,
    trial_id: int | None = None,
    calibration_id: int | None = None,
) -> None:
    """Publish the two checked videos and add their rows (of a trial or a calibration)."""
    for name, info, side in (("left_video", left, "left"), ("right_video", right, "right")):
        video = _video_row(upload, name, info, side)
        video.trial_id = trial_id
        video.calibration_id = calibration_id
        db.add(video)


def _validate_pair(upload: ParsedUpload, *, rig: Any = None) -> tuple[Any, Any, list[str]]:
    left_file = upload.require_file("left_video")
    right_file = upload.require_file("right_video")
    left = validate_video(left_file.path, label="The left video", filename=left_file.filename)
    right = validate_video(right_file.path, label="The right video", filename=right_file.filename)
    warnings = validate_stereo_pair(left, right, rig=rig)
    return left, right, warnings


def _rig_of(db: Session, session: Any) -> Any:
    """The StereoRig that will measure ``session`` (to check the videos against it), or None.

    Raises CalibrationMissingError (409) when the session's rig has no usable
    calibration at all, not even one still being computed.
    """
    from core.camera import rig_from_dict

    try:
        from app.models import calibration_for

        cal = calibration_for(db, session)
    except CalibrationMissingError:
        pending = db.scalars(
            select(Calibration.id)
            .where(Calibration.rig_id == session.rig_id, Calibration.status == "pending")
            .limit(1)
        ).first()
        if pending is None:
            raise
        return None  # checked against the rig once the calibration job is done
    return rig_from_dict(cal.rig_json, source=f"calibration {cal.id}") if cal.rig_json else None


# --------------------------------------------------------------------------- trials


def check_trial_target(db: Session, actor: Actor, session_id: int) -> None:
    """Fail fast before receiving a large body: unknown session (404), no calibration (409)."""
    session = load_session(db, actor, session_id, "create")
    try:
        _rig_of(db, session)
    finally:
        db.rollback()  # end the read transaction; the upload may take a while


def _parse_hand(upload: ParsedUpload) -> str:
    hand = upload.require_field("hand").lower()
    if hand not in ("left", "right"):
        raise InvalidUpload(f"hand must be 'left' or 'right', not {hand[:20]!r}.")
    return hand


def _parse_offset(upload: ParsedUpload) -> float | None:
    raw = (upload.fields.get("offset_frames") or "").strip()
    if not raw:
        return None
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or abs(value) > 10_000:
        raise InvalidUpload(
            "offset_frames must be a number of frames (right frame j = left frame j + K)."
        )
    return value


def create_trial(db: Session, actor: Actor, session_id: int, upload: ParsedUpload) -> TrialOut:
    """Accept a trial upload: check both videos by decoding, store them, queue the analysis.

    Returns
    -------
    TrialOut
        The trial, its job and the recording's warnings.
    """
    hand = _parse_hand(upload)
    offset = _parse_offset(upload)
    session = load_session(db, actor, session_id, "create")
    rig = _rig_of(db, session)
    left, right, warnings = _validate_pair(upload, rig=rig)
    try:
        trial = Trial(session_id=session.id, hand=hand, status="queued", offset_frames=offset)
        db.add(trial)
        db.flush()
        _add_videos(db, upload, left, right, trial_id=trial.id)
        payload: dict[str, Any] = {"warnings": warnings}
        if offset is not None:
            payload["offset_frames"] = offset
        job = jobs.enqueue(db, "analyze_trial", trial_id=trial.id, payload=payload)
        audit(db, actor, "create", "trial", trial.id, session.patient_id)
        db.commit()
    except BaseException:
        db.rollback()
        upload.discard()
        raise
    return TrialOut(trial=trial, job_id=job.id, warnings=warnings)


class TrialOut:
    """A trial with the id of its newest job and the upload's warnings."""

    def __init__(self, trial: Trial, job_id: int | None, warnings: list[str] | None = None):
        self.trial = trial
        self.job_id = job_id
        self.warnings = warnings or []


def _latest_job_id(
    db: Session, *, trial_id: int | None = None, calibration_id: int | None = None
) -> int | None:
    query = select(Job.id)
    if trial_id is not None:
        query = query.where(Job.trial_id == trial_id)
    else:
        query = query.where(Job.calibration_id == calibration_id)
    return db.scalars(query.order_by(Job.id.desc()).limit(1)).first()


def trial_view(db: Session, trial: Trial) -> dict[str, Any]:
    """The ``TrialRead`` fields of a trial."""
    return {
        "id": trial.id,
        "session_id": trial.session_id,
        "hand": trial.hand,
        "status": trial.status,
        "offset_frames": trial.offset_frames,
        "created_at": trial.created_at,
        "job_id": _latest_job_id(db, trial_id=trial.id),
        "has_result": trial.result is not None,
        "videos": list(trial.videos),
    }


def list_trials(db: Session, actor: Actor, session_id: int) -> list[dict[str, Any]]:
    session = load_session(db, actor, session_id, "list")
    trials = [t for t in session.trials if t.deleted_at is None]
    views = [trial_view(db, t) for t in trials]
    audit(db, actor, "list", "trial", None, session.patient_id)
    db.commit()
    return views


def get_trial(db: Session, actor: Actor, trial_id: int) -> dict[str, Any]:
    trial = load_trial(db, actor, trial_id, "read")
    view = trial_view(db, trial)
    audit(db, actor, "read", "trial", trial.id, trial.session.patient_id)
    db.commit()
    return view


def delete_trial(db: Session, actor: Actor, trial_id: int) -> None:
    """Soft-delete a trial: it answers 404 and leaves the lists; rows, files, audit stay.

    Its queued or running job is cancelled (nobody could see the result).
    """
    trial = load_trial(db, actor, trial_id, "delete")
    trial.deleted_at = utcnow()
    cancel_trial_jobs(db, select(Trial.id).where(Trial.id == trial.id))
    audit(db, actor, "delete", "trial", trial.id, trial.session.patient_id)
    db.commit()


def get_job(db: Session, actor: Actor, job_id: int) -> Job:
    """A job's status. Holds no clinical values, so it is not audited (clients poll it)."""
    from app.errors import NotFoundError

    job = db.get(Job, job_id)
    if job is None:
        raise NotFoundError(f"The job {job_id} does not exist; check the id.")
    db.rollback()
    return job


# --------------------------------------------------------------------------- calibrations


def _valid_from(upload: ParsedUpload, *, first: bool) -> datetime:
    raw = (upload.fields.get("valid_from") or "").strip()
    if raw:
        try:
            value = datetime.fromisoformat(raw.replace("Z", "+00:00"))
        except ValueError as exc:
            raise InvalidUpload(
                "valid_from must be an ISO 8601 date-time such as 2026-01-31T08:00:00Z."
            ) from exc
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)
    # A rig's first calibration also covers sessions recorded before it was uploaded.
    return datetime(1970, 1, 1, tzinfo=UTC) if first else utcnow()


def _board_fields(upload: ParsedUpload) -> dict[str, Any]:
    board = upload.require_field("board").lower()
    if board not in BOARDS:
        raise InvalidUpload(f"board must be 'chessboard' or 'charuco', not {board[:20]!r}.")

    def number(name: str, kind: type, low: float, high: float) -> Any:
        raw = upload.require_field(name)
        try:
            value = kind(raw)
        except ValueError:
            value = None
        if value is None or not math.isfinite(value) or not low <= value <= high:
            raise InvalidUpload(f"{name} must be a {kind.__name__} between {low:g} and {high:g}.")
        return value

    fields: dict[str, Any] = {
        "board": board,
        "cols": number("cols", int, 2, 200),
        "rows": number("rows", int, 2, 200),
        "square_mm": number("square_mm", float, 0.1, 1000.0),
    }
    if board == "charuco":
        fields["marker_mm"] = number("marker_mm", float, 0.05, 1000.0)
        if fields["marker_mm"] >= fields["square_mm"]:
            raise InvalidUpload("marker_mm must be smaller than square_mm for a ChArUco board.")
        dictionary = (upload.fields.get("dictionary") or DEFAULT_DICTIONARY).strip()
        import cv2

        if not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
            raise InvalidUpload(f"dictionary {dictionary[:40]!r} is not an ArUco dictionary name.")
        fields["dictionary"] = dictionary
    from core.boards import BoardSpec

    try:  # the measurement library's own rules for a board, too
        BoardSpec(
            kind=board,  # type: ignore[arg-type]  # checked against BOARDS above
            cols=fields["cols"],
            rows=fields["rows"],
            square_mm=fields["square_mm"],
            marker_mm=fields.get("marker_mm"),
            dictionary=fields.get("dictionary"),
        )
    except ValueError as exc:
        raise InvalidUpload(f"The board description is invalid: {exc}.") from exc
    return fields


def create_calibration(
    db: Session, actor: Actor, rig_id: int, upload: ParsedUpload
) -> tuple[Calibration, int | None]:
    """A new calibration version of a rig, from a rig file (ready at once) or board videos (a job).

    Returns
    -------
    (Calibration, job id or None)
    """
    rig = load_rig(db, actor, rig_id, "create")
    has_rig_file = "rig_json" in upload.files
    has_videos = "left_video" in upload.files or "right_video" in upload.files
    if has_rig_file == has_videos:
        raise InvalidUpload(
            "Send either a rig file (rig_json) or two board videos (left_video and right_video"
            " with board, cols, rows, square_mm), not both and not neither."
        )
    first = (
        db.scalars(select(Calibration.id).where(Calibration.rig_id == rig.id).limit(1)).first()
        is None
    )
    valid_from = _valid_from(upload, first=first)
    job_id: int | None = None
    if has_rig_file:
        from core.camera import rig_to_dict

        stereo = validate_rig_file(upload.files["rig_json"].path)
        doc = rig_to_dict(stereo)
        rms = (stereo.quality or {}).get("rms_px")
        try:
            cal = Calibration(
                rig_id=rig.id,
                version=next_calibration_version(db, rig.id),
                valid_from=valid_from,
                rig_json=doc,
                rms_px=float(rms) if isinstance(rms, int | float) and math.isfinite(rms) else None,
                quality=dict(stereo.quality or {}) or None,
                source="rig_file",
                status="ready",
                created_by_user_id=actor.user_id,
            )
            db.add(cal)
            db.flush()
            audit(db, actor, "create", "calibration", cal.id)
            db.commit()
        except IntegrityError as exc:
            db.rollback()
            raise _concurrent_calibration(rig.id) from exc
        except BaseException:
            db.rollback()
            raise
        return cal, None

    board = _board_fields(upload)
    left, right, _warnings = _validate_pair(upload)
    try:
        cal = Calibration(
            rig_id=rig.id,
            version=next_calibration_version(db, rig.id),
            valid_from=valid_from,
            source="board_videos",
            status="pending",
            board=board,
            created_by_user_id=actor.user_id,
        )
        db.add(cal)
        db.flush()
        _add_videos(db, upload, left, right, calibration_id=cal.id)
        job = jobs.enqueue(db, "calibrate", calibration_id=cal.id, payload={"board": board})
        job_id = job.id
        audit(db, actor, "create", "calibration", cal.id)
        db.commit()
    except IntegrityError as exc:
        db.rollback()
        upload.discard()
        raise _concurrent_calibration(rig.id) from exc
    except BaseException:
        db.rollback()
        upload.discard()
        raise
    return cal, job_id


def _concurrent_calibration(rig_id: int) -> ConflictError:
    """Two uploads took the same version number (UNIQUE (rig_id, version)); one must retry."""
    return ConflictError(
        f"Another calibration of rig {rig_id} was stored at the same moment; send this one again."
    )


def calibration_view(db: Session, cal: Calibration) -> dict[str, Any]:
    job_id = _latest_job_id(db, calibration_id=cal.id)
    error = None
    if job_id is not None and cal.status == "failed":
        job = db.get(Job, job_id)
        error = job.error if job is not None else None
    return {
        "id": cal.id,
        "rig_id": cal.rig_id,
        "version": cal.version,
        "valid_from": cal.valid_from,
        "status": cal.status,
        "source": cal.source,
        "rms_px": cal.rms_px,
        "quality": cal.quality,
        "board": cal.board,
        "created_at": cal.created_at,
        "job_id": job_id,
        "error": error,
    }


def list_calibrations(db: Session, actor: Actor, rig_id: int) -> list[dict[str, Any]]:
    rig = load_rig(db, actor, rig_id, "list")
    views = [calibration_view(db, c) for c in rig.calibrations]
    db.rollback()
    return views


def get_calibration(db: Session, actor: Actor, calibration_id: int) -> dict[str, Any]:
    from app.errors import NotFoundError

    cal = db.get(Calibration, calibration_id)
    if cal is None:
        raise NotFoundError(f"The calibration {calibration_id} does not exist; check the id.")
    view = calibration_view(db, cal)
    db.rollback()
    return view


def rig_file_of(db: Session, actor: Actor, calibration_id: int) -> dict[str, Any]:
    """The rig file document of a ready calibration (409 while it is being computed)."""
    view = get_calibration(db, actor, calibration_id)
    cal = db.get(Calibration, calibration_id)
    if cal is None or cal.rig_json is None:
        raise InvalidRequestError(
            f"The calibration {calibration_id} has no rig file (status {view['status']})."
        )
    return dict(cal.rig_json)


__all__ = [
    "CALIBRATION_FILE_FIELDS",
    "CALIBRATION_TEXT_FIELDS",
    "TRIAL_FILE_FIELDS",
    "TRIAL_TEXT_FIELDS",
    "TrialOut",
    "check_trial_target",
    "create_calibration",
    "create_trial",
    "delete_trial",
    "get_calibration",
    "get_job",
    "get_trial",
    "list_calibrations",
    "list_trials",
    "load_trial",
]

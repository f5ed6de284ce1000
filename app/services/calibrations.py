"""Calibrations of a rig: which one a session uses, uploads, their verdict, reads.

A calibration arrives as a rig file (ready at once) or as two board
recordings (``pending`` until the worker's ``calibrate`` job makes it
``ready``). Its quality verdict is judged once, when it becomes ready
(``app.models.calibration_verdict``), and stored with it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import and_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import job_views, jobs
from app.actors import Actor
from app.audit import audit, audit_failure
from app.errors import CalibrationMissingError, ConflictError, InvalidRequestError, NotFoundError
from app.models import (
    Calibration,
    Job,
    RecordingSession,
    Rig,
    Video,
    calibration_verdict,
    next_calibration_version,
)
from app.services.calibration_form import board_fields, valid_from_field
from app.services.common import load_rig
from app.services.videos import add_videos, check_video_pair, times_file
from app.storage import Storage
from app.upload_checks import validate_rig_file
from app.uploads import InvalidUpload, ParsedUpload
from core.boards import BoardSpec
from core.camera import StereoRig, rig_from_dict, rig_to_dict

if TYPE_CHECKING:  # OpenCV and SciPy: imported by the worker that calibrates
    from core.calibration import CalibrationResult

CALIBRATION_FILE_FIELDS = {
    "rig_json": ".json",
    "left_video": ".video",
    "right_video": ".video",
    # each frame's capture time (as a trial's): the capture page sends them with a take
    "left_times": ".csv",
    "right_times": ".csv",
}
CALIBRATION_TEXT_FIELDS = frozenset(
    {"board", "cols", "rows", "square_mm", "marker_mm", "dictionary", "legacy", "valid_from"}
)


# --------------------------------------------------------------------------- which one


def calibration_for(
    db: Session, session: RecordingSession, rig_id: int | None = None
) -> Calibration:
    """The calibration an analysis of ``session`` uses (of one of its trials recorded by
    rig ``rig_id``, when that is not the session's rig: ``Trial.rig_id``).

    The session's own override (``session.calibration_id``) if set and the rig is
    the session's, otherwise the newest ``ready`` calibration of the rig whose
    ``valid_from`` is not after ``session.recorded_at`` (ties: the highest version).

    Raises
    ------
    app.errors.CalibrationMissingError
        When the override is not ready, or the rig has no ready calibration
        valid at the session's time (the message names a calibration that was to
        cover it and failed).
    """
    rig_id = session.rig_id if rig_id is None else rig_id
    if session.calibration_id is not None and rig_id == session.rig_id:
        cal = db.get(Calibration, session.calibration_id)
        if cal is not None and cal.status == "failed":
            raise CalibrationMissingError(
                f"{_failed(db, cal)} It was chosen for session {session.id}: choose a ready"
                " calibration or clear the choice, then measure the trial again."
            )
        if cal is None or cal.status != "ready":
            raise CalibrationMissingError(
                f"calibration {session.calibration_id} chosen for session {session.id} is not "
                "ready; choose a ready calibration or clear the choice."
            )
        return cal
    valid = (Calibration.rig_id == rig_id, Calibration.valid_from <= session.recorded_at)
    newest = (Calibration.valid_from.desc(), Calibration.version.desc())
    cal = db.scalars(
        select(Calibration).where(*valid, Calibration.status == "ready").order_by(*newest).limit(1)
    ).first()
    if cal is not None:
        return cal
    failed = db.scalars(
        select(Calibration).where(*valid, Calibration.status == "failed").order_by(*newest).limit(1)
    ).first()
    if failed is not None:
        # a rig's first usable calibration covers every session (_valid_from)
        again = (
            "upload a corrected calibration of this rig (it will cover this session)"
            if _first(db, rig_id)
            else "upload a corrected calibration of this rig with valid_from before"
            f" {session.recorded_at:%Y-%m-%d %H:%M} UTC"
        )
        raise CalibrationMissingError(
            f"{_failed(db, failed)} No other calibration of rig {rig_id} is valid on"
            f" {session.recorded_at:%Y-%m-%d %H:%M} UTC: {again}, then measure the trial again."
        )
    raise CalibrationMissingError(
        f"rig {rig_id} has no ready calibration valid on "
        f"{session.recorded_at:%Y-%m-%d %H:%M} UTC; upload a calibration for this rig "
        "first (valid from a date before the session)."
    )


def _failed(db: Session, cal: Calibration) -> str:
    """``"the calibration v2 of rig 5 (…) failed: <its job's error>"`` as a sentence."""
    job = job_views.latest_job(db, calibration_id=cal.id)
    why = f": {job.error.rstrip('.')}" if job is not None and job.error else ""
    return f"The calibration v{cal.version} of rig {cal.rig_id} (id {cal.id}) failed{why}."


def _first(db: Session, rig_id: int) -> bool:
    """Whether a new calibration of the rig would be its first: none is ready or being
    computed (a failed one does not count; its replacement covers the earlier sessions)."""
    usable = select(Calibration.id).where(
        Calibration.rig_id == rig_id, Calibration.status.in_(("ready", "pending"))
    )
    return db.scalars(usable.limit(1)).first() is None


def rig_to_check_against(
    db: Session, session: RecordingSession, rig_id: int | None = None
) -> StereoRig | None:
    """The rig that will measure the trials of ``session`` recorded by rig ``rig_id`` (default
    the session's rig), to check uploaded videos against it; or None.

    None while no calibration measures the session yet but one being computed may
    (the session's chosen one, or one of the rig valid from before the session):
    the analysis waits for it (``app.jobs.waits_for_calibration``) and the videos
    are then checked against it by the analysis.

    Raises
    ------
    CalibrationMissingError
        No calibration of that rig can measure the session, ready or being computed (409).
    """
    try:
        cal = calibration_for(db, session, rig_id)
    except CalibrationMissingError:
        rig_id = session.rig_id if rig_id is None else rig_id
        if session.calibration_id is not None and rig_id == session.rig_id:
            covers = Calibration.id == session.calibration_id
        else:
            covers = and_(
                Calibration.rig_id == rig_id, Calibration.valid_from <= session.recorded_at
            )
        pending = db.scalars(
            select(Calibration.id).where(covers, Calibration.status == "pending").limit(1)
        ).first()
        if pending is None:
            raise
        return None
    return rig_from_dict(cal.rig_json, source=f"calibration {cal.id}") if cal.rig_json else None


# --------------------------------------------------------------------------- upload


def audit_rejected_upload(db: Session, actor: Actor, rig_id: int) -> None:
    """Record a calibration upload refused for its content (outcome ``invalid``); commits."""
    audit_failure(db, actor, "create", "calibration", None, None, outcome="invalid")


def _concurrent_calibration(rig_id: int) -> ConflictError:
    """Two uploads took the same version number (UNIQUE (rig_id, version)); one must retry."""
    return ConflictError(
        f"Another calibration of rig {rig_id} was stored at the same moment; send this one again."
    )


def _store(
    db: Session,
    upload: ParsedUpload,
    cal: Calibration,
    actor: Actor,
    *,
    with_it: Callable[[], None] | None = None,
) -> None:
    """Add ``cal`` (and ``with_it()``'s rows) and commit with its audit event.

    On any failure the transaction is rolled back and the upload's files removed.
    """
    try:
        db.add(cal)
        db.flush()
        if with_it is not None:
            with_it()
        audit(db, actor, "create", "calibration", cal.id)
        db.commit()
    except IntegrityError as exc:
        db.rollback()
        upload.discard()
        raise _concurrent_calibration(cal.rig_id) from exc
    except BaseException:
        db.rollback()
        upload.discard()
        raise


def _from_rig_file(
    db: Session, actor: Actor, rig: Rig, upload: ParsedUpload, valid_from: datetime
) -> Calibration:
    stereo = validate_rig_file(upload.files["rig_json"].path)
    quality = dict(stereo.quality or {})
    rms = quality.get("rms_px")
    rms_px = float(rms) if isinstance(rms, int | float) and math.isfinite(rms) else None
    cal = Calibration(
        rig_id=rig.id,
        version=next_calibration_version(db, rig.id),
        valid_from=valid_from,
        rig_json=rig_to_dict(stereo),
        rms_px=rms_px,
        quality=quality or None,
        source="rig_file",
        status="ready",
        created_by_user_id=actor.user_id,
    )
    _store(db, upload, cal, actor)
    return cal


def _from_board_videos(
    db: Session, actor: Actor, rig: Rig, upload: ParsedUpload, valid_from: datetime
) -> tuple[Calibration, int]:
    board = board_fields(upload)
    pair = check_video_pair(upload)
    cal = Calibration(
        rig_id=rig.id,
        version=next_calibration_version(db, rig.id),
        valid_from=valid_from,
        source="board_videos",
        status="pending",
        board=board,
        created_by_user_id=actor.user_id,
    )
    queued: list[Job] = []

    def videos_and_job() -> None:
        add_videos(db, upload, pair, calibration_id=cal.id)
        queued.append(
            jobs.enqueue(db, "calibrate", calibration_id=cal.id, payload={"board": board})
        )

    _store(db, upload, cal, actor, with_it=videos_and_job)
    return cal, queued[0].id


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
    valid_from = valid_from_field(upload, first=_first(db, rig.id))
    if has_rig_file:
        return _from_rig_file(db, actor, rig, upload, valid_from), None
    return _from_board_videos(db, actor, rig, upload, valid_from)


# --------------------------------------------------------------------------- reads


def calibration_view(db: Session, cal: Calibration) -> dict[str, Any]:
    """The ``CalibrationRead`` fields of a calibration."""
    job = job_views.latest_job(db, calibration_id=cal.id)
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
        "job_id": job.id if job is not None else None,
        "error": job.error if job is not None and cal.status == "failed" else None,
    }


def list_calibrations(db: Session, actor: Actor, rig_id: int) -> list[dict[str, Any]]:
    rig = load_rig(db, actor, rig_id, "list")
    views = [calibration_view(db, c) for c in rig.calibrations]
    db.rollback()
    return views


def get_calibration(db: Session, actor: Actor, calibration_id: int) -> dict[str, Any]:
    cal = db.get(Calibration, calibration_id)
    if cal is None:
        raise NotFoundError(f"The calibration {calibration_id} does not exist; check the id.")
    view = calibration_view(db, cal)
    db.rollback()
    return view


def rig_file_of(db: Session, actor: Actor, calibration_id: int) -> dict[str, Any]:
    """The rig file document of a ready calibration (409 while it is computed, or failed)."""
    view = get_calibration(db, actor, calibration_id)
    cal = db.get(Calibration, calibration_id)
    if cal is None or cal.rig_json is None:
        state = f"failed: {view['error']}" if view["status"] == "failed" else "is being computed"
        raise ConflictError(
            f"The calibration {calibration_id} has no rig file: it {state.rstrip('.')}. Retry"
            f" when GET /api/v1/calibrations/{calibration_id} says ready (a failed one needs"
            " its board videos again, or a rig file)."
        )
    return dict(cal.rig_json)


# --------------------------------------------------------------------------- pages


@dataclass(frozen=True)
class CalibrationRow:
    """One calibration version on its rig's page: the row, its newest job, its verdict."""

    cal: Calibration
    job: Job | None

    @property
    def verdict(self) -> str | None:
        return self.cal.verdict

    @property
    def reasons(self) -> list[str]:
        return list(self.cal.verdict_reasons or [])


def calibration_rows(db: Session, rig: Rig) -> list[CalibrationRow]:
    """The rig's calibrations, newest version first, each with its newest job."""
    newest_jobs = job_views.latest_jobs(db, calibration_ids=[c.id for c in rig.calibrations])
    return [
        CalibrationRow(cal=cal, job=newest_jobs.get(cal.id))
        for cal in sorted(rig.calibrations, key=lambda c: c.version, reverse=True)
    ]


def current_calibration(rig: Rig) -> Calibration | None:
    """The rig's ready calibration with the latest ``valid_from`` (then version), if any."""
    ready = [c for c in rig.calibrations if c.status == "ready"]
    return max(ready, key=lambda c: (c.valid_from, c.version)) if ready else None


# --------------------------------------------------------------------------- the worker's side


@dataclass(frozen=True)
class CalibrationInputs:
    """What the worker's ``calibrate`` job needs: the two board recordings and the board."""

    calibration_id: int
    left: Path
    right: Path
    board: BoardSpec
    left_times: Path | None = None
    right_times: Path | None = None


def calibration_inputs(
    db: Session,
    storage: Storage,
    calibration_id: int | None,
    *,
    board: Mapping[str, Any] | None = None,
) -> CalibrationInputs:
    """The board videos and board of a pending calibration (``board``: the job's, if the row has none).

    Raises
    ------
    NotFoundError, InvalidRequestError
        The calibration is gone, or lacks a video or its board description.
    core.errors.InputError
        The stored board description is incomplete (the message says which field).
    """
    cal = db.get(Calibration, calibration_id) if calibration_id else None
    if cal is None:
        raise NotFoundError(f"calibration {calibration_id} no longer exists.")
    videos = {v.side: v for v in db.scalars(select(Video).where(Video.calibration_id == cal.id))}
    if set(videos) != {"left", "right"}:
        raise InvalidRequestError(
            f"calibration {cal.id} needs a left and a right board video; upload both."
        )
    board_doc = cal.board or board
    if not board_doc:
        raise InvalidRequestError(
            f"calibration {cal.id} has no board description; give the board's kind, "
            "cols, rows and square_mm."
        )
    return CalibrationInputs(
        calibration_id=cal.id,
        left=storage.absolute(videos["left"].path),
        right=storage.absolute(videos["right"].path),
        # Reads both stored forms (BoardSpec.to_dict()'s "kind" and the upload form's "board").
        board=BoardSpec.from_dict(dict(board_doc)),
        left_times=times_file(storage, videos["left"]),
        right_times=times_file(storage, videos["right"]),
    )


def store_calibration(db: Session, calibration_id: int, outcome: CalibrationResult) -> None:
    """Make a pending calibration ``ready`` with the computed rig, its quality and verdict.

    In the caller's transaction. The verdict and its reasons are stored in
    their columns and also kept in the quality figures (as the API shows them).
    """
    verdict, reasons = calibration_verdict(outcome.quality)
    quality = {**outcome.quality, "verdict": verdict, "verdict_reasons": reasons}
    rig_doc = rig_to_dict(outcome.rig)
    rig_doc["quality"] = {**rig_doc.get("quality", {}), **quality}
    rms_px = quality.get("rms_px")
    db.execute(
        update(Calibration)
        .where(Calibration.id == calibration_id)
        .values(
            status="ready",
            rig_json=rig_doc,
            quality=quality,
            rms_px=float(rms_px) if rms_px is not None else None,
            verdict=verdict,
            verdict_reasons=reasons,
        )
        .execution_options(synchronize_session=False)
    )

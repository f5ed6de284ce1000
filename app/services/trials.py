"""Trials (two videos of one hand) and the jobs measuring them.

A trial arrives as a streamed multipart upload (:mod:`app.uploads`): both
videos are checked by decoding, published into storage, and committed together
with the trial row and its analysis job. If anything fails before the commit,
the transaction is rolled back and every file of the upload removed: a
rejected upload leaves nothing behind; an accepted one is referenced by
committed rows only.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import and_, func, or_, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import job_views, jobs
from app.actors import ADMIN_SCOPE, Actor
from app.audit import audit, audit_failure
from app.errors import ConflictError, NotFoundError, PermissionDeniedError
from app.models import SIDES, ApiClient, Job, Rig, Trial, Video, utcnow
from app.schemas import TrialRatingUpdate
from app.services.calibrations import rig_to_check_against
from app.services.changes import audit_update, changed_fields
from app.services.common import (
    cancel_trial_jobs,
    load_session,
    load_trial,
    not_found,
    trial_is_visible,
    visible_session,
)
from app.services.videos import CheckedVideo, add_videos, check_video_pair
from app.storage import Storage
from app.upload_checks import sent_before
from app.uploads import InvalidUpload, ParsedUpload
from core.camera import ImageSize
from core.errors import InputError
from core.tasks import DEFAULT_TASK, TASKS
from core.timing import read_times_csv
from core.video import VideoInfo

TRIAL_FILE_FIELDS = {
    "left_video": ".video",
    "right_video": ".video",
    "left_times": ".csv",
    "right_times": ".csv",
}
TRIAL_TEXT_FIELDS = frozenset({"hand", "offset_frames", "task", "rig_id", "take_id"})
"""``take_id``: the client's key of one take (the capture page's, an integrator's), which
makes sending it again after a lost answer safe (docs/capture.md, docs/api.md)."""
PAGE_TRIAL_TEXT_FIELDS = TRIAL_TEXT_FIELDS
_TAKE_ID = re.compile(r"[A-Za-z0-9_-]{8,64}")
_ID = re.compile(r"[0-9]{1,9}")  # a row id (an int4 on PostgreSQL); no sign, no other digits
MAX_OFFSET_FRAMES = 10_000  # as RevisionCreate.offset_frames
RESULTS_READ = "results:read"


@dataclass(frozen=True)
class TrialOut:
    """A new trial, the id of the job measuring it, the upload's warnings and its quick check."""

    trial: Trial
    job_id: int
    warnings: list[str] = field(default_factory=list)
    take: dict[str, dict[str, object]] = field(default_factory=dict)
    """Per side (``left``, ``right``): frames, length, rate reached, frames lost
    (:meth:`app.services.videos.CheckedVideo.take`), known before the analysis."""
    stored_before: bool = False
    """The take (``take_id``) was stored before: this is that trial, nothing new was stored."""


def check_trial_target(db: Session, actor: Actor, session_id: int) -> None:
    """Fail fast before receiving a large body: unknown session (404). Whether a calibration
    can measure the trial (409) depends on its rig, a field of the body (``rig_id``):
    :func:`create_trial` checks it before decoding the videos."""
    try:
        load_session(db, actor, session_id, "create")
    finally:
        db.rollback()  # end the read transaction; the upload may take a while


def _parse_hand(upload: ParsedUpload) -> str:
    hand = upload.require_field("hand").lower()
    if hand not in ("left", "right"):
        raise InvalidUpload(
            f"hand must be 'left' or 'right', not {hand[:20]!r}.", field="hand", kind="enum"
        )
    return hand


def _parse_task(upload: ParsedUpload) -> str:
    """The upload's ``task`` (finger tapping when absent or empty)."""
    raw = (upload.fields.get("task") or "").strip().lower()
    if not raw:
        return DEFAULT_TASK.value
    if raw not in TASKS:
        raise InvalidUpload(
            f"task must be one of {', '.join(TASKS)}, not {raw[:40]!r}.", field="task", kind="enum"
        )
    return raw


def _parse_rig(db: Session, upload: ParsedUpload, session_rig_id: int) -> int | None:
    """The upload's ``rig_id``: None when absent or the session's own rig."""
    raw = (upload.fields.get("rig_id") or "").strip()
    if not raw:
        return None
    if not (raw.isascii() and raw.isdigit()):
        raise InvalidUpload(
            f"rig_id must be a rig's id, a whole number such as 3, not {raw[:20]!r}; give the id"
            " of the rig that recorded the trial (GET /api/v1/rigs), or leave it out for the"
            " session's rig.",
            field="rig_id",
            kind="int_parsing",
        )
    if not _ID.fullmatch(raw) or db.get(Rig, int(raw)) is None:
        raise InvalidUpload(
            f"rig_id {raw[:20]!r} names no rig; give the id of the rig that recorded the trial"
            " (GET /api/v1/rigs), or leave it out for the session's rig.",
            field="rig_id",
        )
    return None if int(raw) == session_rig_id else int(raw)


def _parse_offset(upload: ParsedUpload) -> float | None:
    raw = (upload.fields.get("offset_frames") or "").strip()
    if not raw:
        return None
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or abs(value) > MAX_OFFSET_FRAMES:
        raise InvalidUpload(
            f"offset_frames must be a number of frames from -{MAX_OFFSET_FRAMES} to"
            f" {MAX_OFFSET_FRAMES} (right frame j = left frame j + K), not {raw[:20]!r};"
            " leave it out to estimate the offset from the marker motion.",
            field="offset_frames",
        )
    return value


def _parse_take_id(upload: ParsedUpload) -> str | None:
    raw = (upload.fields.get("take_id") or "").strip()
    if not raw:
        return None
    if not _TAKE_ID.fullmatch(raw):
        raise InvalidUpload(
            "take_id must be 8 to 64 letters, digits, '-' or '_'.",
            field="take_id",
            kind="string_pattern_mismatch",
        )
    return raw


def _stored_take(db: Session, session_id: int, take_id: str | None) -> Trial | None:
    if take_id is None:
        return None
    trial = db.scalars(
        select(Trial).where(Trial.session_id == session_id, Trial.take_id == take_id)
    ).first()
    return trial


def _take_differences(
    stored: Trial, upload: ParsedUpload, request: Mapping[str, object]
) -> list[str]:
    """What of the upload differs from the take stored under its ``take_id``: the fields
    of ``request`` (hand, task, rig_id, offset_frames) and each file's SHA-256."""
    differ = [name for name, value in request.items() if getattr(stored, name) != value]
    videos = {v.side: v for v in stored.videos}
    for side in SIDES:
        video = videos.get(side)
        sent = upload.require_file(f"{side}_video").incoming.sha256
        if video is None or video.sha256 != sent:
            differ.append(f"{side}_video")
        times = upload.files.get(f"{side}_times")
        if (times.incoming.sha256 if times else None) != (video.times_sha256 if video else None):
            differ.append(f"{side}_times")
    return differ


def _stored_take_check(storage: Storage, trial: Trial) -> dict[str, dict[str, object]]:
    """The quick check of a stored trial's recordings (``take``), as its upload answered it:
    from its videos' rows and their stored timestamps files."""
    take: dict[str, dict[str, object]] = {}
    for video in trial.videos:
        times = None
        if video.times_path:
            try:
                times = read_times_csv(storage.absolute(video.times_path))
            except (InputError, OSError):
                continue  # the file is missing from storage: that side's check is not known
        info = VideoInfo(
            path=storage.absolute(video.path),
            fps=video.fps,
            frame_count=video.frame_count,
            image_size=ImageSize(video.width, video.height),
            fourcc=video.codec or "",
        )
        take[video.side] = CheckedVideo(info, times).take()
    return take


def _answer_stored_take(
    db: Session,
    actor: Actor,
    stored: Trial,
    upload: ParsedUpload,
    request: Mapping[str, object],
) -> TrialOut:
    """The answer to a take sent again: the trial stored the first time, when the upload
    is that take unchanged (a retry after a lost answer); else 409, audited as denied."""
    patient_id = stored.session.patient_id
    if not trial_is_visible(stored):  # sent again after its deletion
        audit_failure(db, actor, "create", "trial", None, patient_id, outcome="denied")
        raise ConflictError(
            "This take was stored and then deleted; record a new take to upload it again.",
            audited=True,
        )
    differ = _take_differences(stored, upload, request)
    if differ:
        audit_failure(db, actor, "create", "trial", stored.id, patient_id, outcome="denied")
        raise ConflictError(
            f"The take_id {stored.take_id} belongs to trial {stored.id} of this session, stored"
            f" with another {', '.join(differ)}; give every take its own take_id (send this"
            " one with a new take_id), or send that take unchanged to get its trial.",
            audited=True,
        )
    job = job_views.latest_job(db, trial_id=stored.id)
    take = _stored_take_check(upload.storage, stored)
    audit(db, actor, "read", "trial", stored.id, patient_id)
    db.commit()
    return TrialOut(trial=stored, job_id=job.id if job else 0, take=take, stored_before=True)


def create_trial(db: Session, actor: Actor, session_id: int, upload: ParsedUpload) -> TrialOut:
    """Accept a trial upload: check both videos by decoding (and their timestamps files,
    if any), store them, queue the analysis.

    A take the capture page sends again (the same ``take_id`` in the session, after a
    lost connection) stores nothing: the answer is the trial stored first
    (``stored_before``), with its quick check. A ``take_id`` sent with another hand, task,
    rig, offset or other files than its take was stored with is refused (409).
    """
    hand = _parse_hand(upload)
    task = _parse_task(upload)
    offset = _parse_offset(upload)
    take_id = _parse_take_id(upload)
    session = load_session(db, actor, session_id, "create")
    rig_id = _parse_rig(db, upload, session.rig_id)
    stored = _stored_take(db, session.id, take_id)
    if stored is not None:
        request = {"hand": hand, "task": task, "rig_id": rig_id, "offset_frames": offset}
        return _answer_stored_take(db, actor, stored, upload, request)
    rig = rig_to_check_against(db, session, rig_id)
    pair = check_video_pair(upload, rig=rig)
    warnings = [*pair.warnings, *_sent_before(db, session.id, upload)]
    try:
        trial = Trial(
            session_id=session.id,
            hand=hand,
            task=task,
            rig_id=rig_id,
            status="queued",
            offset_frames=offset,
            take_id=take_id,
        )
        db.add(trial)
        try:
            db.flush()
        except IntegrityError:
            raise ConflictError(
                "This take is being stored by another upload; open the session page to find it."
            ) from None
        add_videos(db, upload, pair, trial_id=trial.id)
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
    take = {side: pair.side(side).take() for side in ("left", "right")}
    return TrialOut(trial=trial, job_id=job.id, warnings=warnings, take=take)


def _sent_before(db: Session, session_id: int, upload: ParsedUpload) -> list[str]:
    """A warning when the session already holds a trial of the same two videos: sent twice
    (a retry after a lost answer, a form posted twice) without a ``take_id``, or sent again
    with the cameras the other way round (:func:`app.upload_checks.sent_before`)."""
    digests = {side: upload.require_file(f"{side}_video").incoming.sha256 for side in SIDES}
    rows = db.execute(
        select(Video.trial_id, Video.side, Video.sha256)
        .join(Trial, Trial.id == Video.trial_id)
        .where(Trial.session_id == session_id, Trial.deleted_at.is_(None),
               Video.sha256.in_(set(digests.values())))
    ).all()  # fmt: skip
    return sent_before(
        ((t, side, d) for t, side, d in rows if t is not None),
        left_sha256=digests["left"],
        right_sha256=digests["right"],
    )


def audit_rejected_upload(db: Session, actor: Actor, session_id: int) -> None:
    """Record a trial upload refused for its content (outcome ``invalid``); commits."""
    session = visible_session(db, session_id)
    patient_id = session.patient_id if session is not None else None
    audit_failure(db, actor, "create", "trial", None, patient_id, outcome="invalid")


def trial_view(db: Session, trial: Trial) -> dict[str, Any]:
    """The ``TrialRead`` fields of a trial."""
    job = job_views.latest_job(db, trial_id=trial.id)
    return {
        "id": trial.id,
        "session_id": trial.session_id,
        "hand": trial.hand,
        "task": trial.task,
        "rig_id": trial.rig_id if trial.rig_id is not None else trial.session.rig_id,
        "status": trial.status,
        "offset_frames": trial.offset_frames,
        "created_at": trial.created_at,
        "job_id": job.id if job is not None else None,
        "has_result": trial.result is not None,
        "videos": list(trial.videos),
        "clinician_rating": trial.clinician_rating,
        "comment": trial.rating_comment,
        "rated_at": trial.rated_at,
        "rated_by_user_id": trial.rated_by_user_id,
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


def rate_trial(db: Session, actor: Actor, trial_id: int, data: TrialRatingUpdate) -> Trial:
    """Set the clinician's rating (0–4) and comment of one trial; omitted fields stay.

    The rating belongs to the trial's hand (and task); who rated and when change only
    with the rating itself (a comment corrected by a colleague leaves the rating theirs).
    Audited as an update of the trial naming the fields changed, their previous and new
    values kept (:mod:`app.services.changes`). The report shows the rating: a measured
    trial's PDF report is made again by the worker.
    """
    trial = load_trial(db, actor, trial_id, "update")
    changes = data.model_dump(exclude_unset=True)
    if "comment" in changes:
        changes["comment"] = changes["comment"] or None
    changed = changed_fields(trial, changes, columns={"comment": "rating_comment"})
    if "clinician_rating" in changed:
        trial.rated_at = utcnow()
        # who answers for it: the user, or the API key's owner (none for a key without one)
        client = db.get(ApiClient, actor.id) if actor.type == "api_client" else None
        trial.rated_by_user_id = client.owner_user_id if client else actor.user_id
    if changed and trial.result is not None:
        jobs.enqueue_report_pdf(db, trial.id)
    audit_update(db, actor, "trial", trial.id, trial.session.patient_id, changed)
    db.commit()
    return trial


def delete_trial(db: Session, actor: Actor, trial_id: int, reason: str | None = None) -> None:
    """Hide (soft-delete) a trial: it answers 404 and leaves the lists; rows, files, audit stay.

    ``reason`` says why (the pages require one); an admin can restore the trial
    (:func:`restore_trial`). Its queued or running job is cancelled (nobody
    could see the result).
    """
    trial = load_trial(db, actor, trial_id, "delete")
    trial.deleted_at = utcnow()
    trial.deleted_reason = (reason or "").strip() or None
    trial.deleted_by = actor.name if actor.type == "user" else f"API client {actor.name}"
    cancel_trial_jobs(db, select(Trial.id).where(Trial.id == trial.id))
    audit(db, actor, "delete", "trial", trial.id, trial.session.patient_id)
    db.commit()


def restore_trial(db: Session, actor: Actor, trial_id: int) -> Trial:
    """Show a hidden trial again (admins only); a cancelled analysis is not restarted.

    Raises
    ------
    PermissionDeniedError
        The actor is not an admin (audited as denied).
    NotFoundError
        No hidden trial with this id in a visible session.
    """
    if not actor.has_scope(ADMIN_SCOPE):
        audit_failure(db, actor, "restore", "trial", trial_id, outcome="denied")
        raise PermissionDeniedError("Only an administrator can restore a hidden trial.")
    trial = db.get(Trial, trial_id)
    if (
        trial is None
        or trial.deleted_at is None
        or trial.session.deleted_at is not None
        or trial.session.patient.deleted_at is not None
    ):
        audit_failure(db, actor, "restore", "trial", trial_id, outcome="not_found")
        raise NotFoundError(f"There is no hidden trial {trial_id} to restore.")
    trial.deleted_at = None
    trial.deleted_reason = None
    trial.deleted_by = None
    audit(db, actor, "restore", "trial", trial.id, trial.session.patient_id)
    db.commit()
    return trial


def get_job(db: Session, actor: Actor, job_id: int) -> Job:
    """A job's status (the API). A trial's job (its analysis, its report) tells what the
    trial's results tell of it (its failure, in words), so it needs ``results:read`` and is
    audited as a read of the trial; the job of a hidden trial, session or patient answers
    404 like the trial. A calibration's job holds no patient data (not audited); the route
    has checked the data scope that reading calibrations needs."""
    job = db.get(Job, job_id)
    if job is None:
        raise not_found(db, actor, "read", "job", job_id, "The job")
    if job.trial is None:
        db.rollback()
        return job
    if not actor.has_scope(RESULTS_READ):
        audit_failure(db, actor, "read", "trial", job.trial.id, outcome="denied")
        raise PermissionDeniedError(
            f"This {'API key' if actor.type == 'api_client' else 'account'} lacks the scope"
            f" {RESULTS_READ}, which the status of a trial's job needs; ask the administrator"
            " to grant it."
        )
    if not trial_is_visible(job.trial):
        raise not_found(db, actor, "read", "job", job_id, "The job")
    audit(db, actor, "read", "trial", job.trial.id, job.trial.session.patient_id)
    db.commit()
    return job


# --------------------------------------------------------------------------- pages


def _visible_job(db: Session, job_id: int) -> Job:
    job = db.get(Job, job_id)
    if job is None or (job.trial is not None and not trial_is_visible(job.trial)):
        raise NotFoundError(f"Job {job_id} does not exist.")
    return job


def job_page(db: Session, actor: Actor, job_id: int) -> Job:
    """The job page (a trial's job is audited as a read of the trial)."""
    job = _visible_job(db, job_id)
    if job.trial is not None:
        audit(db, actor, "read", "trial", job.trial.id, job.trial.session.patient_id)
    db.commit()
    return job


def queue_position(db: Session, job: Job) -> int | None:
    """1 for the next queued job to be claimed, 2 for the one after...; None unless queued.

    Claimed in :data:`app.jobs.CLAIM_ORDER`: every queued report goes before an analysis.
    """
    if job.status != "queued":
        return None
    report = Job.kind == jobs.REPORT_PDF
    earlier = Job.id < job.id
    before = and_(report, earlier) if job.kind == jobs.REPORT_PDF else or_(report, earlier)
    ahead = db.scalar(select(func.count()).select_from(Job).where(Job.status == "queued", before))
    return int(ahead or 0) + 1


def job_progress(db: Session, actor: Actor, job_id: int) -> Job:
    """A job polled by its page's script (holds no clinical values: not audited)."""
    job = _visible_job(db, job_id)
    db.rollback()
    return job

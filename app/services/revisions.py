"""Result revisions: a clinician's corrections and re-analyses of a trial, every one kept.

A trial's result is never replaced. Revision 1 is the first analysis; each
correction or re-analysis adds the next number, with who asked for it, when,
why (a reason is required) and what changed; the newest is current.

- A **correction** (exclude taps or cycles, dismiss a hesitation or halt, set
  the analysis window, swap the two markers' labels) of any task is measured
  again at once by core (:func:`core.corrections.correct_metrics`, with the
  task and side of the analysis) from the stored trajectories of the newest
  *analysis* revision: a few milliseconds, so inside the request.
  The request gives the corrections it changes; the others stay as the current
  revision has them (``window_s: null`` clears the window).
- A **re-analysis** (a given camera offset, or the two videos swapped) is a
  job; when the worker has measured the videos again it stores the next
  revision (:func:`store_analysis`). Corrections made before it referred to
  the taps of the earlier analysis and do not carry over; its result.json
  lists them (``corrections_not_carried``).

Every revision is one audit event (``create revision``) and queues the making
of its PDF report (:func:`app.jobs.enqueue_report_pdf`). The review page that
shows a revision beside the videos is :mod:`app.services.review`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Any

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import job_views, jobs
from app.actors import Actor
from app.audit import audit
from app.errors import ConflictError, InvalidRequestError, NotFoundError
from app.models import Result, Trial, User, utcnow
from app.reports.figures import plots_document
from app.schemas import RevisionCreate
from app.services.common import load_trial, no_result
from app.storage import Storage
from core.markers_csv import MarkerTable, read_markers_csv, write_markers_csv
from core.overlay import swap_overlay_labels
from core.tasks import Task, parse_task

if TYPE_CHECKING:
    from core.corrections import Corrections

# core.corrections (core.metrics, scipy: ~1 s) is imported where a revision is made,
# not when the web application starts.

CORRECTION_FIELDS = ("exclude_taps", "dismiss_pauses", "window_s", "swap_labels")
REANALYSIS_FIELDS = ("offset_frames", "swap_cameras")


@dataclass(frozen=True)
class RevisionOut:
    """What a revision request made: the new revision now, or the job that will make it."""

    trial_id: int
    revision: int | None
    job_id: int | None


@dataclass(frozen=True)
class RevisionInfo:
    """One revision in a trial's history (pages, API)."""

    revision: int
    kind: str
    created_at: datetime
    created_by: str | None
    reason: str | None
    change: dict[str, Any]
    current: bool


def actor_label(db: Session, actor: Actor) -> str:
    """How the record names who acted: a user's name (or e-mail), or the API client."""
    if actor.type == "user":
        user = db.get(User, actor.id)
        if user is not None and user.display_name:
            return f"{user.display_name} <{user.email}>"
        return actor.name
    return f"API client {actor.name}"


def served_document(result: Result) -> dict[str, Any]:
    """``result.json`` of a revision as served: with ``revision`` and ``edits`` (INTERFACES.md)."""
    doc = dict(result.document)
    doc["revision"] = result.revision
    doc["edits"] = list(doc.get("edits") or [])
    return doc


def revision_of(trial: Trial, revision: int | None) -> Result:
    """Revision ``revision`` of the trial's result (None: the current one).

    Raises
    ------
    NotFoundError
        The trial has no such revision.
    """
    row = trial.result if revision is None else trial.revision(revision)
    if row is None:
        raise NotFoundError(
            f"The trial {trial.id} has no revision {revision};"
            f" its revisions are 1 to {len(trial.results)}."
        )
    return row


def history(trial: Trial) -> list[RevisionInfo]:
    """Every revision of the trial's result, newest first."""
    current = trial.result
    return [
        RevisionInfo(
            revision=r.revision,
            kind=r.kind,
            created_at=r.created_at,
            created_by=r.created_by,
            reason=r.reason,
            change=dict(r.change or {}),
            current=current is not None and r.id == current.id,
        )
        for r in reversed(trial.results)
    ]


def list_revisions(db: Session, actor: Actor, trial_id: int) -> list[RevisionInfo]:
    """The revision history of a trial (audited as a read of its result)."""
    trial = load_trial(db, actor, trial_id, "read")
    out = history(trial)
    audit(db, actor, "read", "revision", trial.id, trial.session.patient_id)
    db.commit()
    return out


def latest_analysis(trial: Trial) -> Result | None:
    """The newest revision measured from the videos (whose trajectories corrections use)."""
    return next((r for r in reversed(trial.results) if r.kind == "analysis"), None)


def _edit(revision: int, kind: str, by: str, reason: str, change: dict[str, Any]) -> dict[str, Any]:
    return {
        "revision": revision,
        "kind": kind,
        "by": by,
        "at": utcnow().isoformat().replace("+00:00", "Z"),
        "reason": reason,
        "change": change,
    }


def _change_of(data: RevisionCreate) -> dict[str, Any]:
    """The fields the request changes; a re-analysis field sent as null asks for nothing."""
    return {
        k: v
        for k, v in data.model_dump(exclude_unset=True, exclude={"reason"}).items()
        if k in CORRECTION_FIELDS or (k in REANALYSIS_FIELDS and v is not None)
    }


def cameras_swapped(trial: Trial) -> bool:
    """Whether the newest analysis of the trial measured its videos swapped."""
    base = latest_analysis(trial)
    return base is not None and bool(base.document.get("cameras_swapped"))


def _drop_unchanged_swap(trial: Trial, change: dict[str, Any]) -> None:
    """Remove ``swap_cameras`` from ``change`` when the newest analysis measured the videos
    that way already (``false``: as stored); 422 when nothing is left to change."""
    swapped = cameras_swapped(trial)
    if "swap_cameras" not in change or change["swap_cameras"] != swapped:
        return
    if latest_analysis(trial) is None:
        return  # nothing measured yet (a failed trial): false is the retry as stored
    del change["swap_cameras"]
    if not change:
        how = "with the two videos swapped" if swapped else "as they are stored"
        raise InvalidRequestError(
            f"The newest analysis of trial {trial.id} measured its videos {how} already;"
            f" nothing would change. Send swap_cameras: {str(not swapped).lower()} to measure"
            " them the other way round, or offset_frames to measure them with another offset."
        )


def create_revision(
    db: Session, actor: Actor, trial_id: int, data: RevisionCreate, storage: Storage
) -> RevisionOut:
    """A correction (stored now) or a re-analysis (queued) of the trial's result.

    Raises
    ------
    InvalidRequestError
        Nothing to change (also ``swap_cameras`` as the newest analysis measured the
        videos already, or a re-analysis field sent as null), correction and re-analysis
        fields mixed, a tap that does not exist, or no tap left (422).
    ConflictError
        No result to correct yet, or an analysis of the trial is still running (409).
    """
    change = _change_of(data)
    if not change:
        raise InvalidRequestError(
            "Say what to change: exclude_taps, dismiss_pauses, window_s or swap_labels to"
            " correct the result, or offset_frames or swap_cameras to measure the videos again."
        )
    trial = load_trial(db, actor, trial_id, "update")
    _drop_unchanged_swap(trial, change)
    reanalysis = any(k in change for k in REANALYSIS_FIELDS)
    if reanalysis and any(k in change for k in CORRECTION_FIELDS):
        raise InvalidRequestError(
            "A re-analysis (offset_frames, swap_cameras) measures the videos again and cannot be"
            " combined with corrections of taps; send them as two revisions."
        )
    if reanalysis:
        return _queue_reanalysis(db, actor, trial, data, change)
    return _correct(db, actor, trial, data, change, storage)


def _queue_reanalysis(
    db: Session, actor: Actor, trial: Trial, data: RevisionCreate, change: dict[str, Any]
) -> RevisionOut:
    running = job_views.latest_job(db, trial_id=trial.id)
    if running is not None and running.status in ("queued", "running"):
        raise ConflictError(
            f"An analysis of trial {trial.id} is already {running.status} (job {running.id});"
            " wait for it to finish, then ask again."
        )
    payload: dict[str, Any] = {
        "revision_request": {
            "by": actor_label(db, actor),
            "by_user_id": actor.user_id,
            "reason": data.reason,
            "change": change,
        }
    }
    if data.offset_frames is not None:
        payload["offset_frames"] = float(data.offset_frames)
    # swap_cameras not given stays as the newest analysis measured the videos: an offset
    # asked for on a swapped trial measured it unswapped again
    if change.get("swap_cameras", cameras_swapped(trial)):
        payload["swap_cameras"] = True
    job = jobs.enqueue(db, "analyze_trial", trial_id=trial.id, payload=payload)
    if trial.result is None:
        trial.status = "queued"
    audit(db, actor, "create", "revision", trial.id, trial.session.patient_id)
    db.commit()
    return RevisionOut(trial_id=trial.id, revision=None, job_id=job.id)


def _merged_corrections(current: Result, change: dict[str, Any]) -> Corrections:
    """The current revision's corrections with the request's ``change`` applied over them."""
    from core.corrections import Corrections

    before = (
        Corrections.from_dict(current.document.get("corrections"))
        if current.kind == "correction"
        else Corrections()
    )
    merged = before.to_dict()
    merged.update({k: (list(v) if isinstance(v, list | tuple) else v) for k, v in change.items()})
    try:
        corrections = Corrections.from_dict(merged)
    except (ValueError, TypeError) as exc:
        raise InvalidRequestError(f"The correction cannot be used: {exc}") from exc
    if corrections == before:
        raise InvalidRequestError(
            f"Revision {current.revision} already has these corrections; nothing would change."
        )
    return corrections


def _stored_trajectories(storage: Storage, trial: Trial, base: Result) -> MarkerTable:
    """The markers.csv of the analysis revision ``base``, read back from storage."""
    if not base.markers_path or not storage.exists(base.markers_path):
        raise ConflictError(
            f"The trajectories of trial {trial.id} are missing from storage; it cannot be"
            " measured again (ask the administrator to restore the data directory)."
        )
    return read_markers_csv(
        storage.absolute(base.markers_path), fps=float(base.document.get("fps") or 0) or None
    )


def _write_swapped_labels(
    storage: Storage, base: Result, table: MarkerTable, task: Task, written: list[str]
) -> tuple[str | None, str | None]:
    """markers.csv and the review overlay with the task's two labels swapped (thumb and
    index; finger and wrist); their stored paths.

    Each file written is appended to ``written`` at once, so that the caller
    can remove it if storing the revision fails.
    """
    from core.corrections import swap_labels, swappable_labels

    with storage.writing("results", ".csv") as (tmp, markers_path):
        write_markers_csv(swap_labels(table, task), tmp)
    written.append(markers_path)
    overlay_path = base.overlay_path
    pair = swappable_labels(task)
    if pair and base.overlay_path and storage.exists(base.overlay_path):
        overlay = json.loads(storage.absolute(base.overlay_path).read_text())
        with storage.writing("overlays", ".json") as (tmp, overlay_path):
            tmp.write_text(json.dumps(swap_overlay_labels(overlay, *pair)))
        written.append(overlay_path)
    return markers_path, overlay_path


def _correct(
    db: Session,
    actor: Actor,
    trial: Trial,
    data: RevisionCreate,
    change: dict[str, Any],
    storage: Storage,
) -> RevisionOut:
    current = trial.result
    base = latest_analysis(trial)
    if current is None or base is None:
        raise no_result(db, trial)  # failed: measure it again; else wait for the analysis
    from core.corrections import correct_metrics, revised_document, swap_labels

    task = parse_task(base.document.get("task"))
    corrections = _merged_corrections(current, change)
    table = _stored_trajectories(storage, trial, base)
    try:
        # The task and side the analysis measured (the side: the direction of supination).
        corrected = correct_metrics(table, corrections, task=task, side=trial.hand)
    except ValueError as exc:
        raise InvalidRequestError(f"The correction cannot be applied: {exc}") from exc

    number = _next_revision(db, trial.id)
    by = actor_label(db, actor)
    document = revised_document(base.document, corrected)
    document["revision"] = number
    document["edits"] = [
        *(current.document.get("edits") or []),
        _edit(number, "correction", by, data.reason, change),
    ]
    written: list[str] = []
    markers_path, overlay_path = base.markers_path, base.overlay_path
    try:
        if corrections.swap_labels:
            markers_path, overlay_path = _write_swapped_labels(storage, base, table, task, written)
        shown = swap_labels(table, task) if corrections.swap_labels else table
        plots_path = store_plots(storage, document, shown)
        written.append(plots_path)
        db.add(
            Result(
                trial_id=trial.id,
                revision=number,
                kind="correction",
                base_revision=base.revision,
                job_id=None,
                calibration_id=base.calibration_id,
                document=document,
                markers_path=markers_path,
                overlay_path=overlay_path,
                plots_path=plots_path,
                created_by=by,
                created_by_user_id=actor.user_id,
                reason=data.reason,
                change=change,
            )
        )
        jobs.enqueue_report_pdf(db, trial.id)
        audit(db, actor, "create", "revision", trial.id, trial.session.patient_id)
        db.commit()
    except IntegrityError as exc:
        db.rollback()
        for path in written:
            storage.delete(path)
        raise ConflictError(
            f"Another revision of trial {trial.id} was stored at the same moment; reload and"
            " check it before correcting again."
        ) from exc
    except BaseException:
        db.rollback()
        for path in written:
            storage.delete(path)
        raise
    return RevisionOut(trial_id=trial.id, revision=number, job_id=None)


def _next_revision(db: Session, trial_id: int) -> int:
    current = db.scalar(select(func.max(Result.revision)).where(Result.trial_id == trial_id))
    return int(current or 0) + 1


def store_plots(storage: Storage, document: dict[str, Any], markers: MarkerTable) -> str:
    """Draw a revision's plots and store them; returns their stored path (``Result.plots_path``).

    Drawn from ``document`` (its ``result.json``) and ``markers``, its
    ``markers.csv`` as read back from storage (what a page would draw from).
    The caller removes the file if its transaction fails.
    """
    with storage.writing("plots", ".json") as (tmp, path):
        tmp.write_text(plots_document(document, markers), encoding="utf-8")
    return path


# --------------------------------------------------------------------------- the worker's side


def _corrections_in_force(result: Result | None) -> dict[str, Any] | None:
    """The corrections of ``result`` if it is a correction that changed anything, else None.

    A re-analysis finds the taps anew; corrections naming the earlier taps do
    not apply to it, and its result.json says which were in force before
    (``corrections_not_carried``), so that nobody takes them as still applied.
    """
    if result is None or result.kind != "correction":
        return None
    from core.corrections import Corrections

    corrections = Corrections.from_dict(result.document.get("corrections"))
    return None if corrections.is_empty else corrections.to_dict()


def store_analysis(
    db: Session,
    *,
    trial_id: int,
    job_id: int,
    calibration_id: int,
    document: dict[str, Any],
    markers_path: str,
    overlay_path: str | None,
    request: dict[str, Any] | None = None,
    plots_path: str | None = None,
) -> int:
    """Store a new analysis revision in the caller's transaction; returns its number.

    ``request`` is the job's ``revision_request`` (who asked for a re-analysis,
    why and what changed), None for the analysis of an upload. ``plots_path``:
    its plots (:func:`store_plots`). The making of its PDF report is queued in
    the same transaction (:func:`app.jobs.enqueue_report_pdf`).
    """
    number = _next_revision(db, trial_id)
    previous = db.scalar(
        select(Result).where(Result.trial_id == trial_id).order_by(Result.revision.desc())
    )
    edits = list((previous.document.get("edits") if previous is not None else None) or [])
    dropped = _corrections_in_force(previous)
    by = reason = None
    change: dict[str, Any] | None = None
    user_id = None
    if request:
        by, reason = str(request.get("by") or ""), str(request.get("reason") or "")
        change = dict(request.get("change") or {})
        user_id = request.get("by_user_id")
        edits.append(_edit(number, "analysis", by, reason, change))
    document = {**document, "revision": number, "edits": edits}
    if dropped:
        document["corrections_not_carried"] = dropped
    db.add(
        Result(
            trial_id=trial_id,
            revision=number,
            kind="analysis",
            job_id=job_id,
            calibration_id=calibration_id,
            document=document,
            markers_path=markers_path,
            overlay_path=overlay_path,
            plots_path=plots_path,
            created_by=by,
            created_by_user_id=user_id if isinstance(user_id, int) else None,
            reason=reason,
            change=change,
        )
    )
    jobs.enqueue_report_pdf(db, trial_id)
    return number

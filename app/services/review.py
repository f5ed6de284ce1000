"""The review view of a trial: its videos' browser copies, the task's signal, cycles and pauses.

One revision of a trial's result as the review page shows it beside the two
videos (docs/reports.md), for every task: the task's cycle signal (the
aperture of finger tapping, the rotation of pronation–supination...) with its
taps or cycles, in its words and unit. :func:`review_page` reads the stored trajectories,
the review overlay (the tracked markers drawn on each video) and the revision
history, and is one ``read review`` audit event; :func:`proxy_file` serves the
browser-playable copy of a video to the page's player. The corrections made
from this page are :mod:`app.services.revisions`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy.orm import Session

from app import job_views
from app.actors import Actor
from app.audit import audit
from app.errors import ConflictError, NotFoundError
from app.models import Job, Result, Trial
from app.plots import MARKER_COLOURS
from app.quantities import quantity_of
from app.reports.figures import signal_series
from app.reports.result import read_result
from app.services.common import load_trial
from app.services.revisions import RevisionInfo, cameras_swapped, history, served_document
from app.storage import Storage
from core.markers_csv import MarkerTable, read_markers_csv
from core.protocols import protocol_for
from core.tasks import parse_task

if TYPE_CHECKING:  # core.corrections imports core.metrics (SciPy): when a page needs it
    from core.corrections import Corrections


def read_overlay(result: Result, storage: Storage) -> dict[str, Any] | None:
    """The overlay document of a revision, None when it has none (older results)."""
    if not result.overlay_path or not storage.exists(result.overlay_path):
        return None
    doc = json.loads(storage.absolute(result.overlay_path).read_text(encoding="utf-8"))
    if not isinstance(doc, dict):
        raise ValueError(f"the overlay {result.overlay_path} is not a JSON object")
    return doc


@dataclass(frozen=True)
class ReviewPage:
    """The review view of one revision of a trial's result.

    ``data`` is what the player script draws (embedded in the page, so the one
    audited view covers it): the task's signal per left frame (``signal``, in
    ``unit``, at the frames' times ``time_s``), the taps or cycles (``taps``: their
    result.json objects, the turn at ``peak_key``, the amplitude at
    ``amplitude_key``), pauses (naming their tap or cycle by ``pause_key``) and the
    overlay of each video. ``videos`` are
    the sides that have a browser proxy; ``job`` the newest analysis job (a
    re-analysis in progress or failed); ``swap_pair`` the two labels that may
    be swapped (None for a three-marker protocol).
    """

    trial: Trial
    result: Result
    revisions: list[RevisionInfo]
    data: dict[str, Any]
    videos: tuple[str, ...]
    corrections: Corrections
    job: Job | None = None
    not_carried: tuple[str, ...] = ()
    """The corrections in force before this re-analysis, in words (1-based taps)."""
    swap_pair: tuple[str, str] | None = ("thumb", "index")
    missing_videos: dict[str, str | None] = field(default_factory=dict)
    """The sides without a browser proxy, each with why (:func:`unavailable_videos`)."""
    uploaded_at: datetime | None = None
    """When the trial's recordings were uploaded (its ``created_at``): the page heads the
    trial with it, as the reports name their trials (``app.reports.visit.trial_time``);
    None: not known (the session's time is shown)."""


def _signal(table: MarkerTable, task: str, side: str) -> list[float | None]:
    """The task's raw cycle signal per left frame (0.01 of its unit), None where unknown."""
    series = signal_series(table, task, side=side)
    if series is None:
        return []
    return [round(float(v), 2) if np.isfinite(v) else None for v in series[1]]


def _signal_and_times(
    result: Result, doc: dict[str, Any], task: str, side: str, storage: Storage
) -> tuple[list[float | None], list[float]]:
    """The task's signal per left frame (:func:`_signal`) and each left frame's time (s),
    from the revision's trajectories; both empty when it has none."""
    if not result.markers_path or not storage.exists(result.markers_path):
        return [], []
    table = read_markers_csv(
        storage.absolute(result.markers_path), fps=float(doc.get("fps") or 0) or None
    )
    # the analysis's time of each left frame: lost frames and irregular intervals kept
    return _signal(table, task, side), [round(float(t), 6) for t in table.time_s]


def describe_corrections(corrections: Corrections, task: str = "finger_tapping") -> tuple[str, ...]:
    """Each correction in words, as a clinician reads it (taps or cycles numbered from 1)."""
    from core.corrections import swappable_labels

    word = parse_task(task).cycle_word

    def taps(numbers: tuple[int, ...]) -> str:
        return ", ".join(str(i + 1) for i in numbers)

    words = []
    if corrections.exclude_taps:
        words.append(f"{word}s {taps(corrections.exclude_taps)} excluded")
    if corrections.dismiss_pauses:
        words.append(f"the pauses at {word}s {taps(corrections.dismiss_pauses)} dismissed")
    if corrections.window_s is not None:
        t0, t1 = corrections.window_s
        words.append(f"analysis window {t0:g}–{t1:g} s")
    if corrections.swap_labels:
        a, b = swappable_labels(task) or ("the two", "")
        words.append(f"{a} and {b} labels swapped")
    return tuple(words)


PROXY_WARNING = "the {side} video cannot be shown in the review view"
"""How an analysis's warning begins when it could not make a video's browser proxy
(``app.handlers``: an encoder error, a full disk); the rest of the warning says why."""


def unavailable_videos(trial: Trial, shown: tuple[str, ...]) -> dict[str, str | None]:
    """Why each of the trial's videos not in ``shown`` has no browser proxy (by side), as
    a clause ("its browser copy could not be written (…)").

    The newest analysis that tried to make it and warned says why (its warning, as
    stored in ``quality.warnings``); a proxy recorded but gone from the data directory
    says so; None when nothing says why (a trial measured before the review view
    existed). A re-analysis makes the missing proxies again
    (``app.services.trial_inputs``: ``proxies_needed``).
    """
    missing: dict[str, str | None] = {}
    for video in sorted(trial.videos, key=lambda v: v.side):
        if video.side in shown:
            continue
        if video.proxy_path:
            missing[video.side] = "its browser copy is missing from the data directory"
            continue
        start = PROXY_WARNING.format(side=video.side)
        warned = (
            str(w)
            for r in reversed(trial.results)
            for w in ((r.document or {}).get("quality") or {}).get("warnings") or ()
            if str(w).startswith(start)
        )
        reason = next(warned, None)
        if reason is not None:
            detail = reason[len(start) :].lstrip(": ").rstrip(".")
            reason = f"its browser copy could not be written ({detail})"
        missing[video.side] = reason
    return missing


def review_page(
    db: Session, actor: Actor, trial_id: int, storage: Storage, *, revision: int | None = None
) -> ReviewPage:
    """The review view (one ``read review`` audit event per view).

    Raises
    ------
    NotFoundError
        No such trial or revision (audited).
    ConflictError
        The trial has no result yet: its analysis is queued or running (wait for it), or
        failed (the message says why, and how to measure it again).
    """
    trial = load_trial(db, actor, trial_id, "read")
    if trial.result is None:
        raise ConflictError(_no_result(db, trial))
    result = trial.result if revision is None else trial.revision(revision)
    if result is None:
        audit(db, actor, "read", "review", trial.id, trial.session.patient_id, "not_found")
        db.commit()
        raise NotFoundError(
            f"The trial {trial.id} has no revision {revision};"
            f" its revisions are 1 to {trial.result.revision}."
        )
    doc = served_document(result)
    read = read_result(doc)
    signal, time_s = _signal_and_times(result, doc, read.task, trial.hand, storage)
    videos = tuple(v.side for v in trial.videos if v.proxy_path and storage.exists(v.proxy_path))
    from core.corrections import Corrections, swappable_labels

    corrections = Corrections.from_dict(doc.get("corrections"))
    quantity = quantity_of(read.task)
    data = {
        "trial_id": trial.id,
        "revision": result.revision,
        "current": result.id == trial.result.id,
        "fps": doc.get("fps"),
        "signal": signal,
        "time_s": time_s,
        "unit": quantity.unit,
        "peak_key": quantity.peak_key,
        "amplitude_key": quantity.amplitude_key,
        "pause_key": "tap_index" if quantity.cycle == "tap" else "cycle_index",
        "taps": [dict(c) for c in read.task_cycles],
        "excluded_taps": doc.get("excluded_taps") or [],
        "outside_window_taps": doc.get("outside_window_taps") or [],
        "events": doc.get("events") or [],
        "dismissed_events": doc.get("dismissed_events") or [],
        "window_s": corrections.to_dict()["window_s"],
        "overlay": read_overlay(result, storage),
        # each marker in the colour the plots and the caption give it (the protocol's order)
        "marker_colours": {
            label: MARKER_COLOURS[k % len(MARKER_COLOURS)][0]
            for k, label in enumerate(protocol_for(parse_task(read.task)).labels)
        },
        "videos": {side: f"/trials/{trial.id}/video/{side}" for side in videos},
        # how the newest analysis measured the videos (the re-analysis form starts there)
        "cameras_swapped": cameras_swapped(trial),
    }
    page = ReviewPage(
        trial=trial,
        result=result,
        revisions=history(trial),
        data=data,
        videos=videos,
        corrections=corrections,
        job=job_views.latest_job(db, trial_id=trial.id),
        missing_videos=unavailable_videos(trial, videos),
        not_carried=describe_corrections(
            Corrections.from_dict(doc.get("corrections_not_carried")), read.task
        ),
        swap_pair=swappable_labels(read.task),
        uploaded_at=trial.created_at,
    )
    audit(db, actor, "read", "review", trial.id, trial.session.patient_id)
    db.commit()
    return page


def _no_result(db: Session, trial: Trial) -> str:
    """Why a trial without a result has nothing to review, and what to do."""
    if trial.status != "failed":
        return f"The trial {trial.id} has no result to review yet; wait for its analysis."
    job = job_views.latest_job(db, trial_id=trial.id)
    why = f": {job.error.rstrip('.')}" if job is not None and job.error else ""
    return (
        f"The analysis of trial {trial.id} failed{why}. Nothing will come of waiting: open the"
        f" trial's page (/trials/{trial.id}) to measure its videos again (with the cameras"
        " swapped or a given camera offset), or upload the recording again."
    )


def proxy_file(
    db: Session, actor: Actor, trial_id: int, side: str, storage: Storage, *, first: bool
) -> Path:
    """The browser proxy of one video of a trial, for the review view's player.

    A video is the most identifying data a trial has, and its address can be
    fetched without the review page: a request from its first byte (no
    ``Range``, or one from byte 0, as a player or a download starts) is one
    ``read video`` event (id ``<trial>/<side>``); the player's further range
    requests of the same viewing are not recorded again.
    """
    trial = load_trial(db, actor, trial_id, "read")
    video = next((v for v in trial.videos if v.side == side), None)
    if video is None or not video.proxy_path or not storage.exists(video.proxy_path):
        db.rollback()
        raise NotFoundError(
            f"The {side} video of trial {trial_id} has no browser copy; ask for a re-analysis"
            " to make one."
        )
    if first:
        audit(db, actor, "read", "video", f"{trial.id}/{side}", trial.session.patient_id)
        db.commit()
    else:
        db.rollback()
    return storage.absolute(video.proxy_path)

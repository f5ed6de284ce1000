"""The trial result page (plots, metrics, quality, comparison) and its downloads.

Downloads: ``pdf`` and ``html`` (the report), ``csv`` (markers.csv),
``c3d`` and ``trc`` (trajectories for motion-capture tools), ``json``
(result.json) and ``fhir`` (a FHIR R4 Bundle). Each is one ``export`` audit
event; the page itself one ``read`` event.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from pydantic import ValidationError
from sqlalchemy.orm import Session

from app.actors import ADMIN_SCOPE, Actor
from app.auth import SessionDep
from app.errors import AppError, NotFoundError
from app.models import Trial
from app.reports.comparison import comparison_rows
from app.reports.data import ReportData
from app.reports.figures import comparison_plots
from app.reports.rendering import report_context
from app.schemas import MAX_ID, IdPath, TrialRatingUpdate
from app.services import hidden_trials, results, trajectories, trials, visits
from app.services.common import load_trial
from app.storage import Storage
from app.timezones import local_date
from app.web.common import (
    CSRF_MESSAGE,
    PageUser,
    csrf_refused,
    error_page,
    not_found_page,
    render,
    settings_of,
    status_of,
    validation_message,
)
from core.tasks import parse_task

router = APIRouter()

DOWNLOADS: dict[str, tuple[str, str, str]] = {
    # kind: (label, media type, file suffix)
    "pdf": ("PDF report", "application/pdf", ".pdf"),
    "html": ("HTML report", "text/html; charset=utf-8", ".html"),
    "csv": ("Markers CSV", "text/csv; charset=utf-8", "-markers.csv"),
    "c3d": ("C3D", "application/octet-stream", ".c3d"),
    "trc": ("TRC", "text/plain; charset=utf-8", ".trc"),
    "json": ("Result JSON", "application/json", "-result.json"),
    "fhir": ("FHIR R4 Bundle", "application/fhir+json", "-fhir.json"),
}


def trial_label(trial: Trial, timezone: str) -> str:
    """``"2026-10-29, right hand, medication off"``, the day in the clinic's ``timezone``
    (a session at 00:30 in Prague is on the day the other pages show, not UTC's day before)."""
    s = trial.session
    limb = parse_task(trial.task).limb
    day = local_date(s.recorded_at, timezone)
    return f"{day:%Y-%m-%d}, {trial.hand} {limb}, medication {s.medication_state}"


def _comparison(data: ReportData, other: ReportData) -> dict[str, Any]:
    """The comparison of this trial with ``other``: the visit report's definitions, first
    10 taps (:mod:`app.reports.comparison`), and both trials' plots on the same scales."""
    pair, rows = comparison_rows(data, other)
    plots_a, plots_b = comparison_plots(data, other)
    return {
        "pair": pair,
        "rows": rows,
        "plots_a": plots_a,
        "plots_b": plots_b,
        "task": other.task,
    }


def _suggested(trial: Trial, candidates: list[Trial], timezone: str) -> list[tuple[Trial, str]]:
    """Candidates for comparison: the trials of the same task, the most useful first (other
    side, same session; other medication)."""

    def rank(t: Trial) -> tuple[int, float]:
        same_session = t.session_id == trial.session_id
        other_hand = t.hand != trial.hand
        other_med = t.session.medication_state != trial.session.medication_state
        if same_session and other_hand:
            score = 0
        elif t.hand == trial.hand and other_med:
            score = 1
        elif t.hand == trial.hand:
            score = 2
        else:
            score = 3
        return score, -t.session.recorded_at.timestamp()

    limb = parse_task(trial.task).limb
    hints = {
        0: f"other {limb}, same session",
        1: f"same {limb}, other medication state",
        2: f"same {limb}, other session",
        3: "",
    }
    same_task = (c for c in candidates if c.id != trial.id and c.task == trial.task)
    out = []
    for t in sorted(same_task, key=rank):
        hint = hints[rank(t)[0]]
        out.append((t, trial_label(t, timezone) + (f" ({hint})" if hint else "")))
    return out


@router.get("/trials/{trial_id}", response_class=HTMLResponse)
def trial_page(
    request: Request, db: SessionDep, user: PageUser, trial_id: IdPath, compare: str | None = None
) -> Response:
    # ``compare`` is read here, not by FastAPI: a bad value gets this page, not a JSON error.
    compare_id = int(compare) if compare and compare.strip().isdigit() else None
    if compare_id is not None and not 0 < compare_id <= MAX_ID:
        compare_id = None  # no such trial: said so below
    hidden = hidden_trials.hidden_trial_page(db, user, trial_id)
    if hidden is not None:  # who hid it, when and why, and how it comes back
        return render(
            request,
            "trial_hidden.html",
            user,
            status_code=410,
            active="patients",
            title=f"Trial {hidden.id} (hidden) — {hidden.session.patient.code}",
            trial=hidden,
            patient=hidden.session.patient,
            can_restore=user.has_scope(ADMIN_SCOPE),
        )
    try:
        page = results.trial_page(
            db,
            user,
            trial_id,
            request.app.state.storage,
            compare=compare_id,
            timezone=settings_of(request).timezone,
        )
    except NotFoundError as exc:
        return not_found_page(request, user, exc)
    trial, patient = page.trial, page.patient
    if page.data is None:
        return render(
            request,
            "trial_pending.html",
            user,
            active="patients",
            title=f"Trial {trial.id} — {patient.code}",
            trial=trial,
            patient=patient,
            job=page.job,
        )
    # the visit's signatures, so that the visit report offered is the signed one where it is
    tz = settings_of(request).timezone
    signed = visits.signatures_on_record(db, trial.session, tz)
    comparison = None
    if page.comparison is not None:
        comparison = _comparison(page.data, page.comparison.data)
        comparison["label"] = trial_label(page.comparison.trial, tz)
        comparison["trial"] = page.comparison.trial
    return render(
        request,
        "trial.html",
        user,
        active="patients",
        # as the heading and the review page's title: two takes of a task read apart
        title=f"{patient.code}: trial {trial.id}, {parse_task(trial.task).label.lower()},"
        f" {trial_label(trial, tz)}",
        trial=trial,
        patient=patient,
        label=trial_label(trial, tz),
        candidates=_suggested(trial, list(page.candidates), tz),
        comparison=comparison,
        compare_id=compare_id,
        compare_error=page.compare_error
        or (
            f"“{compare[:20]}” is not a trial number; choose a trial from the list."
            if compare and compare_id is None
            else None
        ),
        downloads=DOWNLOADS,
        signed_visit=signed[-1] if signed else None,
        **report_context(page.data),
    )


def _attachment(name: str) -> dict[str, str]:
    return {"Content-Disposition": f'attachment; filename="{name}"'}


def _download(
    db: Session, user: Actor, trial_id: int, kind: str, storage: Storage, tz: str
) -> bytes | str:
    if kind == "pdf":
        return results.report_pdf(db, user, trial_id, storage, timezone=tz)
    if kind == "html":
        return results.report_html(db, user, trial_id, storage, timezone=tz)
    if kind == "fhir":
        return json.dumps(results.fhir_bundle(db, user, trial_id, storage, timezone=tz), indent=1)
    if kind == "json":
        return json.dumps(results.get_result(db, user, trial_id, action="export"), indent=1)
    if kind == "csv":
        return results.markers_csv_path(db, user, trial_id, storage).read_bytes()
    return trajectories.trajectory_file(
        db, user, trial_id, "c3d" if kind == "c3d" else "trc", storage
    )


@router.get("/trials/{trial_id}/download/{kind}")
def trial_download(
    request: Request, db: SessionDep, user: PageUser, trial_id: IdPath, kind: str
) -> Response:
    if kind not in DOWNLOADS:
        return error_page(request, user, status_code=404, message=f"There is no {kind!r} download.")
    try:
        trial = load_trial(db, user, trial_id, "export")
    except NotFoundError as exc:
        return not_found_page(request, user, exc)
    _, media_type, suffix = DOWNLOADS[kind]
    filename = f"{trial.session.patient.code}-trial{trial.id}-{trial.hand}{suffix}"
    try:
        body = _download(
            db, user, trial.id, kind, request.app.state.storage, settings_of(request).timezone
        )
    except AppError as exc:
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    return Response(content=body, media_type=media_type, headers=_attachment(filename))


@router.post("/trials/{trial_id}/rating", response_class=HTMLResponse)
def trial_rating(
    request: Request,
    db: SessionDep,
    user: PageUser,
    trial_id: IdPath,
    clinician_rating: Annotated[str, Form(max_length=5)] = "",
    comment: Annotated[str, Form(max_length=5000)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
) -> Response:
    """Save the clinician's rating (0–4) and comment of the trial, then show the trial again."""
    if csrf_refused(db, user, csrf_token, request):
        return error_page(request, user, status_code=403, message=CSRF_MESSAGE)
    rating = clinician_rating.strip()
    if rating not in ("", "0", "1", "2", "3", "4"):
        return error_page(
            request, user, status_code=422, message="Rating: choose 0 to 4, or not rated."
        )
    try:
        data = TrialRatingUpdate(
            clinician_rating=int(rating) if rating else None, comment=comment.strip() or None
        )
        trials.rate_trial(db, user, trial_id, data)
    except ValidationError as exc:
        db.rollback()
        return error_page(
            request,
            user,
            status_code=422,
            message=validation_message(exc, {"clinician_rating": "Rating", "comment": "Comment"}),
        )
    except AppError as exc:
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    return RedirectResponse(f"/trials/{trial_id}?msg=Rating+saved.#rating", status_code=303)

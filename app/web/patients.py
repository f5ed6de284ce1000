"""Patient pages: list with search, a patient's sessions and trends, a new session.

Each page that shows or changes patient data writes exactly one audit event:
the list (``list patient``), the patient page (``read patient``), the new
session form (``read patient``) and the creations (through the services).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any
from zoneinfo import ZoneInfo

from fastapi import APIRouter, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from pydantic import ValidationError
from sqlalchemy.orm import Session

from app.actors import Actor
from app.auth import SessionDep
from app.errors import AppError, NotFoundError
from app.models import DBS_STATES, MEDICATION_STATES, Patient, Rig
from app.reports.catalogue import format_metric
from app.reports.task_metrics import trend_metrics
from app.schemas import IdPath, PatientCreate, SessionCreate
from app.services import patients, sessions
from app.services.common import visible_patient
from app.services.rigs import all_rigs
from app.storage import Storage
from app.timezones import from_local, to_zone
from app.trends import TrendPoint
from app.web.common import (
    CSRF_MESSAGE,
    SESSION_LABELS,
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

PAGE_SIZE = 50


@router.get("/patients", response_class=HTMLResponse)
def patient_list(
    request: Request, db: SessionDep, user: PageUser, q: str = "", page: int = 1
) -> Response:
    context = _list_context(db, user, q, page)
    return render(request, "patients.html", user, active="patients", title="Patients", **context)


MAX_PAGE = 10**6
"""Pages beyond this are empty anyway (the offset would overflow the database)."""


def _list_context(db: Session, user: Actor, q: str, page: int) -> dict[str, Any]:
    """The patient list (audited as a list of patients)."""
    q = q.strip()[:64]
    page = min(max(1, page), MAX_PAGE)
    found = patients.patient_list(db, user, q=q, limit=PAGE_SIZE, offset=(page - 1) * PAGE_SIZE)
    return dict(
        patients=found.patients,
        last_seen=found.last_seen,
        counts=found.session_counts,
        q=q,
        total=found.total,
        page=page,
        pages=max(1, -(-int(found.total) // PAGE_SIZE)),
        form={},
    )


@router.post("/patients", response_class=HTMLResponse)
def patient_create(
    request: Request,
    db: SessionDep,
    user: PageUser,
    code: Annotated[str, Form(max_length=200)] = "",
    birth_year: Annotated[str, Form(max_length=10)] = "",
    sex: Annotated[str, Form(max_length=20)] = "",
    notes: Annotated[str, Form(max_length=5000)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
) -> Response:
    form = {"code": code, "birth_year": birth_year, "sex": sex, "notes": notes}
    if csrf_refused(db, user, csrf_token, request):
        return _list_with_error(request, db, user, CSRF_MESSAGE, 403, form)
    try:
        data = PatientCreate(
            code=code.strip(),
            birth_year=int(birth_year) if birth_year.strip() else None,
            sex=sex or None,  # type: ignore[arg-type]  # validated by PatientCreate
            notes=notes.strip() or None,
        )
        patient = patients.create_patient(db, user, data)
    except (ValidationError, ValueError) as exc:
        message = (
            validation_message(
                exc,
                {
                    "code": "Patient code",
                    "birth_year": "Birth year",
                    "sex": "Sex",
                    "notes": "Notes",
                },
            )
            if isinstance(exc, ValidationError)
            else "Birth year must be a year such as 1951."
        )
        return _list_with_error(request, db, user, message, 422, form)
    except AppError as exc:
        return _list_with_error(request, db, user, str(exc), status_of(exc), form)
    return RedirectResponse(f"/patients/{patient.id}?msg=Patient+created.", status_code=303)


def _list_with_error(
    request: Request, db: Session, user: Actor, message: str, status: int, form: dict[str, str]
) -> Response:
    db.rollback()
    context = _list_context(db, user, "", 1)
    context["form"] = form
    return render(
        request,
        "patients.html",
        user,
        status_code=status,
        active="patients",
        title="Patients",
        error=message,
        **context,
    )


def _trend_group(
    storage: Storage, patient_id: int, task: str, points: dict[str, list[TrendPoint]], tz: str
) -> tuple[dict[str, Any], bool]:
    """One task's trends: a plot per trend metric (its keys, words and units; kept in the
    trend cache), or a table when all its trials are from one visit; and whether a plot
    was drawn now."""
    metrics = trend_metrics(task)
    limb = parse_task(task).limb
    group: dict[str, Any] = {"task": task, "trends": [], "table": None, "limb": limb}
    drawn = False
    if patients.plots_trends(task, points, tz):
        for key, label, _ in metrics:
            svg, new = patients.trend_plot_of(storage, patient_id, task, key, points[key])
            group["trends"].append({"key": key, "label": label, "svg": svg})
            drawn |= new
        group["values"] = _trend_values(task, points, tz)
    elif any(p.value is not None for key, _, _ in metrics for p in points[key]):
        group["table"] = _single_visit_table(task, points)
    return group, drawn


@router.get("/patients/{patient_id}", response_class=HTMLResponse)
def patient_page(request: Request, db: SessionDep, user: PageUser, patient_id: IdPath) -> Response:
    try:
        overview = patients.patient_overview(db, user, patient_id)
    except NotFoundError as exc:
        return not_found_page(request, user, exc)
    tz = settings_of(request).timezone
    storage = request.app.state.storage
    drawn = [
        _trend_group(storage, patient_id, task, points, tz)
        for task, points in overview.trends.items()
    ]
    groups = [group for group, _ in drawn]
    if any(new for _, new in drawn):
        patients.forget_trends_if_erased(db, storage, patient_id)
    return render(
        request,
        "patient.html",
        user,
        active="patients",
        title=f"Patient {overview.patient.code}",
        patient=overview.patient,
        rows=[
            {"session": r.session, "trials": r.trials, "hidden": r.hidden}
            for r in overview.sessions
        ],
        trend_groups=[g for g in groups if g["trends"] or g["table"]],
        job_ids=overview.job_ids,
        format_metric=format_metric,
    )


def _trend_values(task: str, points: dict[str, list[TrendPoint]], tz: str) -> dict[str, Any]:
    """The plotted values as a table, one row per trial (date, side, medication state):
    for keyboard, touch and screen-reader users, whom the plots' hover titles miss."""
    metrics = trend_metrics(task)
    rows: dict[tuple[str, str, str], dict[str, str]] = {}
    for key, _, _ in metrics:
        for p in points[key]:
            when = p.recorded_at
            local = to_zone(when, tz) if isinstance(when, datetime) else None
            day = f"{local:%Y-%m-%d %H:%M} {local.tzname()}" if local else f"{when}"
            cells = rows.setdefault((day, p.hand, p.medication_state), {})
            cells[key] = "–" if p.value is None else format_metric(key, p.value, task)
    return {
        "columns": [f"{label} ({unit})" if unit and unit != "count" else label
                    for _, label, unit in metrics],
        "rows": [
            {"date": day, "hand": hand, "medication": med,
             "cells": [cells.get(key, "–") for key, _, _ in metrics]}
            for (day, hand, med), cells in sorted(rows.items())
        ],
    }  # fmt: skip


def _single_visit_table(task: str, points: dict[str, list[TrendPoint]]) -> dict[str, Any]:
    """One visit: a table (metric × side and medication state) instead of one-dot plots."""
    metrics = trend_metrics(task)
    limb = parse_task(task).limb
    columns = sorted(
        {(p.medication_state, p.hand) for key, _, _ in metrics for p in points[key]},
        key=lambda c: (
            ("off", "on", "unknown").index(c[0]) if c[0] in ("off", "on", "unknown") else 9,
            c[1] != "right",
        ),
    )
    rows = []
    for key, label, unit in metrics:
        by_column = {(p.medication_state, p.hand): p.value for p in points[key]}
        cells = [
            "–" if by_column.get(c) is None else format_metric(key, by_column[c], task)
            for c in columns
        ]
        rows.append(
            {"key": key, "label": label, "unit": "" if unit == "count" else unit, "cells": cells}
        )
    return {
        "columns": [f"{hand} {limb}, medication {med}" for med, hand in columns],
        "rows": rows,
    }


@router.get("/patients/{patient_id}/sessions/new", response_class=HTMLResponse)
def session_new(request: Request, db: SessionDep, user: PageUser, patient_id: IdPath) -> Response:
    try:
        patient = patients.patient_for_new_session(db, user, patient_id)
    except NotFoundError as exc:
        return not_found_page(request, user, exc)
    return _session_form(request, user, patient, all_rigs(db), {})


def _session_form(
    request: Request,
    user: Actor,
    patient: Patient,
    rigs: list[Rig],
    values: dict[str, Any],
    *,
    error: str | None = None,
    status_code: int = 200,
) -> Response:
    now = datetime.now(UTC).astimezone(ZoneInfo(settings_of(request).timezone))
    defaults = {
        "rig_id": str(rigs[0].id) if rigs else "",
        "recorded_at": now.strftime("%Y-%m-%dT%H:%M"),
        "medication_state": "unknown",
        "dbs_state": "unknown",
        "time_since_levodopa_min": "",
        "more_affected_side": "",
        "dominant_hand": "",
        "notes": "",
    }
    defaults.update({k: v for k, v in values.items() if v is not None})
    return render(
        request,
        "session_new.html",
        user,
        status_code=status_code,
        active="patients",
        title=f"New session — {patient.code}",
        patient=patient,
        rigs=rigs,
        values=defaults,
        medication_states=MEDICATION_STATES,
        dbs_states=DBS_STATES,
        error=error,
    )


@router.post("/patients/{patient_id}/sessions", response_class=HTMLResponse)
def session_create(
    request: Request,
    db: SessionDep,
    user: PageUser,
    patient_id: IdPath,
    rig_id: Annotated[str, Form(max_length=20)] = "",
    recorded_at: Annotated[str, Form(max_length=40)] = "",
    medication_state: Annotated[str, Form(max_length=20)] = "unknown",
    dbs_state: Annotated[str, Form(max_length=20)] = "unknown",
    time_since_levodopa_min: Annotated[str, Form(max_length=10)] = "",
    more_affected_side: Annotated[str, Form(max_length=10)] = "",
    dominant_hand: Annotated[str, Form(max_length=10)] = "",
    notes: Annotated[str, Form(max_length=5000)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
) -> Response:
    patient = visible_patient(db, patient_id)
    if patient is None:
        return error_page(
            request, user, status_code=404, message=f"Patient {patient_id} does not exist."
        )
    values = {
        "rig_id": rig_id,
        "recorded_at": recorded_at,
        "medication_state": medication_state,
        "dbs_state": dbs_state,
        "time_since_levodopa_min": time_since_levodopa_min,
        "more_affected_side": more_affected_side,
        "dominant_hand": dominant_hand,
        "notes": notes,
    }
    if csrf_refused(db, user, csrf_token, request):
        return _session_form(
            request, user, patient, all_rigs(db), values, error=CSRF_MESSAGE, status_code=403
        )
    tz = settings_of(request).timezone
    try:
        problem = "Date and time of the recording: give a date and time such as 2026-03-01 14:30."
        when = from_local(recorded_at, tz)
        problem = "Camera rig: choose a rig."
        rig = int(rig_id)
        problem = "Time since the last levodopa dose: give a whole number of minutes, or nothing."
        minutes = int(time_since_levodopa_min) if time_since_levodopa_min.strip() else None
        data = SessionCreate(
            patient_id=patient.id,
            rig_id=rig,
            recorded_at=when,
            medication_state=medication_state,  # type: ignore[arg-type]
            dbs_state=dbs_state,  # type: ignore[arg-type]
            time_since_levodopa_min=minutes,
            more_affected_side=more_affected_side or None,  # type: ignore[arg-type]
            dominant_hand=dominant_hand or None,  # type: ignore[arg-type]
            notes=notes.strip() or None,
        )
        session = sessions.create_session(db, user, data)
    except (ValueError, AppError) as exc:  # ValidationError is a ValueError
        if isinstance(exc, ValidationError):
            error, status = validation_message(exc, SESSION_LABELS), 422
        elif isinstance(exc, AppError):
            error, status = str(exc), status_of(exc)
        else:
            error, status = problem, 422
        db.rollback()
        return _session_form(
            request, user, patient, all_rigs(db), values, error=error, status_code=status
        )
    return RedirectResponse(f"/sessions/{session.id}?msg=Session+created.", status_code=303)

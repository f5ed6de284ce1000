"""Patient pages: list with search, a patient's sessions and trends, a new session.

Each page that shows or changes patient data writes exactly one audit event:
the list (``list patient``), the patient page (``read patient``), the new
session form (``read patient``) and the creations (through the services).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any

from fastapi import APIRouter, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from pydantic import ValidationError
from sqlalchemy import func, select

from app.audit import audit
from app.auth import SessionDep
from app.errors import AppError
from app.models import (
    DBS_STATES,
    MEDICATION_STATES,
    Job,
    Patient,
    RecordingSession,
    Rig,
    Trial,
)
from app.plots import TrendPoint, trend_plot
from app.reports import TREND_METRICS, format_metric
from app.services.common import visible_patient
from app.web.common import (
    CSRF_MESSAGE,
    PageUser,
    csrf_ok,
    error_page,
    missing_page,
    render,
    status_of,
    validation_message,
)

router = APIRouter()

PAGE_SIZE = 50


@router.get("/patients", response_class=HTMLResponse)
def patient_list(
    request: Request, db: SessionDep, user: PageUser, q: str = "", page: int = 1
) -> Response:
    context = _list_context(db, q, page)
    audit(db, user, "list", "patient")
    db.commit()
    return render(request, "patients.html", user, active="patients", title="Patients", **context)


def _list_context(db: Any, q: str, page: int) -> dict[str, Any]:
    from app.services.patients import search_patients

    q = q.strip()[:64]
    page = max(1, page)
    patients, total = search_patients(db, q=q, limit=PAGE_SIZE, offset=(page - 1) * PAGE_SIZE)
    ids = [p.id for p in patients]
    last_seen: dict[int, Any] = {}
    counts: dict[int, int] = {}
    if ids:
        rows = db.execute(
            select(
                RecordingSession.patient_id,
                func.max(RecordingSession.recorded_at),
                func.count(RecordingSession.id),
            )
            .where(RecordingSession.patient_id.in_(ids), RecordingSession.deleted_at.is_(None))
            .group_by(RecordingSession.patient_id)
        ).all()
        for pid, last, count in rows:
            last_seen[pid] = last
            counts[pid] = count
    return dict(
        patients=patients,
        last_seen=last_seen,
        counts=counts,
        q=q,
        total=total,
        page=page,
        pages=max(1, -(-int(total) // PAGE_SIZE)),
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
    from app.schemas import PatientCreate
    from app.services.patients import create_patient

    form = {"code": code, "birth_year": birth_year, "sex": sex, "notes": notes}
    if not csrf_ok(user, csrf_token):
        return _list_with_error(request, db, user, CSRF_MESSAGE, 403, form)
    try:
        data = PatientCreate(
            code=code.strip(),
            birth_year=int(birth_year) if birth_year.strip() else None,
            sex=sex or None,  # type: ignore[arg-type]  # validated by PatientCreate
            notes=notes.strip() or None,
        )
        patient = create_patient(db, user, data)
    except (ValidationError, ValueError) as exc:
        message = (
            validation_message(exc)
            if isinstance(exc, ValidationError)
            else "Birth year must be a year such as 1951."
        )
        return _list_with_error(request, db, user, message, 422, form)
    except AppError as exc:
        return _list_with_error(request, db, user, str(exc), status_of(exc), form)
    return RedirectResponse(f"/patients/{patient.id}?msg=Patient+created.", status_code=303)


def _list_with_error(
    request: Request, db: Any, user: Any, message: str, status: int, form: dict[str, str]
) -> Response:
    db.rollback()
    context = _list_context(db, "", 1)
    context["form"] = form
    audit(db, user, "list", "patient")
    db.commit()
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


def _no_patient(request: Request, user: Any, patient_id: int) -> Response:
    return error_page(
        request, user, status_code=404, message=f"Patient {patient_id} does not exist."
    )


def _session_rows(db: Any, patient: Patient) -> list[dict[str, Any]]:
    sessions = [s for s in patient.sessions if s.deleted_at is None]
    sessions.sort(key=lambda s: (s.recorded_at, s.id), reverse=True)
    rows = []
    for s in sessions:
        trials = [t for t in s.trials if t.deleted_at is None]
        rows.append({"session": s, "trials": trials})
    return rows


def trend_points(patient: Patient) -> dict[str, list[TrendPoint]]:
    """Per trend metric, one point per analysed trial of the patient."""
    points: dict[str, list[TrendPoint]] = {key: [] for key, _, _ in TREND_METRICS}
    for s in patient.sessions:
        if s.deleted_at is not None:
            continue
        for t in s.trials:
            if t.deleted_at is not None or t.result is None:
                continue
            metrics = (t.result.document or {}).get("metrics") or {}
            for key, _, _ in TREND_METRICS:
                value = metrics.get(key)
                if key == "hesitation_count" and isinstance(value, int | float):
                    halts = metrics.get("halt_count")
                    value = value + (halts if isinstance(halts, int | float) else 0)
                points[key].append(
                    TrendPoint(
                        recorded_at=s.recorded_at,
                        hand=t.hand,
                        medication_state=s.medication_state,
                        value=float(value) if isinstance(value, int | float) else None,
                    )
                )
    return points


@router.get("/patients/{patient_id}", response_class=HTMLResponse)
def patient_page(request: Request, db: SessionDep, user: PageUser, patient_id: int) -> Response:
    patient = visible_patient(db, patient_id)
    if patient is None:
        return missing_page(request, db, user, "read", "patient", patient_id)
    rows = _session_rows(db, patient)
    points = trend_points(patient)
    trends = [
        {"key": key, "label": label, "svg": trend_plot(points[key], label=label, unit=unit)}
        for key, label, unit in TREND_METRICS
    ]
    n_results = sum(1 for p in points[TREND_METRICS[0][0]] if p.value is not None)
    job_ids = _latest_jobs(db, [t.id for r in rows for t in r["trials"]])
    audit(db, user, "read", "patient", patient.id, patient.id)
    db.commit()
    return render(
        request,
        "patient.html",
        user,
        active="patients",
        title=f"Patient {patient.code}",
        patient=patient,
        rows=rows,
        trends=trends,
        n_results=n_results,
        job_ids=job_ids,
        format_metric=format_metric,
    )


def _latest_jobs(db: Any, trial_ids: list[int]) -> dict[int, int]:
    if not trial_ids:
        return {}
    rows = db.execute(
        select(Job.trial_id, func.max(Job.id))
        .where(Job.trial_id.in_(trial_ids))
        .group_by(Job.trial_id)
    ).all()
    return {tid: jid for tid, jid in rows}


def _rigs(db: Any) -> list[Rig]:
    return list(db.scalars(select(Rig).order_by(Rig.name)))


@router.get("/patients/{patient_id}/sessions/new", response_class=HTMLResponse)
def session_new(request: Request, db: SessionDep, user: PageUser, patient_id: int) -> Response:
    patient = visible_patient(db, patient_id)
    if patient is None:
        return _no_patient(request, user, patient_id)
    audit(db, user, "read", "patient", patient.id, patient.id)
    db.commit()
    return _session_form(request, user, patient, _rigs(db), {})


def _session_form(
    request: Request,
    user: Any,
    patient: Patient,
    rigs: list[Rig],
    values: dict[str, Any],
    *,
    error: str | None = None,
    status_code: int = 200,
) -> Response:
    now = datetime.now(UTC)
    defaults = {
        "rig_id": str(rigs[0].id) if rigs else "",
        "recorded_at": now.strftime("%Y-%m-%dT%H:%M"),
        "medication_state": "unknown",
        "dbs_state": "unknown",
        "updrs_34_rating": "",
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
    patient_id: int,
    rig_id: Annotated[str, Form(max_length=20)] = "",
    recorded_at: Annotated[str, Form(max_length=40)] = "",
    medication_state: Annotated[str, Form(max_length=20)] = "unknown",
    dbs_state: Annotated[str, Form(max_length=20)] = "unknown",
    updrs_34_rating: Annotated[str, Form(max_length=5)] = "",
    notes: Annotated[str, Form(max_length=5000)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
) -> Response:
    from app.schemas import SessionCreate
    from app.services.sessions import create_session

    patient = visible_patient(db, patient_id)
    if patient is None:
        return _no_patient(request, user, patient_id)
    values = {
        "rig_id": rig_id,
        "recorded_at": recorded_at,
        "medication_state": medication_state,
        "dbs_state": dbs_state,
        "updrs_34_rating": updrs_34_rating,
        "notes": notes,
    }
    if not csrf_ok(user, csrf_token):
        return _session_form(
            request, user, patient, _rigs(db), values, error=CSRF_MESSAGE, status_code=403
        )
    try:
        when = datetime.fromisoformat(recorded_at.strip()) if recorded_at.strip() else None
        if when is None:
            raise ValueError("recorded_at")
        if when.tzinfo is None:
            when = when.replace(tzinfo=UTC)
        data = SessionCreate(
            patient_id=patient.id,
            rig_id=int(rig_id),
            recorded_at=when,
            medication_state=medication_state,  # type: ignore[arg-type]
            dbs_state=dbs_state,  # type: ignore[arg-type]
            updrs_34_rating=int(updrs_34_rating) if updrs_34_rating.strip() else None,
            notes=notes.strip() or None,
        )
        session = create_session(db, user, data)
    except (ValueError, AppError) as exc:  # ValidationError is a ValueError
        if isinstance(exc, ValidationError):
            error, status = validation_message(exc), 422
        elif isinstance(exc, AppError):
            error, status = str(exc), status_of(exc)
        else:
            error = (
                "Choose a rig and give the date and time of the recording (rating 0–4 or empty)."
            )
            status = 422
        db.rollback()
        return _session_form(
            request, user, patient, _rigs(db), values, error=error, status_code=status
        )
    return RedirectResponse(f"/sessions/{session.id}?msg=Session+created.", status_code=303)


def trials_of_patient(db: Any, patient: Patient) -> list[Trial]:
    """Every visible trial of the patient that has a result, newest session first."""
    out: list[Trial] = []
    for s in sorted(patient.sessions, key=lambda s: s.recorded_at, reverse=True):
        if s.deleted_at is not None:
            continue
        out.extend(t for t in s.trials if t.deleted_at is None and t.result is not None)
    return out

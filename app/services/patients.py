"""Patients: create, list (search + pagination), read, update, soft delete.

Deletion rule: a patient is never removed from the database. ``DELETE`` sets
``deleted_at`` (the patient, its sessions and trials then answer 404 and
disappear from lists), the audit trail keeps referring to its id, and its
code stays reserved so that it cannot be given to somebody else by mistake.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import UTC, date, datetime

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app import job_views
from app.actors import Actor
from app.audit import audit, audit_failure, audit_listed
from app.errors import ConflictError, NotFoundError
from app.models import Job, Patient, RecordingSession, Trial, utcnow
from app.reports.result import read_result
from app.reports.task_metrics import trend_metrics
from app.reports.trend_cache import TrendSvgCache, cached_trend_plot
from app.schemas import PatientCreate, PatientUpdate
from app.services.changes import audit_update, changed_fields
from app.services.common import (
    cancel_trial_jobs,
    load_patient,
    paginate,
    visible_patient,
    visible_trial,
)
from app.services.erasure import tombstone_code
from app.storage import Storage
from app.timezones import local_date
from app.trends import TrendPoint
from core.tasks import TASKS, parse_task


def _code_taken(db: Session, code: str, *, exclude_id: int | None = None) -> Patient | None:
    """The patient holding ``code`` (any case), or the erased patient it belonged to."""
    query = select(Patient).where(
        func.lower(Patient.code).in_((code.lower(), tombstone_code(db, code).lower()))
    )
    if exclude_id is not None:
        query = query.where(Patient.id != exclude_id)
    return db.scalars(query.limit(1)).first()


def _conflict(existing: Patient) -> ConflictError:
    if existing.erased_at is not None:
        return ConflictError(
            "This code belonged to a patient whose data was erased and stays reserved;"
            " choose another code."
        )
    if existing.deleted_at is not None:
        return ConflictError(
            f"The code {existing.code} belonged to a deleted patient and stays reserved;"
            " choose another code."
        )
    return ConflictError(f"A patient with the code {existing.code} exists already.")


def _refused(
    db: Session, actor: Actor, action: str, patient_id: int | None, error: ConflictError
) -> ConflictError:
    """Audit a change refused for a taken code (outcome ``denied``); returns ``error`` to raise.

    ``patient_id`` is the patient being changed, or the one holding the code (``None``
    when a concurrent request took it).
    """
    audit_failure(db, actor, action, "patient", patient_id, patient_id, outcome="denied")
    return error


def create_patient(db: Session, actor: Actor, data: PatientCreate) -> Patient:
    """Create a patient (409 if the code exists, case-insensitively)."""
    existing = _code_taken(db, data.code)
    if existing is not None:
        raise _refused(db, actor, "create", existing.id, _conflict(existing))
    patient = Patient(**data.model_dump())
    db.add(patient)
    try:
        db.flush()
    except IntegrityError as exc:  # a concurrent request took the code
        error = ConflictError(f"A patient with the code {data.code} exists already.")
        raise _refused(db, actor, "create", None, error) from exc
    audit(db, actor, "create", "patient", patient.id, patient.id)
    db.commit()
    return patient


def search_patients(
    db: Session, *, q: str | None, limit: int, offset: int
) -> tuple[list[Patient], int]:
    """Patients whose code contains ``q`` (case-insensitive), ordered by code; and the total.

    A query only: the callers audit the listing (:func:`list_patients`, :func:`patient_list`).
    """
    query = select(Patient).where(Patient.deleted_at.is_(None))
    if q:
        escaped = q.strip().lower().replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
        query = query.where(func.lower(Patient.code).like(f"%{escaped}%", escape="\\"))
    return paginate(db, query, Patient.code, Patient.id, limit=limit, offset=offset)


def list_patients(
    db: Session, actor: Actor, *, q: str | None, limit: int, offset: int
) -> tuple[list[Patient], int]:
    """Patients whose code contains ``q`` (case-insensitive), ordered by code; and the total.

    Audited as one ``list`` naming every patient returned (:func:`app.audit.audit_listed`):
    each one's trail shows the listing."""
    items, total = search_patients(db, q=q, limit=limit, offset=offset)
    audit_listed(db, actor, "patient", [p.id for p in items])
    db.commit()
    return items, int(total)


def get_patient(db: Session, actor: Actor, patient_id: int) -> Patient:
    patient = load_patient(db, actor, patient_id, "read")
    audit(db, actor, "read", "patient", patient.id, patient.id)
    db.commit()
    return patient


def update_patient(db: Session, actor: Actor, patient_id: int, data: PatientUpdate) -> Patient:
    """Change the given fields; ``code`` cannot be cleared, other fields can (``null``).

    Audited as an update naming the fields changed, their values kept beside the event
    (:mod:`app.services.changes`)."""
    patient = load_patient(db, actor, patient_id, "update")
    changes = data.model_dump(exclude_unset=True)
    if changes.get("code") is None:
        changes.pop("code", None)
    if "code" in changes:
        existing = _code_taken(db, changes["code"], exclude_id=patient.id)
        if existing is not None:
            raise _refused(db, actor, "update", patient_id, _conflict(existing))
    changed = changed_fields(patient, changes)
    try:
        db.flush()
    except IntegrityError as exc:
        error = ConflictError("Another patient took this code meanwhile; choose another.")
        raise _refused(db, actor, "update", patient_id, error) from exc
    audit_update(db, actor, "patient", patient.id, patient.id, changed)
    db.commit()
    return patient


def delete_patient(db: Session, actor: Actor, patient_id: int) -> None:
    """Soft-delete a patient (see the module's deletion rule); jobs of its trials are cancelled."""
    patient = load_patient(db, actor, patient_id, "delete")
    patient.deleted_at = utcnow()
    cancel_trial_jobs(
        db,
        select(Trial.id)
        .join(RecordingSession, Trial.session_id == RecordingSession.id)
        .where(RecordingSession.patient_id == patient.id),
    )
    audit(db, actor, "delete", "patient", patient.id, patient.id)
    db.commit()


# --------------------------------------------------------------------------- pages


@dataclass(frozen=True)
class PatientList:
    """One page of the patient list: the patients, and per patient id its last session and count."""

    patients: list[Patient]
    total: int
    last_seen: dict[int, datetime]
    session_counts: dict[int, int]


def patient_list(db: Session, actor: Actor, *, q: str, limit: int, offset: int) -> PatientList:
    """The patient list page: :func:`search_patients` with each patient's sessions summed up."""
    patients, total = search_patients(db, q=q, limit=limit, offset=offset)
    last_seen: dict[int, datetime] = {}
    counts: dict[int, int] = {}
    ids = [p.id for p in patients]
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
        for patient_id, last, count in rows:
            last_seen[patient_id] = last
            counts[patient_id] = count
    audit_listed(db, actor, "patient", ids)
    db.commit()
    return PatientList(patients, total, last_seen, counts)


@dataclass(frozen=True)
class SessionRow:
    """A session on its patient's page, with its visible trials and its hidden ones (a side
    whose trials were all hidden reads "hidden", not as never recorded)."""

    session: RecordingSession
    trials: list[Trial]
    hidden: list[Trial] = field(default_factory=list)


@dataclass(frozen=True)
class PatientOverview:
    """The patient page: sessions newest first, trends, and the newest job of each trial."""

    patient: Patient
    sessions: list[SessionRow]
    trends: dict[str, dict[str, list[TrendPoint]]]
    """Per task, per trend metric: the points (:func:`trend_points`)."""
    job_ids: dict[int, int]


def trend_points(patient: Patient) -> dict[str, dict[str, list[TrendPoint]]]:
    """Per task measured, per trend metric of that task, one point per analysed trial of the
    patient: its first-10-tap (cycle) value.

    The MDS-UPDRS items are rated on the first 10 taps (cycles), so the trends
    follow ``metrics_first_10`` (a result without it has no point). Each task
    has its own trends, in its own metrics and units
    (:func:`app.reports.task_metrics.trend_metrics`): the items are rated apart and
    their amplitudes are not of one quantity (mm, degrees). Tasks come in the
    order of the items; a task with no analysed trial has no entry.
    """
    points: dict[str, dict[str, list[TrendPoint]]] = {}
    for s in patient.sessions:
        if s.deleted_at is not None:
            continue
        for t in s.trials:
            if t.deleted_at is not None or t.result is None:
                continue
            metrics = trend_metrics(t.task)
            by_key = points.setdefault(t.task, {key: [] for key, _, _ in metrics})
            first10 = read_result(t.result.document).metrics_first_10
            for key, _, _ in metrics:
                raw = first10.get(key)
                value = None if raw is None else float(raw)
                if key == "hesitation_count" and value is not None:
                    value += float(first10.get("halt_count") or 0)  # interruptions: both kinds
                by_key[key].append(
                    TrendPoint(
                        recorded_at=s.recorded_at,
                        hand=t.hand,
                        medication_state=s.medication_state,
                        value=value,
                    )
                )
    return {task: points[task] for task in TASKS if task in points}


def _aware(value: date | datetime) -> datetime:
    if isinstance(value, datetime):
        return value
    return datetime(value.year, value.month, value.day, tzinfo=UTC)


def plots_trends(task: str, points: dict[str, list[TrendPoint]], tz: str) -> bool:
    """Whether the patient page draws the task's trends as plots: its measured trials are
    from more than one visit (day in the clinic's time zone ``tz``); one visit is a table."""
    measured = [p for key, _, _ in trend_metrics(task) for p in points[key] if p.value is not None]
    return len({local_date(_aware(p.recorded_at), tz) for p in measured}) > 1


def trend_plot_of(
    storage: Storage, patient_id: int, task: str, key: str, points: list[TrendPoint]
) -> tuple[str, bool]:
    """The patient's plot of one trend metric (``key`` of :func:`trend_metrics` of ``task``):
    kept in the trend cache (:mod:`app.reports.trend_cache`), or drawn now and kept; and
    whether it was drawn now (then call :func:`forget_trends_if_erased`)."""
    label, unit = next((lb, un) for k, lb, un in trend_metrics(task) if k == key)
    cache = TrendSvgCache.of(storage)
    limb = parse_task(task).limb
    return cached_trend_plot(cache, patient_id, points, label=label, unit=unit, limb=limb)


def forget_trends_if_erased(db: Session, storage: Storage, patient_id: int) -> None:
    """Remove the patient's kept trend plots if the patient was erased while they were drawn.

    Call it after the plots were kept, in a transaction begun after that: an erasure
    committed before this query is seen here; one committed after it removes the
    patient's kept files itself, the new ones included.
    """
    if db.scalar(select(Patient.erased_at).where(Patient.id == patient_id)) is not None:
        TrendSvgCache.of(storage).forget_patient(patient_id)


def _analyses_pending(db: Session, patient_id: int) -> bool:
    """Whether an analysis of one of the patient's trials is queued or running."""
    pending = db.scalar(
        select(func.count())
        .select_from(Job)
        .join(Trial, Job.trial_id == Trial.id)
        .join(RecordingSession, Trial.session_id == RecordingSession.id)
        .where(
            Job.kind == "analyze_trial",
            Job.status.in_(("queued", "running")),
            RecordingSession.patient_id == patient_id,
        )
    )
    return bool(pending)


def draw_trend_plots(
    sessions: sessionmaker[Session], storage: Storage, trial_id: int, timezone: str
) -> int:
    """Draw the trend plots of the trial's patient page into the trend cache (the worker,
    after a result changed); returns how many were drawn (not kept already).

    ``timezone`` is the server's (``Settings.timezone``): it decides which tasks show
    plots. Nothing is drawn for a trial hidden or erased, nor while another analysis of
    the patient is queued or running (a batch of recordings is drawn once, after its
    last); a patient erased meanwhile loses the plots drawn for them (as
    :func:`app.services.results.make_report_pdfs`).
    """
    with sessions() as db:
        trial = visible_trial(db, trial_id)
        if trial is None:
            return 0
        patient_id = trial.session.patient_id
        if _analyses_pending(db, patient_id):
            return 0  # they change the trends; the last one's report job draws them
        trends = trend_points(trial.session.patient)
    cache = TrendSvgCache.of(storage)
    drawn = 0
    for task, points in trends.items():
        if not plots_trends(task, points, timezone):
            continue
        limb = parse_task(task).limb
        for key, label, unit in trend_metrics(task):
            _, new = cached_trend_plot(
                cache, patient_id, points[key], label=label, unit=unit, limb=limb
            )
            drawn += new
    if drawn:
        with sessions() as db:
            forget_trends_if_erased(db, storage, patient_id)
    return drawn


def patient_overview(db: Session, actor: Actor, patient_id: int) -> PatientOverview:
    """The patient page (audited as a read of the patient)."""
    patient = load_patient(db, actor, patient_id, "read")
    sessions = sorted(
        (s for s in patient.sessions if s.deleted_at is None),
        key=lambda s: (s.recorded_at, s.id),
        reverse=True,
    )
    rows = [
        SessionRow(
            s,
            [t for t in s.trials if t.deleted_at is None],
            [t for t in s.trials if t.deleted_at is not None],
        )
        for s in sessions
    ]
    newest = job_views.latest_jobs(db, trial_ids=[t.id for r in rows for t in r.trials])
    overview = PatientOverview(
        patient=patient,
        sessions=rows,
        trends=trend_points(patient),
        job_ids={trial_id: job.id for trial_id, job in newest.items()},
    )
    audit(db, actor, "read", "patient", patient.id, patient.id)
    db.commit()
    return overview


def patient_for_new_session(db: Session, actor: Actor, patient_id: int) -> Patient:
    """The patient of the new-session form (audited as a read of the patient)."""
    patient = visible_patient(db, patient_id)
    if patient is None:
        raise NotFoundError(f"Patient {patient_id} does not exist.")
    audit(db, actor, "read", "patient", patient.id, patient.id)
    db.commit()
    return patient

"""Results of a trial: the trial page, result.json, markers.csv, reports and exports.

Each export is generated first and audited (``export``) only when it could be
produced, in the same commit. :func:`load_report_data` gathers what a report
shows about one trial from the database and storage into a
:class:`~app.reports.data.ReportData`, for the page, the reports and FHIR.

A trial's PDF report is made ahead of time: whatever changes what it shows
queues a ``report_pdf`` job (:func:`app.jobs.enqueue_report_pdf`), whose
worker makes it into the report cache (:func:`make_report_pdfs`,
:mod:`app.reports.pdf_cache`); a request finds it there, or makes it then and
keeps it (:func:`report_pdf`, :func:`fhir_bundle`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app import job_views
from app.actors import Actor
from app.audit import audit
from app.errors import ConflictError, NotFoundError
from app.models import Calibration, Job, Patient, Result, Trial, User
from app.reports.data import CalibrationInfo, ReportData
from app.reports.figures import read_plots_document
from app.reports.pdf_cache import ReportPdfCache
from app.reports.rendering import render_report_html, render_report_pdf, report_key
from app.reports.result import read_result
from app.reports.summary import SummaryColumn, neighbours
from app.services.common import (
    load_trial,
    no_result,
    visible_trial,
    visit_analyses_pending,
    visit_trials,
)
from app.services.revisions import served_document
from app.storage import Storage
from core.markers_csv import MarkerTable, read_markers_csv
from core.tasks import parse_task

T = TypeVar("T")


def result_of(
    db: Session, actor: Actor, trial_id: int, action: str, revision: int | None = None
) -> tuple[Trial, Result]:
    """The trial and its current result, or its revision ``revision``.

    Raises
    ------
    NotFoundError
        No such trial (audited), or no such revision (audited).
    ConflictError
        The trial has no result: its analysis failed, or has not finished yet.
    """
    trial = load_trial(db, actor, trial_id, action)
    result = trial.result
    if result is not None and revision is not None:
        found = trial.revision(revision)
        if found is None:
            audit(db, actor, action, "result", trial.id, trial.session.patient_id, "not_found")
            db.commit()
            raise NotFoundError(
                f"The trial {trial.id} has no revision {revision};"
                f" its revisions are 1 to {result.revision}."
            )
        result = found
    if result is None:
        raise no_result(db, trial)
    return trial, result


def exported(db: Session, actor: Actor, trial: Trial, resource_type: str, value: T) -> T:
    """Audit the export of ``trial``'s ``resource_type`` (committed); returns ``value``."""
    audit(db, actor, "export", resource_type, trial.id, trial.session.patient_id)
    db.commit()
    return value


# --------------------------------------------------------------------------- report data


def _markers(result: Result, storage: Storage) -> MarkerTable | None:
    path = storage.absolute(result.markers_path) if result.markers_path else None
    if path is None or not path.is_file():
        return None
    fps = float(result.document.get("fps") or 0) or None
    return read_markers_csv(path, fps=fps)


def _stored_plots(result: Result, storage: Storage) -> dict[str, str] | None:
    """The revision's plots as the worker stored them; None when it has none (then drawn)."""
    if not result.plots_path or not storage.exists(result.plots_path):
        return None
    return read_plots_document(storage.absolute(result.plots_path).read_text(encoding="utf-8"))


def _calibration_info(db: Session, trial: Trial, result: Result) -> CalibrationInfo:
    session = trial.session
    cal = db.get(Calibration, result.calibration_id) if result.calibration_id else None
    cal = cal or session.calibration
    if cal is None:
        return CalibrationInfo(
            rig_name=session.rig.name, version=None, valid_from=None, rms_px=None
        )
    return CalibrationInfo(
        rig_name=cal.rig.name,
        version=cal.version,
        valid_from=cal.valid_from,
        rms_px=cal.rms_px,
        verdict=cal.verdict,
        reasons=tuple(cal.verdict_reasons or ()),
        id=cal.id,
    )


def trial_column(trial: Trial, result: Result | None = None) -> SummaryColumn:
    """A trial with a result (its current one, or ``result``) as a column of a summary
    block (no markers are read)."""
    result = result or trial.result
    if result is None:
        db = Session.object_session(trial)
        raise (
            no_result(db, trial)
            if db is not None
            else ConflictError(f"The trial {trial.id} has no result yet (status {trial.status}).")
        )
    return SummaryColumn(
        trial_id=trial.id,
        task=trial.task,
        hand=trial.hand,
        medication_state=trial.session.medication_state,
        result=read_result(served_document(result)),
        clinician_rating=trial.clinician_rating,
        rating_comment=trial.rating_comment,
    )


def load_report_data(
    db: Session,
    trial: Trial,
    storage: Storage,
    result: Result | None = None,
    *,
    timezone: str = "UTC",
    markers: bool = False,
) -> ReportData:
    """What the report of ``trial`` shows: its current result, or the revision ``result``.

    ``timezone`` is the clinic's (``Settings.timezone``): the report shows dates in it.
    The trajectories (``markers.csv``) are read when ``markers`` is true, or when
    the revision has no stored plots (they are then drawn from them).

    Raises
    ------
    ConflictError
        The trial has no result yet.
    """
    result = result or trial.result
    if result is None:
        raise no_result(db, trial)
    session = trial.session
    this = trial_column(trial, result)
    beside = tuple(
        c
        for c in neighbours(this, [trial_column(t) for t in visit_trials(session, timezone)])
        if c is not None
    )
    clinician = None
    if session.clinician_user_id is not None:
        user = db.get(User, session.clinician_user_id)
        if user is not None:
            clinician = user.display_name or user.email
    plots = _stored_plots(result, storage)
    return ReportData(
        trial_id=trial.id,
        patient_code=session.patient.code,
        patient_id=session.patient_id,
        session_id=session.id,
        hand=trial.hand,
        task=trial.task,
        recorded_at=session.recorded_at,
        uploaded_at=trial.created_at,
        medication_state=session.medication_state,
        dbs_state=session.dbs_state,
        clinician_rating=trial.clinician_rating,
        rating_comment=trial.rating_comment,
        rated_by=(trial.rated_by.display_name or trial.rated_by.email) if trial.rated_by else None,
        rated_at=trial.rated_at,
        clinician=clinician,
        notes=session.notes,
        time_since_levodopa_min=session.time_since_levodopa_min,
        more_affected_side=session.more_affected_side,
        dominant_hand=session.dominant_hand,
        timezone=timezone,
        beside=beside,
        result=served_document(result),
        markers=_markers(result, storage) if markers or plots is None else None,
        plots=plots,
        calibration=_calibration_info(db, trial, result),
        revision=result.revision,
        edits=tuple(e for e in (result.document.get("edits") or []) if isinstance(e, dict)),
    )


# --------------------------------------------------------------------------- PDF reports


def _cached_pdf(
    data: ReportData, cache: ReportPdfCache, key: str | None = None
) -> tuple[bytes, bool]:
    """The PDF report of ``data``: from ``cache``, or made now and kept there.

    ``key``: ``report_key(data)`` when the caller has it already. Returns the bytes and
    whether they were made now (then call :func:`_forget_if_erased` after a commit).
    """
    if data.patient_id is None:
        raise ValueError(f"the report data of trial {data.trial_id} names no patient")
    key = report_key(data) if key is None else key
    kept = cache.get(data.patient_id, data.trial_id, key)
    if kept is not None:
        return kept, False
    pdf = render_report_pdf(data)
    cache.put(data.patient_id, data.trial_id, key, pdf)
    return pdf, True


def _forget_if_erased(db: Session, cache: ReportPdfCache, data: ReportData) -> None:
    """Remove the patient's cached reports if the trial was erased while its PDF was made.

    Call it after :meth:`ReportPdfCache.put`, in a transaction begun after it: an
    erasure committed before this query is seen here; one committed after it
    removes the patient's cached files itself, the new one included.
    """
    if data.patient_id is None:
        return
    if db.scalar(select(Trial.id).where(Trial.id == data.trial_id)) is None:
        cache.forget_patient(data.patient_id)


def _current_report_data(
    sessions: sessionmaker[Session], storage: Storage, trial_id: int, timezone: str
) -> ReportData | None:
    """What the report of the trial's current result shows; None for a trial that is
    hidden, erased or has no result."""
    with sessions() as db:
        trial = visible_trial(db, trial_id)
        if trial is None or trial.result is None:
            return None
        return load_report_data(db, trial, storage, timezone=timezone)


def make_report_pdfs(
    sessions: sessionmaker[Session], storage: Storage, trial_id: int, *, timezone: str
) -> list[int] | None:
    """The worker's part of a ``report_pdf`` job: the PDF reports of the trial's visit,
    the trial's own first, each made into the report cache unless it is there already,
    dated in ``timezone``.

    A trial's report shows the trials of its visit beside it (the other hand, the other
    medication state), so a change of one trial changes the others' reports: all of the
    visit's are looked at (one already made costs its HTML, ~20 ms). Nothing is made
    (None) while an analysis of the visit is queued or running: it would change them
    again, and its own report job, or its failure's
    (:func:`app.jobs.enqueue_report_pdf` in :func:`app.jobs.fail`), makes them once it
    ends, so a batch of recordings is made once, after its last (the trend plots wait
    the same way: :func:`app.services.patients.draw_trend_plots`).

    ``timezone`` must be the server's (``Settings.timezone``), or the request will
    not find the reports. Returns the ids of the trials whose PDF was made; nothing
    is made for a trial that is hidden, erased or has no result.
    """
    with sessions() as db:
        trial = visible_trial(db, trial_id)
        if trial is None:
            return []
        if visit_analyses_pending(db, trial.session, timezone):
            return None
        visit = [t.id for t in visit_trials(trial.session, timezone) if t.id != trial_id]
    cache = ReportPdfCache.of(storage)
    made = []
    for shown_id in (trial_id, *visit):
        shown = _current_report_data(sessions, storage, shown_id, timezone)
        if shown is None:
            continue
        _, new = _cached_pdf(shown, cache)
        if new:
            with sessions() as db:
                _forget_if_erased(db, cache, shown)
            made.append(shown.trial_id)
    return made


# --------------------------------------------------------------------------- exports


def get_result(
    db: Session,
    actor: Actor,
    trial_id: int,
    revision: int | None = None,
    *,
    action: Literal["read", "export"] = "read",
) -> dict[str, Any]:
    """The trial's ``result.json`` document: the current revision, or ``revision``;
    audited as ``action`` (``export`` for the page's download, like the other files).

    409 until the first analysis has succeeded; 404 for a revision that does not exist.
    """
    trial, result = result_of(db, actor, trial_id, action, revision)
    document = served_document(result)
    audit(db, actor, action, "result", trial.id, trial.session.patient_id)
    db.commit()
    return document


def markers_csv_path(
    db: Session, actor: Actor, trial_id: int, storage: Storage, revision: int | None = None
) -> Path:
    """The stored ``markers.csv`` of the trial's current result, or of ``revision``."""
    trial, result = result_of(db, actor, trial_id, "export", revision)
    path = storage.absolute(result.markers_path) if result.markers_path else None
    if path is None or not path.is_file():
        raise NotFoundError(f"The markers file of trial {trial.id} is missing from storage.")
    return exported(db, actor, trial, "markers_csv", path)


def _report_data(
    db: Session, actor: Actor, trial_id: int, storage: Storage, revision: int | None, timezone: str
) -> tuple[Trial, ReportData]:
    trial, result = result_of(db, actor, trial_id, "export", revision)
    return trial, load_report_data(db, trial, storage, result, timezone=timezone)


def report_html(
    db: Session,
    actor: Actor,
    trial_id: int,
    storage: Storage,
    revision: int | None = None,
    *,
    timezone: str = "UTC",
) -> str:
    trial, data = _report_data(db, actor, trial_id, storage, revision, timezone)
    return exported(db, actor, trial, "report_html", render_report_html(data))


def report_pdf(
    db: Session,
    actor: Actor,
    trial_id: int,
    storage: Storage,
    revision: int | None = None,
    *,
    timezone: str = "UTC",
) -> bytes:
    """The trial's report as PDF (the current revision, or ``revision``), from the report
    cache when the worker (or an earlier request) made it already."""
    trial, data = _report_data(db, actor, trial_id, storage, revision, timezone)
    cache = ReportPdfCache.of(storage)
    pdf, made = _cached_pdf(data, cache)
    exported(db, actor, trial, "report_pdf", pdf)
    if made:
        _forget_if_erased(db, cache, data)
    return pdf


def kept_report_pdf(
    db: Session, actor: Actor, trial_id: int, storage: Storage, revision: int | None, timezone: str
) -> bytes | None:
    """As :func:`report_pdf` (statuses, audit event), but only from the report cache: None
    when it does not hold it, never made here (a ``HEAD`` must not cost a second of CPU)."""
    trial, data = _report_data(db, actor, trial_id, storage, revision, timezone)
    kept = ReportPdfCache.of(storage).get(trial.session.patient_id, trial.id, report_key(data))
    return exported(db, actor, trial, "report_pdf", kept)


def fhir_bundle(
    db: Session,
    actor: Actor,
    trial_id: int,
    storage: Storage,
    revision: int | None = None,
    *,
    timezone: str = "UTC",
) -> dict[str, Any]:
    """A FHIR R4 Bundle (DiagnosticReport + Observations, the PDF attached) of the current
    result or of ``revision`` (its resources carry the revision as their version)."""
    trial, data = _report_data(db, actor, trial_id, storage, revision, timezone)
    from app.exports import fhir_bundle as make_fhir_bundle  # fhir.resources: ~1 s to import

    cache = ReportPdfCache.of(storage)
    key = report_key(data)  # the PDF's cache key, and what the report's version follows
    pdf, made = _cached_pdf(data, cache, key)
    bundle = exported(
        db, actor, trial, "fhir_bundle", make_fhir_bundle(data, pdf, report_content=key)
    )
    if made:
        _forget_if_erased(db, cache, data)
    return bundle


# --------------------------------------------------------------------------- the trial page


def trials_with_results(patient: Patient) -> list[Trial]:
    """Every visible trial of the patient that has a result, newest session first."""
    out: list[Trial] = []
    for s in sorted(patient.sessions, key=lambda s: s.recorded_at, reverse=True):
        if s.deleted_at is not None:
            continue
        out.extend(t for t in s.trials if t.deleted_at is None and t.result is not None)
    return out


@dataclass(frozen=True)
class Comparison:
    """A second trial of the same patient shown beside the first."""

    trial: Trial
    data: ReportData


@dataclass(frozen=True)
class TrialPage:
    """What the trial page shows: ``data`` is None while the trial has no result (then
    ``job`` tells its progress); ``comparison`` is the trial asked for with ``?compare=``,
    or ``compare_error`` says why it cannot be shown."""

    trial: Trial
    patient: Patient
    job: Job | None = None
    data: ReportData | None = None
    candidates: tuple[Trial, ...] = ()
    comparison: Comparison | None = None
    compare_error: str | None = None


def trial_page(
    db: Session,
    actor: Actor,
    trial_id: int,
    storage: Storage,
    *,
    compare: int | None = None,
    timezone: str = "UTC",
) -> TrialPage:
    """The trial page: its result (audited as a read of the result) or its pending job."""
    trial = load_trial(db, actor, trial_id, "read")
    patient = trial.session.patient
    if trial.result is None:
        page = TrialPage(
            trial=trial, patient=patient, job=job_views.latest_job(db, trial_id=trial.id)
        )
        audit(db, actor, "read", "trial", trial.id, patient.id)
        db.commit()
        return page
    comparison, compare_error = None, None
    if compare == trial.id:
        compare, compare_error = None, "That is this trial: choose another trial to compare with."
    # The trajectories are read only to draw the plots of a comparison.
    with_markers = compare is not None
    data = load_report_data(db, trial, storage, timezone=timezone, markers=with_markers)
    if compare is not None:
        other = visible_trial(db, compare)
        if other is None or other.result is None or other.session.patient_id != patient.id:
            compare_error = (
                "That trial cannot be compared: it does not exist, has no result,"
                " or belongs to another patient."
            )
        elif other.task != trial.task:
            compare_error = (
                f"That trial measured {parse_task(other.task).label.lower()}, this one"
                f" {parse_task(trial.task).label.lower()}: only trials of the same task compare."
            )
        else:
            comparison = Comparison(
                trial=other,
                data=load_report_data(db, other, storage, timezone=timezone, markers=True),
            )
            # The compared trial's result is read too: it has its own audit event.
            audit(db, actor, "read", "result", other.id, patient.id)
    page = TrialPage(
        trial=trial,
        patient=patient,
        data=data,
        candidates=tuple(trials_with_results(patient)),
        comparison=comparison,
        compare_error=compare_error,
    )
    audit(db, actor, "read", "result", trial.id, patient.id)
    db.commit()
    return page

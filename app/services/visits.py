"""The visit report: every trial of one visit on one page, then each trial's detail.

A visit is the patient's sessions on one calendar day in the clinic's time
zone (:func:`app.services.common.visit_sessions`). :func:`load_visit` gathers
it into a :class:`~app.reports.visit.VisitData`; rendering is a pure function
of that (``app.reports.rendering.render_visit_html`` / ``render_visit_pdf``).
Each report is audited as one ``export`` of the session it was asked for.
"""

from __future__ import annotations

from dataclasses import replace
from datetime import date

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.actors import Actor
from app.audit import audit
from app.job_views import latest_jobs
from app.models import RecordingSession, Signature, Trial, User
from app.reports.pdf_cache import ReportPdfCache
from app.reports.rendering import render_visit_html, render_visit_pdf, visit_key
from app.reports.visit import (
    HiddenTrial,
    SessionFacts,
    SignatureLine,
    UnmeasuredTrial,
    VisitData,
)
from app.services.common import load_session, visit_sessions, visit_trials
from app.services.results import load_report_data
from app.storage import Storage
from app.timezones import local_date
from core.tasks import parse_task
from core.version import software_version


def _clinician(db: Session, user_id: int | None) -> str | None:
    user = db.get(User, user_id) if user_id is not None else None
    return None if user is None else (user.display_name or user.email)


def unmeasured_trials(session: RecordingSession, timezone: str) -> list[Trial]:
    """The visible trials of ``session``'s visit without a result (failed or being
    measured), oldest session first."""
    return [
        t
        for s in visit_sessions(session, timezone)
        for t in sorted(s.trials, key=lambda t: t.id)
        if t.deleted_at is None and t.result is None
    ]


def _unmeasured(
    db: Session, session: RecordingSession, timezone: str
) -> tuple[UnmeasuredTrial, ...]:
    trials = unmeasured_trials(session, timezone)
    jobs = latest_jobs(db, trial_ids=[t.id for t in trials])
    out = []
    for t in trials:
        job, failed = jobs.get(t.id), t.status == "failed"
        out.append(
            UnmeasuredTrial(
                trial_id=t.id,
                task=t.task,
                hand=t.hand,
                medication_state=t.session.medication_state,
                recorded_at=t.session.recorded_at,
                status="failed" if failed else "measuring",
                why=job.error if failed and job is not None else None,
                uploaded_at=t.created_at,
            )
        )
    return tuple(out)


def sign_warnings(session: RecordingSession, timezone: str) -> list[str]:
    """What a clinician should know before signing ``session``'s visit, in words: trials
    that failed, trials still being measured, and measured trials without their rating.
    Signing stays possible (a failed take may never be measured; the rating is the
    clinician's own): the signed report lists the first two and shows "–" for the last."""

    def named(trials: list[Trial]) -> str:
        return "; ".join(
            f"#{t.id} ({parse_task(t.task).label.lower()}, {t.hand} {parse_task(t.task).limb},"
            f" medication {t.session.medication_state})"
            for t in trials
        )

    unmeasured = unmeasured_trials(session, timezone)
    failed = [t for t in unmeasured if t.status == "failed"]
    pending = [t for t in unmeasured if t.status != "failed"]
    unrated = [t for t in visit_trials(session, timezone) if t.clinician_rating is None]
    out = []
    if failed:
        out.append(
            f"{_trials(len(failed))} failed and will be listed in the signed report as not"
            f" measured, with why: {named(failed)}."
        )
    if pending:
        out.append(
            f"{_trials(len(pending))} {'is' if len(pending) == 1 else 'are'} still being"
            f" measured; the signed report will list"
            f" {'it' if len(pending) == 1 else 'them'} without a result — wait for the"
            f" measurement, or sign now and sign again once measured: {named(pending)}."
        )
    if unrated:
        out.append(
            f"{_trials(len(unrated))} {'has' if len(unrated) == 1 else 'have'} no rating of"
            " yours yet (the signed report shows “–” for it):"
            f" {named(unrated)}."
        )
    return out


def _trials(n: int) -> str:
    return f"{n} trial" if n == 1 else f"{n} trials"


def load_visit(
    db: Session, session: RecordingSession, storage: Storage, *, timezone: str = "UTC"
) -> VisitData:
    """The visit of ``session``: its sessions, every trial of them with a result, and the
    hidden ones (named with who hid them, when and why)."""
    sessions = visit_sessions(session, timezone)
    return VisitData(
        patient_code=session.patient.code,
        session_id=session.id,
        visit_date=local_date(session.recorded_at, timezone),
        timezone=timezone,
        sessions=tuple(
            SessionFacts(
                id=s.id,
                recorded_at=s.recorded_at,
                medication_state=s.medication_state,
                dbs_state=s.dbs_state,
                time_since_levodopa_min=s.time_since_levodopa_min,
                more_affected_side=s.more_affected_side,
                dominant_hand=s.dominant_hand,
                notes=s.notes,
                clinician=_clinician(db, s.clinician_user_id),
            )
            for s in sessions
        ),
        trials=tuple(
            load_report_data(db, t, storage, timezone=timezone)
            for t in visit_trials(session, timezone)
        ),
        software_version=software_version(),
        hidden=tuple(
            HiddenTrial(
                trial_id=t.id,
                task=t.task,
                hand=t.hand,
                medication_state=s.medication_state,
                recorded_at=s.recorded_at,
                hidden_at=t.deleted_at,
                hidden_by=t.deleted_by,
                reason=t.deleted_reason,
                uploaded_at=t.created_at,
            )
            for s in sessions
            for t in sorted(s.trials, key=lambda t: t.id)
            if t.deleted_at is not None
        ),
        unmeasured=_unmeasured(db, session, timezone),
    )


def visit_signatures(db: Session, patient_id: int, day: date) -> list[Signature]:
    """The signatures of the patient's visit on ``day`` (clinic zone), oldest first."""
    return list(
        db.scalars(
            select(Signature)
            .where(Signature.patient_id == patient_id, Signature.visit_date == day.isoformat())
            .order_by(Signature.number)
        )
    )


def signatures_on_record(
    db: Session, session: RecordingSession, timezone: str
) -> tuple[SignatureLine, ...]:
    """The signatures of ``session``'s visit, oldest first, as the report prints them
    (read only; :mod:`app.services.signatures` makes them and judges what changed)."""
    rows = visit_signatures(db, session.patient_id, local_date(session.recorded_at, timezone))
    return tuple(
        SignatureLine(
            signed_by=row.signed_by,
            signed_at=row.signed_at,
            number=row.number,
            amends=row.amends_number,
            revisions=tuple(sorted((int(k), int(v)) for k, v in row.trial_revisions.items())),
        )
        for row in rows
    )


def _visit(
    db: Session, actor: Actor, session_id: int, storage: Storage, timezone: str
) -> tuple[RecordingSession, VisitData]:
    """The visit as a copy made now: not the signed record, which it names if there is one."""
    session = load_session(db, actor, session_id, "export")
    visit = load_visit(db, session, storage, timezone=timezone)
    return session, replace(visit, signatures_on_record=signatures_on_record(db, session, timezone))


def visit_report_html(
    db: Session, actor: Actor, session_id: int, storage: Storage, *, timezone: str = "UTC"
) -> str:
    """The visit report of ``session_id``'s visit as HTML (audited ``export visit_report_html``)."""
    session, visit = _visit(db, actor, session_id, storage, timezone)
    html = render_visit_html(visit)
    audit(db, actor, "export", "visit_report_html", session.id, session.patient_id)
    db.commit()
    return html


def visit_report_pdf(
    db: Session, actor: Actor, session_id: int, storage: Storage, *, timezone: str = "UTC"
) -> bytes:
    """The visit report of ``session_id``'s visit as PDF (audited ``export visit_report_pdf``)."""
    session, visit = _visit(db, actor, session_id, storage, timezone)
    # Made once per content (2-3 s of CPU for a visit of several tasks) and kept in the
    # report cache: a report asked for again, or printed, comes from there.
    cache = ReportPdfCache.of(storage)
    key = visit_key(visit)
    pdf = cache.get_visit(session.patient_id, session.id, key)
    made = pdf is None
    if pdf is None:
        pdf = render_visit_pdf(visit)
        cache.put_visit(session.patient_id, session.id, key, pdf)
    _exported(db, actor, session)
    # a patient erased while the PDF was made: its erasure may have missed the new file
    # (as app.services.results._forget_if_erased, in a transaction begun after the put)
    if (
        made
        and db.scalar(select(RecordingSession.id).where(RecordingSession.id == session.id)) is None
    ):
        cache.forget_patient(session.patient_id)
    return pdf


def kept_visit_report_pdf(
    db: Session, actor: Actor, session_id: int, storage: Storage, *, timezone: str = "UTC"
) -> bytes | None:
    """As :func:`visit_report_pdf` (statuses, audit event), but only from the report cache:
    None when it does not hold it, never made here (a ``HEAD`` must not cost 2-3 s of CPU)."""
    session, visit = _visit(db, actor, session_id, storage, timezone)
    kept = ReportPdfCache.of(storage).get_visit(session.patient_id, session.id, visit_key(visit))
    _exported(db, actor, session)
    return kept


def _exported(db: Session, actor: Actor, session: RecordingSession) -> None:
    audit(db, actor, "export", "visit_report_pdf", session.id, session.patient_id)
    db.commit()


def visit_file_name(db: Session, session_id: int, timezone: str, suffix: str = "report") -> str:
    """``PD-0042-visit-2026-03-01-report.pdf``: the patient's code and the visit's day, as
    the trials' reports are named (not the session's internal id)."""
    session = db.get(RecordingSession, session_id)
    if session is None:
        return f"visit-{session_id}-{suffix}.pdf"
    day = local_date(session.recorded_at, timezone)
    return f"{session.patient.code}-visit-{day:%Y-%m-%d}-{suffix}.pdf"

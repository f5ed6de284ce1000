"""The administrator's page of the audit trail (``/admin/audit``), with filters and pages.

Only users holding ``audit:read`` (admins, auditors) see it; anyone else gets 403, and
the refusal is audited like an API refusal. Reading the page is audited too. Each event
shows what ``GET /api/v1/audit`` tells of it: an update's changed fields, with their
previous and new values for a reader who also holds ``patients:read``
(:func:`app.services.audit_log.changes_for`), and the patients a list returned. A page
that shows values is recorded, as the API's answer is, with the patients whose values
they are (:func:`app.audit.audit_values_shown`).
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import HTMLResponse
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.actors import Actor
from app.apikeys import AUDIT_READ
from app.audit import audit_failure, audit_values_shown
from app.auth import SessionDep
from app.errors import AppError, InvalidRequestError
from app.models import Patient
from app.schemas import MAX_ID
from app.services import audit_log
from app.web.common import PATIENT_PAGES_SCOPE, AnyPageUser, error_page, render, status_of

router = APIRouter()

PAGE_SIZE = 50


def _time(text: str | None, name: str) -> datetime | None:
    return audit_log.parse_time(text, name) if text else None


def _patient_id(db: Session, user: Actor, text: str) -> int | None:
    """The patient the filter names, by code (as clinicians know them) or by id (as the
    trail holds them); an erased patient's code is gone, its id still finds its events.

    Only a user who reads patients (an admin) may name a code: the code of a patient is
    their data, and an auditor who could filter by any code would learn which codes exist.
    An auditor gives the id (the trail's events show ids; a clinician tells the id of a
    code); a code from them is answered alike whether a patient holds it or not.
    """
    if not text:
        return None
    if text.isdigit():
        return int(text) if int(text) <= MAX_ID else 0
    if not user.has_scope(PATIENT_PAGES_SCOPE):
        raise InvalidRequestError(
            "Give the patient's id, a number as the events show it (“patient 12”): the"
            " audit trail knows patients by id, and a code is looked up only by those who"
            " read patients' data; a clinician or an administrator can tell a code's id."
        )
    found = db.scalar(select(Patient.id).where(func.lower(Patient.code) == text.lower()))
    if found is None:
        raise InvalidRequestError(
            f"No patient has the code “{text}”; give a code as the patient list shows it, or an id."
        )
    return int(found)


@router.get("/admin/audit", response_class=HTMLResponse)
def audit_page(
    request: Request,
    db: SessionDep,
    user: AnyPageUser,
    patient_id: Annotated[str | None, Query(max_length=64)] = None,
    actor: Annotated[str | None, Query(max_length=80)] = None,
    since: Annotated[str | None, Query(max_length=40)] = None,
    until: Annotated[str | None, Query(max_length=40)] = None,
    page: Annotated[int, Query(ge=1, le=100_000)] = 1,
) -> HTMLResponse:
    if not user.has_scope(AUDIT_READ):
        audit_failure(db, user, "access", "route", "/admin/audit", outcome="denied")
        return error_page(
            request,
            user,
            status_code=403,
            message="Only administrators and auditors can read the audit trail.",
        )
    form = {"patient_id": patient_id or "", "actor": actor or "", "since": since or "",
            "until": until or ""}  # fmt: skip
    try:
        f = audit_log.make_filter(
            patient_id=_patient_id(db, user, (patient_id or "").strip()),
            actor=actor,
            since=_time(since, "From"),
            until=_time(until, "Until"),
        )
    except AppError as exc:  # the filter stays, with what to correct above it
        return render(request, "audit.html", user, status_code=status_of(exc), active="audit",
                      title="Audit trail", events=[], total=0, page=1, pages=1, form=form,
                      error=str(exc))  # fmt: skip
    events, total = audit_log.list_events(
        db, user, f, limit=PAGE_SIZE, offset=(page - 1) * PAGE_SIZE
    )
    pages = max(1, -(-total // PAGE_SIZE))
    # An update's values go to those the API shows them to (patients:read), decided there.
    values = audit_log.changes_for(db, user, events)
    audit_values_shown(db, user, events, values)  # whose values these are, on record
    return render(
        request,
        "audit.html",
        user,
        active="audit",
        title="Audit trail",
        events=events,
        values=values,
        total=total,
        page=page,
        pages=pages,
        form=form,
    )

"""Signed visit reports: a clinician signs a visit; the signed PDF is kept unchanged.

A visit is the patient's sessions on one day (:func:`app.services.common.visit_sessions`).
Signing it (:func:`sign_visit`) needs the clinician's password again
(:func:`app.login.reauthenticate`); it renders the visit report of every trial
in its current result revision, with the signature line filled in, stores the
PDF bytes as they are, and records who, when, the bytes' SHA-256 and which
revision of each trial was signed (:class:`app.models.Signature`). A signature
row is never changed (the database refuses it) and its PDF is served byte for
byte (``GET /sessions/{id}/report.pdf?signed=true``).

A correction or re-analysis after signing, a trial added to or hidden from the
visit, or a change to anything else the signed report printed (a rating or its
comment, a session's medication or DBS state, last levodopa, more affected side,
dominant hand, time or clinician, the patient's code, a trial without a result
hidden or shown again: ``Signature.signed_facts``) makes an **amendment pending
signature**: the signed report stays retrievable, and signing again stores a
second signed report that says which one it amends. Every signature and every
download of a signed report is one audit event.

Signing is never refused for a trial that failed, is still being measured or is not
rated; the clinician is told of them first (:func:`app.services.visits.sign_warnings`:
the session page's sign form, ``warnings`` of the API's signing state and of its answer
to signing), and the signed report lists them. They are told only while there is
something to sign (:attr:`VisitSigning.something_to_sign`, the one place that decides it
for the page, the API and :func:`sign_visit`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace
from datetime import date, datetime
from typing import Any, Literal

from sqlalchemy.orm import Session

from app.actors import Actor
from app.audit import audit, audit_failure
from app.errors import ConflictError, NotFoundError, PermissionDeniedError
from app.login import reauthenticate
from app.models import RecordingSession, Signature, utcnow
from app.reports.rendering import render_visit_pdf
from app.reports.visit import SignatureLine
from app.services.common import load_session, visit_sessions, visit_trials
from app.services.revisions import actor_label
from app.services.visits import load_visit, sign_warnings, unmeasured_trials, visit_signatures
from app.storage import Storage
from app.timezones import local_date, to_zone

VisitStatus = Literal["unsigned", "signed", "amendment_pending"]


@dataclass(frozen=True)
class VisitSigning:
    """Where a visit stands: its signatures (oldest first) and what changed since the newest.

    ``changes`` lists, in words, each difference between the visit now and the
    newest signature (a trial's newer revision, a trial added or hidden). ``warnings``
    says what the clinician should know before signing (:func:`sign_warnings`: failed,
    pending and unrated trials), filled (by :func:`visit_signing` with ``warnings=True``,
    as :func:`signing_state` and the session page ask) only while
    :attr:`something_to_sign` holds: a signed visit's failed take is no warning.
    """

    session: RecordingSession
    visit_date: date
    signatures: list[Signature]
    current: dict[str, int]
    changes: list[str]
    warnings: tuple[str, ...] = ()

    @property
    def status(self) -> VisitStatus:
        if not self.signatures:
            return "unsigned"
        return "amendment_pending" if self.changes else "signed"

    @property
    def something_to_sign(self) -> bool:
        """Whether signing would sign something: a trial of the visit has a result, and the
        visit is not signed or changed since its newest signature (else signing is refused,
        409, and the page shows no sign form)."""
        return self.status != "signed" and bool(self.current)

    @property
    def newest(self) -> Signature | None:
        return self.signatures[-1] if self.signatures else None


def _visit_key(session: RecordingSession, timezone: str) -> tuple[int, date]:
    return session.patient_id, local_date(session.recorded_at, timezone)


#: What the visit report prints of each session and trial beyond the results, with the
#: words a change of it is told in.
_SESSION_FACTS = (
    ("recorded_at", "time"),
    ("medication_state", "medication state"),
    ("dbs_state", "DBS state"),
    ("time_since_levodopa_min", "minutes since the last levodopa"),
    ("more_affected_side", "more affected side"),
    ("dominant_hand", "dominant hand"),
    ("clinician_user_id", "clinician"),
)
_TRIAL_FACTS = (
    ("clinician_rating", "rating"),
    ("rating_comment", "rating comment"),
    ("task", "task"),
    ("hand", "side"),
    ("session_id", "session"),
)


def _fact(value: Any) -> Any:
    return value.isoformat() if isinstance(value, datetime) else value


def visit_facts(session: RecordingSession, timezone: str) -> dict[str, Any]:
    """What the visit report of ``session``'s visit prints beyond its trials' results
    (JSON-ready): the patient code, each session's facts, each measured trial's."""
    return {
        "patient_code": session.patient.code,
        "sessions": {
            str(s.id): {name: _fact(getattr(s, name)) for name, _ in _SESSION_FACTS}
            for s in visit_sessions(session, timezone)
        },
        "trials": {
            str(t.id): {name: _fact(getattr(t, name)) for name, _ in _TRIAL_FACTS}
            for t in visit_trials(session, timezone)
        },
        # the report lists every hidden trial of the visit, with the reason
        "hidden": {
            str(t.id): t.deleted_reason
            for s in visit_sessions(session, timezone)
            for t in s.trials
            if t.deleted_at is not None
        },
        # and every trial without a result: failed, or still being measured
        "unmeasured": {
            str(t.id): "failed" if t.status == "failed" else "measuring"
            for t in unmeasured_trials(session, timezone)
        },
    }


def _shown(name: str, value: Any, timezone: str) -> str:
    if value is None:
        return "none"
    if name == "recorded_at":
        return to_zone(datetime.fromisoformat(value), timezone).strftime("%H:%M")
    if name == "rating_comment":
        return "a comment"  # said as changed, not quoted
    if name == "clinician_user_id":
        return "a clinician"  # an account id says nothing on a page: "changed" alone
    return str(value)


def _fact_changes(signed: dict[str, Any], now: dict[str, Any], timezone: str) -> list[str]:
    """Each difference, in words, between the facts of a signature and those of now."""
    out = []
    if signed.get("patient_code") != now["patient_code"]:
        out.append(f"the patient code changed (signed: {signed.get('patient_code')})")
    for kind, fields in (("session", _SESSION_FACTS), ("trial", _TRIAL_FACTS)):
        before_all, now_all = signed.get(kind + "s", {}), now[kind + "s"]
        for key in sorted(set(before_all) & set(now_all), key=int):
            for name, words in fields:
                before, after = before_all[key].get(name), now_all[key].get(name)
                if before != after:
                    was, is_ = _shown(name, before, timezone), _shown(name, after, timezone)
                    detail = "" if was == is_ else f" from {was} to {is_}"
                    out.append(f"the {words} of {kind} {key} changed{detail}")
        if kind == "session":  # trials come and go with their result (revisions)
            out += [
                f"session {k} joined the visit"
                for k in sorted(set(now_all) - set(before_all), key=int)
            ]
            out += [
                f"session {k} left the visit"
                for k in sorted(set(before_all) - set(now_all), key=int)
            ]
    # trials without a result that were hidden or shown again (those with one: revisions)
    hidden_before, hidden_now = signed.get("hidden"), now["hidden"]
    if hidden_before is not None:
        measured = set(signed.get("trials", {})) | set(now["trials"])
        for key in sorted(set(hidden_now) ^ set(hidden_before), key=int):
            if key not in measured:
                done = "hidden" if key in hidden_now else "shown again"
                out.append(f"trial {key} (not measured) was {done}")
    return out + _unmeasured_changes(signed, now)


def _unmeasured_changes(signed: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """Trials without a result added or failed since the signature (those measured since are
    told by their revisions; those hidden, by the hidden ones)."""
    before, after = signed.get("unmeasured"), now["unmeasured"]
    if before is None:  # signed before the report listed them
        return []
    told = {
        *signed.get("trials", {}),
        *now["trials"],
        *(signed.get("hidden") or {}),
        *now["hidden"],
    }
    out = []
    for key in sorted((set(before) | set(after)) - told, key=int):
        was, is_ = before.get(key), after.get(key)
        if was == is_ or is_ is None:
            continue
        if was is None:
            words = "its measurement failed" if is_ == "failed" else "still being measured"
            out.append(f"trial {key} was added ({words})")
        elif is_ == "failed":
            out.append(f"the measurement of trial {key} failed (it was being measured when signed)")
        else:
            out.append(f"trial {key} is being measured again (it had failed when signed)")
    return out


def _changes(signed: dict[str, int], now: dict[str, int]) -> list[str]:
    out = []
    for trial_id, revision in sorted(now.items(), key=lambda kv: int(kv[0])):
        before = signed.get(trial_id)
        if before is None:
            out.append(f"trial {trial_id} was added (revision {revision})")
        elif before != revision:
            out.append(f"trial {trial_id} is now at revision {revision} (signed: {before})")
    for trial_id in sorted(set(signed) - set(now), key=int):
        out.append(f"trial {trial_id} was hidden or lost its result")
    return out


def visit_signing(
    db: Session, session: RecordingSession, timezone: str, *, warnings: bool = False
) -> VisitSigning:
    """The signing state of ``session``'s visit (no audit: the caller's use case audits);
    with ``warnings``, what to know before signing while there is something to sign."""
    patient_id, day = _visit_key(session, timezone)
    signatures = visit_signatures(db, patient_id, day)
    current = {str(t.id): t.result.revision for t in visit_trials(session, timezone) if t.result}
    changes = []
    if signatures:
        newest = signatures[-1]
        changes = _changes(dict(newest.trial_revisions), current)
        if newest.signed_facts is not None:  # None: signed before migration 0017
            now = visit_facts(session, timezone)
            changes += _fact_changes(dict(newest.signed_facts), now, timezone)
    state = VisitSigning(session, day, signatures, current, changes)
    if warnings and state.something_to_sign:
        return replace(state, warnings=tuple(sign_warnings(session, timezone)))
    return state


@dataclass(frozen=True)
class SignedVisit:
    """A signature just made, and what the clinician was told to know before it
    (:func:`sign_warnings`, as it stood when signing; signing was not refused for it)."""

    signature: Signature
    warnings: tuple[str, ...]


def sign_visit(
    db: Session,
    actor: Actor,
    session_id: int,
    password: str,
    storage: Storage,
    *,
    settings: Any,
    ip: str | None = None,
) -> SignedVisit:
    """Sign the visit of ``session_id``: re-authenticate, render, store the PDF, record.

    Raises
    ------
    PermissionDeniedError
        Not a clinician (an admin or an API key cannot sign; audited as denied), or the
        password is wrong (from ``reauthenticate``: 403, the login stands).
    AuthenticationError, RateLimitedError
        The account was deactivated, or too many wrong passwords (``reauthenticate``).
    ConflictError
        Nothing to sign (no measured trial), or nothing changed since the newest signature.
    """
    if actor.type != "user" or actor.role != "clinician":
        audit_failure(db, actor, "sign", "visit", session_id, outcome="denied")
        raise PermissionDeniedError(
            "Only a clinician signs a visit report; log in with a clinician's account."
        )
    reauthenticate(db, settings, actor, password, ip=ip)  # audited and committed there
    timezone = str(settings.timezone)
    session = load_session(db, actor, session_id, "sign")
    state = visit_signing(db, session, timezone, warnings=True)
    if not state.something_to_sign:
        newest = state.newest
        raise ConflictError(
            "No trial of this visit has a result yet; there is nothing to sign."
            if not state.current or newest is None
            else f"This visit was signed (signature {newest.number}) and nothing changed"
            " since; the signed report stays as it is."
        )
    line = SignatureLine(
        signed_by=actor_label(db, actor),
        signed_at=utcnow(),
        number=(state.newest.number if state.newest else 0) + 1,
        amends=state.newest.number if state.newest else None,
        revisions=tuple(sorted((int(k), v) for k, v in state.current.items())),
    )
    pdf = render_visit_pdf(load_visit(db, session, storage, timezone=timezone).signed(line))
    row = _store_signature(db, actor, state, line, pdf, storage, timezone)
    return SignedVisit(row, state.warnings)


def _store_signature(
    db: Session,
    actor: Actor,
    state: VisitSigning,
    line: SignatureLine,
    pdf: bytes,
    storage: Storage,
    timezone: str,
) -> Signature:
    """Store the signed PDF as it is and record its row and audit event, committed (the
    file is removed again when the row cannot be committed)."""
    session = state.session
    stored = storage.write_bytes("signed", ".pdf", pdf)
    try:
        row = Signature(
            patient_id=session.patient_id,
            session_id=session.id,
            visit_date=state.visit_date.isoformat(),
            number=line.number,
            amends_number=line.amends,
            signed_by=line.signed_by,
            signed_by_user_id=actor.id,
            signed_at=line.signed_at,
            sha256=hashlib.sha256(pdf).hexdigest(),
            size_bytes=len(pdf),
            pdf_path=stored.path,
            trial_revisions=dict(state.current),
            signed_facts=visit_facts(session, timezone),
        )
        db.add(row)
        audit(db, actor, "sign", "visit", session.id, session.patient_id)
        db.commit()
    except BaseException:
        db.rollback()
        storage.delete(stored.path)
        raise
    return row


def signing_state(db: Session, actor: Actor, session_id: int, *, timezone: str) -> VisitSigning:
    """The signatures of a visit, whether an amendment is pending, and what to know before
    signing it (``warnings``, as the session page's sign form says them: only while there is
    something to sign); audited ``read``."""
    session = load_session(db, actor, session_id, "read")
    state = visit_signing(db, session, timezone, warnings=True)
    audit(db, actor, "read", "signature", session.id, session.patient_id)
    db.commit()
    return state


def signed_report(
    db: Session,
    actor: Actor,
    session_id: int,
    storage: Storage,
    *,
    timezone: str,
    number: int | None = None,
) -> tuple[Signature, bytes]:
    """The signed PDF of the visit, byte for byte (the newest, or signature ``number``).

    Raises
    ------
    NotFoundError
        The visit has no (such) signature.
    ConflictError
        The stored bytes no longer match their SHA-256 (the file was damaged).
    """
    session = load_session(db, actor, session_id, "export")
    signatures = visit_signing(db, session, timezone).signatures
    row = (
        signatures[-1]
        if number is None and signatures
        else next((s for s in signatures if s.number == number), None)
    )
    if row is None:
        audit(db, actor, "export", "signed_report", session.id, session.patient_id, "not_found")
        db.commit()
        raise NotFoundError(
            "This visit has no signed report yet; a clinician signs it from the session page."
            if not signatures
            else f"This visit has no signature {number}; it has 1 to {signatures[-1].number}."
        )
    body = storage.absolute(row.pdf_path).read_bytes()
    if hashlib.sha256(body).hexdigest() != row.sha256:
        audit(db, actor, "export", "signed_report", session.id, session.patient_id, "error")
        db.commit()
        raise ConflictError(
            f"The stored signed report {row.number} does not match its SHA-256; restore the data"
            " directory from a backup and tell the administrator."
        )
    audit(db, actor, "export", "signed_report", session.id, session.patient_id)
    db.commit()
    return row, body


__all__ = [
    "SignedVisit",
    "VisitSigning",
    "sign_visit",
    "signed_report",
    "signing_state",
    "visit_signing",
]

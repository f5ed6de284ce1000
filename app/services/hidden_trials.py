"""Hidden trials where the pages meet them: a hidden trial is not "a trial that does not exist".

Hiding a trial (:func:`app.services.trials.delete_trial`, a reason required) takes
it out of the lists, reports and exports; nothing is removed, and an administrator
restores it (:func:`app.services.trials.restore_trial`). Its own page then says so:
:func:`hidden_trial_page` finds it and audits the page as a read of the trial.
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from app.actors import Actor
from app.audit import audit
from app.models import Trial
from app.services.common import visible_session


def hidden_trial(db: Session, trial_id: int) -> Trial | None:
    """The trial if it was hidden and its session and patient are not, else None (not
    audited)."""
    row = db.get(Trial, trial_id)
    if row is None or row.deleted_at is None or visible_session(db, row.session_id) is None:
        return None
    return row


def hidden_trial_page(db: Session, actor: Actor, trial_id: int) -> Trial | None:
    """The hidden trial whose page shows who hid it, when and why (audited as a read of the
    trial); None, with nothing audited, when the trial is not hidden: the caller's use case
    then audits the page it shows."""
    trial = hidden_trial(db, trial_id)
    if trial is not None:
        audit(db, actor, "read", "trial", trial.id, trial.session.patient_id)
        db.commit()
    return trial


__all__ = ["hidden_trial", "hidden_trial_page"]

"""A backup refused, and a restore failed, because the audit trail does not verify are
themselves in the audit trail (outcome ``error``, no patient data).

e368240 made ``admin backup`` refuse a trail that does not verify and ``admin restore``
fail on a restored one; neither left an event, though a successful backup or restore
does: the trail did not show that someone tried to copy, or put back, a tampered record.
"""

from __future__ import annotations

import errno
from pathlib import Path

import pytest
from cli_support import admin_cli
from sqlalchemy import func, select
from test_backup_trail import (
    ALTERED,
    CODE,
    NOTES,
    _patients_with_an_update,
    _tamper,
    settings,  # noqa: F401 - fixture (SQLite, and PostgreSQL when available)
)

import app.audit
from app import backup as backup_module
from app.audit_check import verify_trail
from app.db import dispose_engines, get_sessionmaker
from app.models import AuditEvent
from app.settings import Settings


def _events(settings: Settings, action: str) -> list[AuditEvent]:  # noqa: F811
    with get_sessionmaker(settings)() as db:
        rows = list(
            db.scalars(
                select(AuditEvent).where(AuditEvent.action == action).order_by(AuditEvent.seq)
            )
        )
        db.expunge_all()
        return rows


def _problems(settings: Settings) -> list[str]:  # noqa: F811
    with get_sessionmaker(settings)() as db:
        return verify_trail(db).problems


def _is_the_trails_failure(event: AuditEvent, action: str) -> None:
    assert (event.action, event.resource_type, event.outcome) == (action, "database", "error")
    assert event.actor_type == "system" and (event.actor_id or "").startswith("cli:")
    assert event.patient_id is None and event.resource_id is None and event.details is None
    fields = " ".join(str(getattr(event, c.key)) for c in AuditEvent.__table__.columns)
    for secret in (CODE, NOTES, ALTERED):
        assert secret not in fields


def test_a_backup_refused_for_the_trail_is_audited_as_an_error(
    settings: Settings,  # noqa: F811
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ids = _patients_with_an_update(settings)
    assert admin_cli(settings, monkeypatch, "backup", str(tmp_path / "before")) == 0
    assert [e.outcome for e in _events(settings, "backup")] == ["success"]
    _tamper(settings, ids, "field_changes")
    problems = _problems(settings)
    assert len(problems) == 1, problems

    assert admin_cli(settings, monkeypatch, "backup", str(tmp_path / "after")) == 2
    events = _events(settings, "backup")
    assert [e.outcome for e in events] == ["success", "error"]
    _is_the_trails_failure(events[-1], "backup")
    assert _problems(settings) == problems  # sealed onto the chain: hides none, adds none


def test_a_restore_failed_for_the_trail_is_audited_in_the_restored_database(
    settings: Settings,  # noqa: F811
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ids = _patients_with_an_update(settings)
    _tamper(settings, ids, "field_changes")
    with get_sessionmaker(settings)() as db:  # the backup's own event comes after its copy
        backed_up = db.scalar(select(func.max(AuditEvent.seq)))
    real_check = backup_module.trail_problems
    monkeypatch.setattr(backup_module, "trail_problems", lambda settings: None)
    assert (
        admin_cli(settings, monkeypatch, "backup", str(tmp_path / "old")) == 0
    )  # as before e368240
    monkeypatch.setattr(backup_module, "trail_problems", real_check)
    dispose_engines()

    assert admin_cli(settings, monkeypatch, "restore", "--force", str(tmp_path / "old")) == 2
    events = _events(settings, "restore")
    assert len(events) == 1, [(e.seq, e.outcome) for e in events]
    _is_the_trails_failure(events[0], "restore")
    assert events[0].seq is not None and backed_up is not None
    assert events[0].seq > backed_up  # after everything the backup brought: the restored trail
    problems = _problems(settings)
    assert len(problems) == 1 and str(ids["update"]) in problems[0], problems  # the tampering


def test_a_backup_that_fails_for_another_reason_is_not_told_as_the_trails(
    settings: Settings,  # noqa: F811
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ids = _patients_with_an_update(settings)

    def full(settings, target):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(backup_module, "_write_backup", full)
    assert admin_cli(settings, monkeypatch, "backup", str(tmp_path / "full")) == 2
    assert _events(settings, "backup") == []  # the trail verifies: no trail failure to record
    _tamper(settings, ids, "audit_event_patients")  # now it is the trail's
    assert admin_cli(settings, monkeypatch, "backup", str(tmp_path / "after")) == 2
    assert [e.outcome for e in _events(settings, "backup")] == ["error"]


def test_a_trail_failure_that_cannot_be_recorded_still_says_its_own_message(
    settings: Settings,  # noqa: F811
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    ids = _patients_with_an_update(settings)
    _tamper(settings, ids, "audit_event_patients")

    def refused(*args, **kwargs):
        raise RuntimeError(f"database is locked ({CODE})")  # a message that must not leak

    monkeypatch.setattr(app.audit, "audit_failure", refused)
    capsys.readouterr()
    assert admin_cli(settings, monkeypatch, "backup", str(tmp_path / "after")) == 2
    err = capsys.readouterr().err
    assert "no backup was made: the audit trail does not verify (1 problem)" in err, err
    note = "the failed backup could not be recorded in the audit trail (RuntimeError)"
    assert note in err
    assert err.index(note) < err.index("no backup was made")  # the refusal is said last
    assert CODE not in err
    assert _events(settings, "backup") == []

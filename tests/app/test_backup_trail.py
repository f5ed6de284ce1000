"""A backup and a restore check the whole audit trail, not the hash chain alone.

An operations review: ``admin backup`` copied a database whose kept values
(``field_changes``) had been altered, and the restore put it back without a word, though
``verify-audit`` reports it. A backup is now refused while the trail does not verify
(nothing written), and a restore whose trail does not verify (a backup made before the
check, here by the backup without it) fails with what to do. Neither message holds
patient data. On SQLite and PostgreSQL, through the ``bradyscope admin`` commands.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_support import admin_cli
from sqlalchemy import select, text, update

from app import backup as backup_module
from app.audit import audit_listed
from app.db import dispose_engines, get_sessionmaker
from app.models import FieldChange, Patient
from app.services.changes import audit_update
from app.settings import Settings

CODE = "PD-SECRET-7"
NOTES = "tremor worse after coffee"
ALTERED = "no tremor at all"


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def settings(request: pytest.FixtureRequest) -> Settings:
    name = "app_settings" if request.param == "sqlite" else "pg_settings"
    return request.getfixturevalue(name)


def _patients_with_an_update(settings: Settings) -> dict[str, int]:
    """Two patients, an update of the first (its values kept), a list of both."""
    with get_sessionmaker(settings)() as db:
        patients = [Patient(code=CODE), Patient(code="PD-OTHER")]
        db.add_all(patients)
        db.flush()
        patients[0].notes = NOTES
        event = audit_update(db, None, "patient", patients[0].id, patients[0].id,
                             {"notes": [None, NOTES]})  # fmt: skip
        listed = audit_listed(db, None, "patient", [p.id for p in patients])
        db.commit()
        return {"update": event.id, "list": listed.id, "other": patients[1].id}


def _tamper(settings: Settings, ids: dict[str, int], how: str) -> None:
    with get_sessionmaker(settings)() as db:
        if how == "field_changes":
            db.execute(
                update(FieldChange)
                .where(FieldChange.event_id == ids["update"])
                .values(changes={"notes": [None, ALTERED]})
            )
        else:  # the list no longer shows in the other patient's trail
            db.execute(
                text("DELETE FROM audit_event_patients WHERE event_id = :e AND patient_id = :p"),
                {"e": ids["list"], "p": ids["other"]},
            )
        db.commit()


def _no_patient_data(message: str) -> None:
    for secret in (CODE, NOTES, ALTERED):
        assert secret not in message


@pytest.mark.parametrize("how", ["field_changes", "audit_event_patients"])
def test_a_backup_of_a_tampered_trail_is_refused(
    settings: Settings,
    how: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    ids = _patients_with_an_update(settings)
    assert admin_cli(settings, monkeypatch, "backup", str(tmp_path / "before")) == 0
    _tamper(settings, ids, how)
    capsys.readouterr()
    target = tmp_path / "after"
    assert admin_cli(settings, monkeypatch, "backup", str(target)) == 2
    err = capsys.readouterr().err
    assert "no backup was made: the audit trail does not verify (1 problem)" in err, err
    assert "bradyscope admin verify-audit" in err and "nothing was written" in err
    assert "Traceback" not in err
    _no_patient_data(err)
    assert not target.exists()
    # what verify-audit says of the same database, which the message sends the reader to
    assert admin_cli(settings, monkeypatch, "verify-audit") == 2
    assert f"(id {ids['list' if how == 'audit_event_patients' else 'update']})" in (
        capsys.readouterr().err
    )


def test_a_restored_trail_that_does_not_verify_fails_the_restore(
    settings: Settings,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    ids = _patients_with_an_update(settings)
    _tamper(settings, ids, "field_changes")
    # a backup made without the check (as before it existed) holds the altered values
    real_check = backup_module.trail_problems
    monkeypatch.setattr(backup_module, "trail_problems", lambda settings: None)
    assert admin_cli(settings, monkeypatch, "backup", str(tmp_path / "old")) == 0
    monkeypatch.setattr(backup_module, "trail_problems", real_check)
    dispose_engines()
    capsys.readouterr()
    assert admin_cli(settings, monkeypatch, "restore", "--force", str(tmp_path / "old")) == 2
    err = capsys.readouterr().err
    assert "the backup was restored, but its audit trail does not verify (1 problem)" in err, err
    assert "Do not start bradyscope on it" in err and "bradyscope admin verify-audit" in err
    _no_patient_data(err)
    with get_sessionmaker(settings)() as db:  # restored indeed, altered values and all
        kept = db.scalars(select(FieldChange.changes)).one()
    assert kept == {"notes": [None, ALTERED]}


def test_an_intact_trail_is_backed_up_and_restored_without_a_word(
    settings: Settings,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    _patients_with_an_update(settings)
    assert backup_module.trail_problems(settings) is None
    assert admin_cli(settings, monkeypatch, "backup", str(tmp_path / "good")) == 0
    dispose_engines()
    status = admin_cli(settings, monkeypatch, "restore", "--force", str(tmp_path / "good"))
    assert status == 0, capsys.readouterr().err
    assert backup_module.trail_problems(settings) is None

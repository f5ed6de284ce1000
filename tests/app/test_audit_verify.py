"""``verify-audit`` checks the rows kept beside the chain against what their events sealed.

An update's values (``field_changes``) and the patients a list returned
(``audit_event_patients``) are outside the hash chain; their events seal a digest
and the ids. Altering a value, deleting or adding a listed patient shows; erasing
a patient, which removes their values by design, does not. SQLite and PostgreSQL
(the JSON column reads back differently on each).
"""

from __future__ import annotations

import pytest
from cli_support import admin_cli
from sqlalchemy import select, text, update
from sqlalchemy.orm import Session, sessionmaker

from app.audit import audit_listed
from app.audit_check import verify_trail
from app.db import get_sessionmaker
from app.models import FieldChange, Patient
from app.services.changes import audit_update
from app.services.erasure import erase_patient
from app.settings import Settings
from app.storage import Storage


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def settings(request: pytest.FixtureRequest) -> Settings:
    name = "app_settings" if request.param == "sqlite" else "pg_settings"
    return request.getfixturevalue(name)


def _trail(sessions: sessionmaker[Session]) -> dict[str, int]:
    """Three patients, an update of each (values kept), and a list that returned them all;
    the update and the list event ids by name."""
    with sessions() as db:
        patients = [Patient(code=f"PD-{i}", notes="before") for i in range(3)]
        db.add_all(patients)
        db.flush()
        ids = {}
        for i, p in enumerate(patients):
            changed = {"notes": ["before", f"after {i}"]}
            p.notes = f"after {i}"
            ids[f"update{i}"] = audit_update(db, None, "patient", p.id, p.id, changed).id
        ids["list"] = audit_listed(db, None, "patient", [p.id for p in patients]).id
        for i, p in enumerate(patients):
            ids[f"patient{i}"] = p.id
        db.commit()
    with sessions() as db:
        assert verify_trail(db).ok
    return ids


def _problems(sessions: sessionmaker[Session]) -> list[str]:
    with sessions() as db:
        return verify_trail(db).problems


def test_an_altered_value_is_reported(
    settings: Settings, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    sessions = get_sessionmaker(settings)
    ids = _trail(sessions)
    assert admin_cli(settings, monkeypatch, "verify-audit") == 0
    assert "their kept values and listed patients match" in capsys.readouterr().out
    with sessions() as db:
        db.execute(
            update(FieldChange)
            .where(FieldChange.event_id == ids["update1"])
            .values(changes={"notes": ["before", "something else"]})
        )
        db.commit()
    problems = _problems(sessions)
    assert len(problems) == 1, problems
    assert f"(id {ids['update1']})" in problems[0] and "altered" in problems[0]
    assert admin_cli(settings, monkeypatch, "verify-audit") == 2
    err = capsys.readouterr().err
    assert "tampered with" in err and f"(id {ids['update1']})" in err, err


def test_deleted_values_of_a_patient_not_erased_are_reported(settings: Settings) -> None:
    sessions = get_sessionmaker(settings)
    ids = _trail(sessions)
    with sessions() as db:
        db.execute(text("DELETE FROM field_changes WHERE event_id = :e"), {"e": ids["update0"]})
        db.commit()
    problems = _problems(sessions)
    assert len(problems) == 1, problems
    assert f"(id {ids['update0']})" in problems[0] and "was not erased" in problems[0]


def test_a_deleted_listed_patient_is_reported(settings: Settings) -> None:
    sessions = get_sessionmaker(settings)
    ids = _trail(sessions)
    with sessions() as db:
        db.execute(
            text("DELETE FROM audit_event_patients WHERE event_id = :e AND patient_id = :p"),
            {"e": ids["list"], "p": ids["patient1"]},
        )
        db.commit()
    problems = _problems(sessions)
    assert len(problems) == 1, problems
    assert f"(id {ids['list']}) returned patients {ids['patient1']}," in problems[0]
    assert "lacks" in problems[0]


@pytest.mark.parametrize("where", ["same_event", "other_event"])
def test_an_added_listed_patient_is_reported(settings: Settings, where: str) -> None:
    sessions = get_sessionmaker(settings)
    ids = _trail(sessions)
    event_id = ids["list"] if where == "same_event" else ids["update2"]
    with sessions() as db:
        db.execute(
            text("INSERT INTO audit_event_patients (event_id, patient_id) VALUES (:e, 999)"),
            {"e": event_id},
        )
        db.commit()
    problems = _problems(sessions)
    assert len(problems) == 1, problems
    assert f"event id {event_id}" in problems[0] or f"(id {event_id})" in problems[0]
    assert "999" in problems[0] and "added" in problems[0]


def test_erasing_a_patient_reports_nothing(
    settings: Settings, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    sessions = get_sessionmaker(settings)
    ids = _trail(sessions)
    with sessions() as db:
        erase_patient(db, Storage.from_settings(settings), None, "PD-1")
    with sessions() as db:
        kept = set(db.scalars(select(FieldChange.event_id)))
    assert kept == {ids["update0"], ids["update2"]}  # the erased patient's values are gone
    assert _problems(sessions) == []
    assert admin_cli(settings, monkeypatch, "verify-audit") == 0
    assert "intact" in capsys.readouterr().out

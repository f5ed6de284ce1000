"""Database layer: SQLite pragmas, UTC timestamps, constraints, calibration lookup."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone

import pytest
import sqlalchemy as sa
from sqlalchemy.exc import DBAPIError, IntegrityError, StatementError

from app.db import current_revision, get_engine, head_revision
from app.errors import CalibrationMissingError
from app.models import (
    ACTOR_TYPES,
    AuditEvent,
    Calibration,
    Job,
    Patient,
    RecordingSession,
    Result,
    Rig,
    Trial,
    Video,
    next_calibration_version,
)
from app.services.calibrations import calibration_for

T0 = datetime(2026, 3, 1, 9, 0, tzinfo=UTC)
RIG_DOC = {"format": "bradyscope.rig/1", "units": "mm", "cameras": []}


def test_fixture_database_is_migrated_to_head(app_settings):
    assert current_revision(app_settings) == head_revision()


def test_sqlite_pragmas_are_set_on_every_connection(app_settings):
    with get_engine(app_settings).connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
        assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar() == 30_000


def test_foreign_keys_are_enforced(db_session):
    db_session.add(Trial(session_id=12345, hand="left"))
    with pytest.raises(IntegrityError):
        db_session.flush()


def test_a_failed_statement_does_not_carry_its_values(db_session):
    """The error of a failed write is logged (app.main): it must not hold the patient
    code, notes or file names the statement carried."""
    db_session.add(Patient(code="PD-SECRET-7", notes="lives at 4 Example Street"))
    db_session.flush()
    db_session.add(Patient(code="PD-SECRET-7", notes="lives at 4 Example Street"))
    with pytest.raises(IntegrityError) as caught:
        db_session.flush()
    text = str(caught.value)
    assert "INSERT INTO patients" in text and "hidden due to hide_parameters" in text
    assert "PD-SECRET-7" not in text and "Example Street" not in text
    db_session.rollback()


def test_timestamps_round_trip_as_aware_utc(db_session):
    cest = timezone(timedelta(hours=2))
    db_session.add(Patient(code="PD-1", created_at=datetime(2026, 6, 1, 14, 30, tzinfo=cest)))
    db_session.commit()
    db_session.expire_all()
    got = db_session.scalars(sa.select(Patient)).one().created_at
    assert got.tzinfo is not None and got.utcoffset() == timedelta(0)
    assert got == datetime(2026, 6, 1, 12, 30, tzinfo=UTC)


def test_naive_timestamps_are_refused(db_session):
    db_session.add(Patient(code="PD-1", created_at=datetime(2026, 6, 1, 14, 30)))
    with pytest.raises(StatementError, match="naive datetime"):
        db_session.flush()


@pytest.mark.parametrize(
    ("model", "values"),
    [
        (RecordingSession, {"medication_state": "maybe"}),
        (RecordingSession, {"more_affected_side": "both"}),
        (RecordingSession, {"time_since_levodopa_min": -5}),
        (RecordingSession, {"dbs_state": "yes"}),
    ],
)
def test_check_constraints_reject_bad_enumerations(db_session, model, values):
    rig = Rig(name="r")
    patient = Patient(code="PD-1")
    db_session.add_all([rig, patient])
    db_session.flush()
    db_session.add(model(patient_id=patient.id, rig_id=rig.id, recorded_at=T0, **values))
    with pytest.raises(IntegrityError):
        db_session.flush()


def test_a_trial_has_at_most_one_result(db_session):
    rig, patient = Rig(name="r"), Patient(code="PD-1")
    db_session.add_all([rig, patient])
    db_session.flush()
    s = RecordingSession(patient_id=patient.id, rig_id=rig.id, recorded_at=T0)
    db_session.add(s)
    db_session.flush()
    trial = Trial(session_id=s.id, hand="left")
    db_session.add(trial)
    db_session.flush()
    db_session.add(Result(trial_id=trial.id, document={"format": "bradyscope.result/1"}))
    db_session.flush()
    db_session.add(Result(trial_id=trial.id, document={}))
    with pytest.raises(IntegrityError):
        db_session.flush()


def test_a_video_belongs_to_exactly_one_trial_or_calibration(db_session):
    video = dict(
        side="left", size_bytes=1, sha256="0" * 64, fps=100.0, frame_count=1, width=8, height=8
    )
    db_session.add(Video(path="files/videos/00/a.mp4", **video))
    with pytest.raises(IntegrityError):
        db_session.flush()


def _calibration(db, rig, *, valid_from, status="ready"):
    cal = Calibration(
        rig_id=rig.id,
        version=next_calibration_version(db, rig.id),
        valid_from=valid_from,
        rig_json=RIG_DOC if status == "ready" else None,
        source="rig_file",
        status=status,
    )
    db.add(cal)
    db.flush()
    return cal


def test_calibration_lookup_picks_newest_ready_valid_at_session_time(db_session):
    db = db_session
    rig, other_rig, patient = Rig(name="clinic-A"), Rig(name="clinic-B"), Patient(code="PD-1")
    db.add_all([rig, other_rig, patient])
    db.flush()
    old = _calibration(db, rig, valid_from=T0 - timedelta(days=30))
    current = _calibration(db, rig, valid_from=T0 - timedelta(days=1))
    _calibration(db, rig, valid_from=T0 - timedelta(hours=1), status="pending")
    _calibration(db, rig, valid_from=T0 + timedelta(days=1))  # future: not valid yet
    _calibration(db, other_rig, valid_from=T0 - timedelta(hours=2))  # another rig
    assert [c.version for c in (old, current)] == [1, 2]

    session = RecordingSession(patient_id=patient.id, rig_id=rig.id, recorded_at=T0)
    db.add(session)
    db.flush()
    assert calibration_for(db, session).id == current.id

    session.calibration_id = old.id  # explicit override wins
    assert calibration_for(db, session).id == old.id

    early = RecordingSession(
        patient_id=patient.id, rig_id=rig.id, recorded_at=T0 - timedelta(days=60)
    )
    db.add(early)
    db.flush()
    with pytest.raises(CalibrationMissingError, match="no ready calibration"):
        calibration_for(db, early)


def test_calibration_override_must_be_ready(db_session):
    db = db_session
    rig, patient = Rig(name="clinic-A"), Patient(code="PD-1")
    db.add_all([rig, patient])
    db.flush()
    pending = _calibration(db, rig, valid_from=T0, status="pending")
    session = RecordingSession(
        patient_id=patient.id, rig_id=rig.id, recorded_at=T0, calibration_id=pending.id
    )
    db.add(session)
    db.flush()
    with pytest.raises(CalibrationMissingError, match="not ready"):
        calibration_for(db, session)


def test_calibration_versions_are_unique_per_rig(db_session):
    db = db_session
    rig = Rig(name="clinic-A")
    db.add(rig)
    db.flush()
    _calibration(db, rig, valid_from=T0)
    db.add(Calibration(rig_id=rig.id, version=1, valid_from=T0, source="rig_file"))
    with pytest.raises(IntegrityError):
        db.flush()


def test_job_defaults(db_session):
    job = Job(kind="analyze_trial")
    db_session.add(job)
    db_session.flush()
    assert (job.status, job.progress, job.attempts, job.payload) == ("queued", 0.0, 0, {})
    assert job.run_after.tzinfo is not None


def _audit_event(db) -> int:
    event = AuditEvent(actor_type="user", actor_id="1", action="read", resource_type="patient")
    db.add(event)
    db.commit()
    return event.id


def _assert_append_only(db, event_id) -> None:
    for statement in (
        sa.update(AuditEvent).where(AuditEvent.id == event_id).values(outcome="denied"),
        sa.delete(AuditEvent).where(AuditEvent.id == event_id),
    ):
        with pytest.raises(DBAPIError, match="append-only"):
            db.execute(statement)
        db.rollback()
    assert db.get(AuditEvent, event_id).outcome == "success"


@pytest.mark.parametrize("actor_type", ACTOR_TYPES)
def test_audit_actor_types_are_the_models_and_the_migrations(db_session, actor_type):
    db_session.add(AuditEvent(actor_type=actor_type, action="login", resource_type="user"))
    db_session.commit()


def test_audit_actor_type_is_constrained(db_session):
    db_session.add(AuditEvent(actor_type="robot", action="login", resource_type="user"))
    with pytest.raises(IntegrityError):
        db_session.flush()


def test_audit_events_are_append_only_sqlite(db_session):
    _assert_append_only(db_session, _audit_event(db_session))


@pytest.mark.postgres
def test_audit_events_are_append_only_postgres(pg_settings):
    from app.db import get_sessionmaker

    with get_sessionmaker(pg_settings)() as db:
        _assert_append_only(db, _audit_event(db))
        with pytest.raises(DBAPIError, match="append-only"):
            db.execute(sa.text("TRUNCATE audit_events"))
        db.rollback()


@pytest.mark.parametrize(
    ("given", "used"),
    [
        ("postgresql://u@h:5432/d", "postgresql+psycopg://u@h:5432/d"),
        ("postgres://u:p@h/d", "postgresql+psycopg://u:p@h/d"),
        ("postgresql+psycopg://u@h/d", "postgresql+psycopg://u@h/d"),
        ("sqlite:////srv/x.sqlite3", "sqlite:////srv/x.sqlite3"),
    ],
)
def test_database_urls_use_the_installed_driver(tmp_path, given, used):
    from app.settings import Settings

    assert Settings(data_dir=tmp_path, database_url=given).effective_database_url == used


def test_default_database_is_sqlite_in_the_data_dir(tmp_path, monkeypatch):
    from app.settings import Settings

    monkeypatch.delenv("BRADYSCOPE_DATABASE_URL", raising=False)
    monkeypatch.setenv("BRADYSCOPE_DATA_DIR", str(tmp_path / "d"))
    settings = Settings()
    assert settings.data_dir == tmp_path / "d"
    assert settings.effective_database_url == f"sqlite:///{tmp_path / 'd' / 'bradyscope.sqlite3'}"


def test_unreachable_database_is_one_sentence(tmp_path, capsys, monkeypatch):
    import socket

    from app.cli import main

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setenv("BRADYSCOPE_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("BRADYSCOPE_DATABASE_URL", f"postgresql://nobody:secret@127.0.0.1:{port}/x")
    assert main(["admin", "migrate"]) == 2
    err = capsys.readouterr().err
    assert "cannot be reached" in err and "BRADYSCOPE_DATABASE_URL" in err
    assert "secret" not in err  # the password is not echoed
    assert len(err.strip().splitlines()) == 1


def test_a_ready_calibration_is_judged_once_when_stored(db_session):
    db = db_session
    rig = Rig(name="clinic-V")
    db.add(rig)
    db.flush()
    cal = _calibration(db, rig, valid_from=T0, status="pending")
    assert cal.verdict is None  # nothing to judge yet
    cal.quality, cal.rms_px = {"rms_px": 0.8, "views_used": 30}, 0.8
    cal.rig_json, cal.status = RIG_DOC, "ready"
    db.flush()
    assert cal.verdict == "acceptable" and "reprojection" in cal.verdict_reasons[0]
    cal.quality = {"rms_px": 3.0}  # stored figures change: the verdict stays as judged
    db.flush()
    assert cal.verdict == "acceptable"
    with pytest.raises(IntegrityError):  # a ready calibration without a verdict is refused
        db.execute(sa.update(Calibration).where(Calibration.id == cal.id).values(verdict=None))

"""The demo seed: account, rig, patient with a progression; idempotent; real analyses."""

from __future__ import annotations

import itertools
import re
from datetime import UTC, datetime

from sqlalchemy import func, select

from app import demo
from app.models import Calibration, Job, Patient, RecordingSession, Result, Rig, Trial, User
from app.passwords import verify_password

NOW = datetime(2026, 1, 15, 12, 0, tzinfo=UTC)


def _counts(db_sessionmaker) -> dict[str, int]:
    with db_sessionmaker() as db:
        return {
            m.__name__: db.scalar(select(func.count()).select_from(m)) or 0
            for m in (User, Rig, Calibration, Patient, RecordingSession, Trial, Job)
        }


def test_the_planned_progression_is_realistic():
    trials = demo.demo_trials()
    assert len(trials) == len(demo.VISITS) * 2 * 2  # visits x medication x hands
    assert len({t.seed for t in trials}) == len(trials)

    def pick(hand, med):
        return sorted(
            (t for t in trials if t.hand == hand and t.medication_state == med),
            key=lambda t: t.visit,
        )

    for hand in ("left", "right"):
        off = pick(hand, "off")
        # Over the visits OFF medication: smaller, slower, more decrement, not fewer pauses.
        assert all(a.amplitude_mm > b.amplitude_mm for a, b in itertools.pairwise(off))
        assert all(a.frequency_hz > b.frequency_hz for a, b in itertools.pairwise(off))
        assert all(
            a.decrement_mm_per_tap > b.decrement_mm_per_tap for a, b in itertools.pairwise(off)
        )
        # Medication ON is better than OFF at every visit.
        for o, n in zip(off, pick(hand, "on"), strict=True):
            assert n.amplitude_mm > o.amplitude_mm and n.frequency_hz > o.frequency_hz
            assert len(n.hesitations) + len(n.halts) <= len(o.hesitations) + len(o.halts)
    # Every planned pause fits in the demo's clips (none is dropped to make them fit).
    for t in trials:
        assert demo.pauses_that_fit(t, demo.CLIP_S) == (t.hesitations, t.halts), t
    # The right hand is the more affected one at the last visit.
    assert pick("right", "off")[-1].amplitude_mm < pick("left", "off")[-1].amplitude_mm
    # The right hand OFF medication is simulated first at every visit (trend appears first).
    assert [(t.hand, t.medication_state) for t in trials[: len(demo.VISITS)]] == [
        ("right", "off")
    ] * 3


def test_seed_demo_is_idempotent_and_its_trials_are_measured(app_settings, db_sessionmaker):
    from app.worker import run_worker

    text = demo.seed_demo(app_settings, background=False, clip_s=3.0, max_trials=1, now=NOW)
    password = re.search(r"password: (\S+)", text).group(1)
    assert demo.DEMO_EMAIL in text and demo.DEMO_PATIENT in text
    first = _counts(db_sessionmaker)
    assert first["Patient"] == 1 and first["Rig"] == 1 and first["Calibration"] == 1
    assert first["RecordingSession"] == 2 * len(demo.VISITS)
    assert first["Trial"] == 1 and first["Job"] == 1
    with db_sessionmaker() as db:
        user = db.scalars(select(User).where(User.email == demo.DEMO_EMAIL)).one()
        assert verify_password(user.password_hash, password)
        cal = db.scalars(select(Calibration)).one()
        assert cal.status == "ready" and cal.rig_json["format"] == "bradyscope.rig/1"
        sessions = db.scalars(select(RecordingSession).order_by(RecordingSession.recorded_at)).all()
        assert (sessions[-1].recorded_at - sessions[0].recorded_at).days > 600  # about two years
        assert {s.medication_state for s in sessions} == {"on", "off"}
        assert all(cal.valid_from <= s.recorded_at for s in sessions)
    # The file keeps the credentials, readable by the owner only.
    cred = app_settings.data_dir / demo.CREDENTIALS_FILE
    assert (cred.stat().st_mode & 0o777) == 0o600 and password in cred.read_text()

    # A restart adds nothing twice and prints the same password.
    again = demo.seed_demo(app_settings, background=False, clip_s=3.0, max_trials=0, now=NOW)
    assert f"password: {password}" in again
    assert _counts(db_sessionmaker) == first

    # The queued trial is a real recording: the real worker measures it.
    assert run_worker(app_settings, once=True) == 2  # the analysis, then its PDF report
    with db_sessionmaker() as db:
        job = db.scalars(select(Job).where(Job.kind == "analyze_trial")).one()
        assert job.status == "succeeded", job.error
        result = db.scalars(select(Result)).one()
        metrics = result.document["metrics"]
        planned = demo.demo_trials()[0]
        # Within the metrics' tolerances on clean simulated video (a few mm, ~0.1 Hz).
        assert abs(metrics["frequency_hz"] - planned.frequency_hz) < 0.3  # Hz
        assert (
            metrics["amplitude_mm_mean"] < planned.amplitude_mm + 3
        )  # mm; decrement shrinks later taps
        assert metrics["tap_count"] >= 6


def test_generation_stops_when_asked(app_settings, db_sessionmaker):
    import threading

    demo.seed_demo(app_settings, background=False, max_trials=0, now=NOW)
    with db_sessionmaker() as db:
        sessions = {(i, med): s.id for i, med, s in _sessions(db)}
        todo = demo._missing_trials(db, sessions)
    assert len(todo) == len(demo.demo_trials())
    stop = threading.Event()
    stop.set()
    assert demo.generate_recordings(app_settings, 1, todo, clip_s=3.0, stop_event=stop) == 0
    assert _counts(db_sessionmaker)["Trial"] == 0
    assert not list((app_settings.data_dir / "tmp").glob("demo-*"))  # nothing left behind


def _sessions(db):
    rows = db.scalars(select(RecordingSession)).all()
    for s in rows:
        visit = int(re.match(r"Demo visit (\d+) of", s.notes).group(1)) - 1
        yield visit, s.medication_state, s


def test_a_running_simulation_stops_promptly(tmp_path):
    import threading

    import pytest

    stop = threading.Event()
    stop.set()
    with pytest.raises(demo._Stopped):
        demo._simulate(demo.demo_trials()[0], tmp_path, clip_s=2.0, stop_event=stop)

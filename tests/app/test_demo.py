"""The demo seed: account, rig, patient with a progression; idempotent; real analyses."""

from __future__ import annotations

import itertools
import re
from datetime import UTC, datetime

import pytest
from sqlalchemy import func, select

from app import demo, demo_plan
from app.models import Calibration, Job, Patient, RecordingSession, Result, Rig, Trial, User
from app.passwords import verify_password
from core.tasks import Task

NOW = datetime(2026, 1, 15, 12, 0, tzinfo=UTC)


def _counts(db_sessionmaker) -> dict[str, int]:
    with db_sessionmaker() as db:
        return {
            m.__name__: db.scalar(select(func.count()).select_from(m)) or 0
            for m in (User, Rig, Calibration, Patient, RecordingSession, Trial, Job)
        }


def test_the_planned_progression_is_realistic():
    everything = demo_plan.demo_trials()
    trials = [t for t in everything if t.task is Task.FINGER_TAPPING]
    assert len(trials) == len(demo_plan.VISITS) * 2 * 2  # visits x medication x hands
    assert len({t.seed for t in everything}) == len(everything)

    def pick(hand, med):
        return sorted(
            (t for t in trials if t.hand == hand and t.medication_state == med),
            key=lambda t: t.visit,
        )

    for hand in ("left", "right"):
        off = pick(hand, "off")
        # Over the visits OFF medication: smaller, slower, more decrement, not fewer pauses.
        assert all(a.amplitude > b.amplitude for a, b in itertools.pairwise(off))
        assert all(a.frequency_hz > b.frequency_hz for a, b in itertools.pairwise(off))
        assert all(
            a.decrement_per_cycle > b.decrement_per_cycle for a, b in itertools.pairwise(off)
        )
        # Medication ON is better than OFF at every visit.
        for o, n in zip(off, pick(hand, "on"), strict=True):
            assert n.amplitude > o.amplitude and n.frequency_hz > o.frequency_hz
            assert len(n.hesitations) + len(n.halts) <= len(o.hesitations) + len(o.halts)
    # Every recording holds the ten cycles the items ask for, and every planned pause
    # (none is dropped to make them fit), in 6 s or the half seconds more it needs.
    for t in everything:
        assert demo_plan.pauses_that_fit(t, t.clip_s) == (t.hesitations, t.halts), t
        moving_s = t.clip_s - demo_plan.STILL_S - t.pauses_s
        assert 0.9 * moving_s * t.frequency_hz >= demo_plan.CYCLES, t
        assert (
            t.clip_s == demo_plan.CLIP_S
            or 0.9 * (moving_s - 0.5) * t.frequency_hz < demo_plan.CYCLES
        ), t
    # The right hand is the more affected one at the last visit.
    assert pick("right", "off")[-1].amplitude < pick("left", "off")[-1].amplitude
    # The other items of the examination come last: once each, at the last visit, OFF
    # medication, on the more affected side, each shrinking from cycle to cycle.
    others = everything[len(trials) :]
    assert [t.task for t in others] == [t for t in Task if t is not Task.FINGER_TAPPING]
    assert {(t.visit, t.medication_state, t.hand) for t in others} == {
        (len(demo_plan.VISITS) - 1, "off", "right")
    }
    assert all(t.decrement_per_cycle < 0 for t in others)
    # The right hand OFF medication is simulated first at every visit (trend appears first).
    assert [(t.hand, t.medication_state) for t in trials[: len(demo_plan.VISITS)]] == [
        ("right", "off")
    ] * 3


def test_seed_demo_is_idempotent_and_its_trials_are_measured(app_settings, db_sessionmaker):
    from app.worker import run_worker

    text = demo.seed_demo(app_settings, background=False, clip_s=3.0, max_trials=1, now=NOW)
    password = re.search(r"password: (\S+)", text).group(1)
    assert demo.DEMO_EMAIL in text and demo.DEMO_PATIENT in text
    first = _counts(db_sessionmaker)
    # the hands' rig, and the same cameras placed for the feet and for the legs
    assert first["Patient"] == 1 and first["Rig"] == 3 and first["Calibration"] == 3
    assert first["RecordingSession"] == 2 * len(demo_plan.VISITS)
    assert first["Trial"] == 1 and first["Job"] == 1
    with db_sessionmaker() as db:
        user = db.scalars(select(User).where(User.email == demo.DEMO_EMAIL)).one()
        assert verify_password(user.password_hash, password)
        cals = db.scalars(select(Calibration)).all()
        assert all(c.status == "ready" for c in cals)
        assert all(c.rig_json["format"] == "bradyscope.rig/1" for c in cals)
        sessions = db.scalars(select(RecordingSession).order_by(RecordingSession.recorded_at)).all()
        assert (sessions[-1].recorded_at - sessions[0].recorded_at).days > 600  # about two years
        assert {s.medication_state for s in sessions} == {"on", "off"}
        assert all(c.valid_from <= s.recorded_at for s in sessions for c in cals)
        assert {s.rig.name for s in sessions} == {demo.DEMO_RIG}
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
        planned = demo_plan.demo_trials()[0]
        # Within the metrics' tolerances on clean simulated video (a few mm, ~0.1 Hz).
        assert abs(metrics["frequency_hz"] - planned.frequency_hz) < 0.3  # Hz
        assert (
            metrics["amplitude_mm_mean"] < planned.amplitude + 3
        )  # mm; decrement shrinks later taps
        assert metrics["tap_count"] >= 6


@pytest.mark.slow
def test_the_feet_and_legs_are_recorded_with_their_rig_and_measured(app_settings, db_sessionmaker):
    """Toe tapping and leg agility at the last visit: uploaded with the rig placed for them
    (the hand tasks take the session's), measured by the real worker as planned."""
    from app.worker import run_worker

    demo.seed_demo(app_settings, background=False, max_trials=0, now=NOW)
    with db_sessionmaker() as db:
        sessions = {(i, med): s.id for i, med, s in _sessions(db)}
        todo = [
            (t, s) for t, s in demo._missing_trials(db, sessions) if t.task in demo.DEMO_TASK_RIGS
        ]
        rigs = {r.name: r.id for r in db.scalars(select(Rig))}
    assert len(todo) == 2
    task_rigs = {task: rigs[name] for task, (name, _) in demo.DEMO_TASK_RIGS.items()}
    assert demo.generate_recordings(app_settings, 1, todo, clip_s=4.0, rigs=task_rigs) == 2
    run_worker(app_settings, once=True)
    with db_sessionmaker() as db:
        for planned, _ in todo:
            trial = db.scalars(select(Trial).where(Trial.task == planned.task.value)).one()
            assert (trial.hand, trial.status) == ("right", "succeeded"), trial.task
            assert trial.rig_id == task_rigs[planned.task], trial.task
            assert trial.clinician_rating == 3
            metrics = trial.result.document["metrics"]
            # 4-s clips: the first cycles of the planned rhythm, shrinking as planned
            assert abs(metrics["frequency_hz"] - planned.frequency_hz) < 0.1, trial.task  # Hz
            first = planned.amplitude
            assert first * 0.8 < metrics["amplitude_mean"] <= first * 1.02, trial.task
            assert metrics["amplitude_decrement_per_cycle"] < 0, trial.task
        # A restart finds them: it does not make them again.
        missing = demo._missing_trials(db, sessions)
        assert not [t for t, _ in missing if t.task in demo.DEMO_TASK_RIGS]


def test_generation_stops_when_asked(app_settings, db_sessionmaker):
    import threading

    demo.seed_demo(app_settings, background=False, max_trials=0, now=NOW)
    with db_sessionmaker() as db:
        sessions = {(i, med): s.id for i, med, s in _sessions(db)}
        todo = demo._missing_trials(db, sessions)
    assert len(todo) == len(demo_plan.demo_trials())
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
    with pytest.raises(demo_plan.SimulationStopped):
        demo_plan.simulate_trial(demo_plan.demo_trials()[0], tmp_path, clip_s=2.0, stop_event=stop)


def test_a_simulation_process_that_dies_fails_its_recording_and_is_replaced(tmp_path):
    """A killed simulation child (out of memory, say) fails the recording it was making at
    once, with its exit code, and the next recording is made by a new child; a process pool
    would have waited for the lost result forever."""
    import os
    import signal
    import threading
    import time

    trial = demo_plan.demo_trials()[0]
    simulator = demo_plan.Simulator(None)
    failure: list[BaseException] = []

    def first() -> None:
        try:
            simulator.simulate(trial, tmp_path, 3.0)
        except RuntimeError as exc:
            failure.append(exc)

    try:
        making = threading.Thread(target=first)
        making.start()
        deadline = time.monotonic() + 30
        while (
            simulator._proc is None or simulator._proc.pid is None
        ) and time.monotonic() < deadline:
            time.sleep(0.05)
        os.kill(simulator._proc.pid, signal.SIGKILL)
        making.join(timeout=30)
        assert not making.is_alive(), "the dead child's recording was waited for"
        assert len(failure) == 1 and f"exit code -{signal.SIGKILL}" in str(failure[0])
        left, right = simulator.simulate(trial, tmp_path, 1.0)
        assert left.stat().st_size > 0 and right.stat().st_size > 0
        # one that died between two recordings is replaced too
        os.kill(simulator._proc.pid, signal.SIGKILL)
        simulator._proc.join(10)
        left.unlink()
        assert simulator.simulate(trial, tmp_path, 1.0)[0].stat().st_size > 0
    finally:
        simulator.close()


def test_the_demo_tells_the_address_it_is_served_at(app_settings):
    """`bradyscope serve --demo --port 8131` printed 'Open http://127.0.0.1:8000/'."""
    text = demo.seed_demo(
        app_settings, background=False, max_trials=0, now=NOW, url="http://127.0.0.1:8131/"
    )
    assert "Open http://127.0.0.1:8131/ and log in with:" in text

"""Demo data for ``bradyscope serve --demo``: a clinician, rigs, a patient followed for two years.

:func:`seed_demo` creates (once; it is idempotent):

- a clinician account ``demo@example.org`` whose random password is kept in
  ``<data_dir>/demo-credentials.txt`` (mode 600) and printed at every start;
- a rig ``demo-rig`` calibrated with the simulator's true rig (640 x 512 px),
  and the same cameras placed for the feet (``demo-rig-feet``, toe tapping) and
  for the legs (``demo-rig-legs``, leg agility) as docs/protocols.md asks,
  each calibrated the same way;
- a patient ``DEMO-0001`` with visits over two years, each with a session OFF
  medication and one ON medication: finger tapping gets smaller, slower,
  decrements more and hesitates more as the disease progresses, the right hand
  more than the left, and medication ON improves it;
- one finger-tapping trial per hand and session, and at the last visit, OFF
  medication, the other items of the examination (hand movements,
  pronation–supination, toe tapping, leg agility) on the more affected right
  side, each made from a real simulated stereo recording (640 x 512 px, 60 fps,
  6 s, MPEG-4) uploaded through the service's own trial use case (the feet and
  legs with their own rig), so the worker measures it like any upload.

What the patient does and how it is simulated is :mod:`app.demo_plan`. The
recordings are simulated in a background thread, most useful first (the
right hand OFF medication at every visit, so that the trend appears early;
the other tasks last), so the pages fill while the server runs. Restarting
only adds what is missing.
"""

from __future__ import annotations

import logging
import os
import secrets
import shutil
import tempfile
import threading
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.actors import ROLE_SCOPES, Actor
from app.audit import SystemActor, audit
from app.db import get_sessionmaker
from app.demo_plan import (
    VISITS,
    DemoTrial,
    DemoVisit,
    SimulationStopped,
    Simulator,
    demo_rating,
    demo_trials,
    should_stop,
    true_rig_doc,
)
from app.models import Calibration, Patient, RecordingSession, Rig, Trial, User
from app.passwords import hash_password, verify_password
from app.schemas import TrialRatingUpdate
from app.services.trials import create_trial, rate_trial
from app.settings import Settings
from app.storage import Storage
from app.uploads import ParsedUpload, StagedFile
from core.tasks import Task

log = logging.getLogger(__name__)

DEMO_EMAIL = "demo@example.org"
DEMO_PATIENT = "DEMO-0001"
DEMO_RIG = "demo-rig"
#: The demo's other rigs: the same cameras placed as the feet and the legs need them
#: (core.simulation.tasks.rig_geometry); the hand tasks use ``DEMO_RIG``.
DEMO_TASK_RIGS: dict[Task, tuple[str, str]] = {
    Task.TOE_TAPPING: (
        "demo-rig-feet",
        "The demo's cameras placed for toe tapping: lower, 400 mm apart, 800 mm from the foot.",
    ),
    Task.LEG_AGILITY: (
        "demo-rig-legs",
        "The demo's cameras placed for leg agility: at knee height, 700 mm apart, 1 m away.",
    ),
}
CREDENTIALS_FILE = "demo-credentials.txt"
_threads: list[threading.Thread] = []


def _password(settings: Settings) -> tuple[str, bool]:
    """The demo password from the credentials file, or a new one (and whether it is new)."""
    path = Path(settings.data_dir) / CREDENTIALS_FILE
    if path.is_file():
        for line in path.read_text(encoding="utf-8").splitlines():
            if line.startswith("password:"):
                return line.split(":", 1)[1].strip(), False
    password = secrets.token_urlsafe(12)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.write(f"email: {DEMO_EMAIL}\npassword: {password}\n")
    return password, True


def _visit_tag(i: int) -> str:
    """The start of a demo session's notes; it identifies the visit at the next start."""
    return f"Demo visit {i + 1} of {len(VISITS)}."


def _visit_time(now: datetime, visit: DemoVisit, medication_state: str) -> datetime:
    day = (now - timedelta(days=round(30.44 * visit.months_ago))).replace(
        hour=9, minute=0, second=0, microsecond=0
    )
    return day if medication_state == "off" else day + timedelta(hours=2)


def _seed_rows(db: Session, settings: Settings, now: datetime) -> dict[str, Any]:
    password, _new = _password(settings)
    user = db.scalars(select(User).where(User.email == DEMO_EMAIL)).first()
    if user is None:
        user = User(
            email=DEMO_EMAIL,
            password_hash=hash_password(password),
            role="clinician",
            display_name="Demo Clinician",
        )
        db.add(user)
        db.flush()
        audit(db, SystemActor("demo"), "create", "user", user.id)
    elif not verify_password(user.password_hash, password):
        user.password_hash = hash_password(password)  # the file is the source of truth
    db.flush()
    rig = _calibrated_rig(
        db,
        DEMO_RIG,
        "Simulated two-camera rig of the demo (640 x 512 px).",
        Task.FINGER_TAPPING,
        user.id,
        now,
    )
    task_rigs = {
        task: _calibrated_rig(db, name, description, task, user.id, now).id
        for task, (name, description) in DEMO_TASK_RIGS.items()
    }
    patient = db.scalars(select(Patient).where(Patient.code == DEMO_PATIENT)).first()
    if patient is None:
        patient = Patient(code=DEMO_PATIENT, birth_year=1958, sex="male", notes="Demo patient.")
        db.add(patient)
        db.flush()
    sessions: dict[tuple[int, str], int] = {}
    existing = {
        (s.recorded_at, s.medication_state): s
        for s in db.scalars(
            select(RecordingSession).where(RecordingSession.patient_id == patient.id)
        )
    }
    for i, visit in enumerate(VISITS):
        for med in ("off", "on"):
            # Sessions are matched by their month: a restart days later finds them again.
            found = next(
                (
                    s
                    for (when, state), s in existing.items()
                    if state == med and s.notes and s.notes.startswith(_visit_tag(i))
                ),
                None,
            )
            if found is None:
                found = RecordingSession(
                    patient_id=patient.id,
                    rig_id=rig.id,
                    recorded_at=_visit_time(now, visit, med),
                    clinician_user_id=user.id,
                    medication_state=med,
                    dbs_state="none",
                    time_since_levodopa_min=120 if med == "on" else 12 * 60,
                    more_affected_side="right",
                    dominant_hand="right",
                    notes=f"{_visit_tag(i)} {visit.note}"
                    + (
                        " Two hours after 200 mg levodopa."
                        if med == "on"
                        else " 12 h off medication."
                    ),
                )
                db.add(found)
                db.flush()
            sessions[(i, med)] = found.id
    db.commit()
    return {"user_id": user.id, "password": password, "sessions": sessions, "rigs": task_rigs}


def _calibrated_rig(
    db: Session, name: str, description: str, task: Task, user_id: int, now: datetime
) -> Rig:
    """The demo rig ``name``, with a ready calibration: the simulator's true rig placed for
    ``task``."""
    rig = db.scalars(select(Rig).where(Rig.name == name)).first()
    if rig is None:
        rig = Rig(name=name, description=description)
        db.add(rig)
        db.flush()
    if not any(c.status == "ready" for c in rig.calibrations):
        doc = true_rig_doc(task)
        db.add(
            Calibration(
                rig_id=rig.id,
                version=1 + max((c.version for c in rig.calibrations), default=0),
                valid_from=now - timedelta(days=3 * 365),
                rig_json=doc,
                rms_px=doc["quality"]["rms_px"],
                quality=doc["quality"],
                source="rig_file",
                status="ready",
                created_by_user_id=user_id,
            )
        )
        db.flush()
    return rig


def _missing_trials(
    db: Session, sessions: dict[tuple[int, str], int]
) -> list[tuple[DemoTrial, int]]:
    out = []
    for trial in demo_trials():
        session_id = sessions[(trial.visit, trial.medication_state)]
        exists = db.scalars(
            select(Trial.id).where(
                Trial.session_id == session_id,
                Trial.hand == trial.hand,
                Trial.task == trial.task.value,
                Trial.deleted_at.is_(None),
            )
        ).first()
        if exists is None:
            out.append((trial, session_id))
    return out


def _upload_trial(
    settings: Settings,
    user_id: int,
    session_id: int,
    hand: str,
    left: Path,
    right: Path,
    rating: int | None = None,
    *,
    task: Task = Task.FINGER_TAPPING,
    rig_id: int | None = None,
) -> int:
    """Store the two videos through the service's trial use case; returns the job id.

    ``rig_id``: the rig that recorded them, when not the session's."""
    storage = Storage.from_settings(settings)
    fields = {"hand": hand, "task": task.value}
    if rig_id is not None:
        fields["rig_id"] = str(rig_id)
    upload = ParsedUpload(storage, fields=fields)
    try:
        for name, path in (("left_video", left), ("right_video", right)):
            incoming = storage.receive("videos", path.suffix, max_bytes=settings.max_upload_bytes)
            upload.files[name] = StagedFile(name, path.name, incoming)
            with open(path, "rb") as fh:
                while chunk := fh.read(1 << 20):
                    incoming.write(chunk)
            incoming.flush()
        actor = Actor(
            type="user",
            id=user_id,
            name=DEMO_EMAIL,
            scopes=ROLE_SCOPES["clinician"],
            role="clinician",
        )
        with get_sessionmaker(settings)() as db:
            out = create_trial(db, actor, session_id, upload)
            if rating is not None:
                rate_trial(db, actor, out.trial.id, TrialRatingUpdate(clinician_rating=rating))
        return out.job_id
    finally:
        upload.close()


def generate_recordings(
    settings: Settings,
    user_id: int,
    todo: list[tuple[DemoTrial, int]],
    *,
    clip_s: float | None = None,
    stop_event: threading.Event | None = None,
    start: threading.Event | None = None,
    rigs: dict[Task, int] | None = None,
) -> int:
    """Simulate and upload the given demo trials one by one; returns how many were queued.

    ``rigs``: the rig of each task not recorded by the session's (``DEMO_TASK_RIGS``).
    With ``start``, waits until it is set (or the server has ended) before the first.
    The recordings are simulated in a child process (:class:`Simulator`).
    """
    rigs = rigs or {}
    while start is not None and not start.wait(0.2):
        if should_stop(stop_event):
            return 0
    work = Path(settings.data_dir) / "tmp"
    work.mkdir(parents=True, exist_ok=True)
    done = 0
    simulator = Simulator(stop_event)
    try:
        for trial, session_id in todo:
            if should_stop(stop_event):
                break
            queued = _prepare_one(
                settings, user_id, trial, session_id, work, simulator, clip_s, rigs
            )
            if queued is None:
                break
            done += queued
    finally:
        simulator.close()
    return done


def _prepare_one(
    settings: Settings,
    user_id: int,
    trial: DemoTrial,
    session_id: int,
    work: Path,
    simulator: Simulator,
    clip_s: float | None,
    rigs: dict[Task, int],
) -> int | None:
    """Simulate and upload one demo trial: 1 when queued, 0 when it failed (logged), None
    when asked to stop."""
    tmp = Path(tempfile.mkdtemp(prefix="demo-", dir=work))
    try:
        left, right = simulator.simulate(trial, tmp, clip_s)
        job_id = _upload_trial(
            settings,
            user_id,
            session_id,
            trial.hand,
            left,
            right,
            demo_rating(trial),
            task=trial.task,
            rig_id=rigs.get(trial.task),
        )
        log.info(
            "demo: queued visit %d, %s, %s side, medication %s (job %d)",
            trial.visit,
            trial.task.value,
            trial.hand,
            trial.medication_state,
            job_id,
        )
        return 1
    except SimulationStopped:
        log.info("demo: stopped; the remaining recordings are made at the next start")
        return None
    except Exception:
        log.exception("demo: could not prepare a simulated recording; skipping it")
        return 0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def seed_demo(
    settings: Settings,
    *,
    background: bool = True,
    clip_s: float | None = None,
    max_trials: int | None = None,
    now: datetime | None = None,
    start: threading.Event | None = None,
    url: str = "http://127.0.0.1:8000/",
) -> str:
    """Create the demo account, rig, patient and sessions; queue simulated trials.

    Parameters
    ----------
    settings : app.settings.Settings
        The database must be migrated.
    background : bool
        Simulate the recordings in a background thread (default) so the server
        starts at once; it ends with the main thread. ``False`` simulates them
        before returning (tests).
    clip_s : float, optional
        Length of each simulated recording (s); default each trial's own (``clip_s``:
        6 s, or what its ten cycles need).
    max_trials : int, optional
        Simulate at most this many of the missing trials (tests).
    start : threading.Event, optional
        With ``background``: the recordings are simulated once it is set (the
        server sets it when it answers, so that start-up does not share the
        processor with the simulation).
    url : str
        The address the printed lines tell the user to open (``bradyscope serve``'s).
    now : datetime, optional
        "Today" of the demo (UTC); default the current time.

    Returns
    -------
    str
        Lines to print: where to log in and with which credentials.
    """
    now = now or datetime.now(UTC)
    with get_sessionmaker(settings)() as db:
        seeded = _seed_rows(db, settings, now)
        todo = _missing_trials(db, seeded["sessions"])
    if max_trials is not None:
        todo = todo[:max_trials]
    if todo:
        if background:
            thread = threading.Thread(
                target=generate_recordings,
                args=(settings, seeded["user_id"], todo),
                kwargs={"clip_s": clip_s, "start": start, "rigs": seeded["rigs"]},
                name="bradyscope-demo-recordings",
                daemon=False,
            )
            thread.start()
            _threads.append(thread)
        else:
            generate_recordings(
                settings, seeded["user_id"], todo, clip_s=clip_s, rigs=seeded["rigs"]
            )
    n_total = len(demo_trials())
    lines = [
        f"Open {url} and log in with:",
        f"  e-mail:   {DEMO_EMAIL}",
        f"  password: {seeded['password']}",
        f"  (also in {Path(settings.data_dir) / CREDENTIALS_FILE})",
        f"Demo patient {DEMO_PATIENT}: {len(VISITS)} visits over two years, medication off and on;"
        " finger tapping at each, the other tasks at the last.",
    ]
    if todo:
        lines.append(
            f"Simulating {len(todo)} of {n_total} recordings"
            + (" in the background" if background else "")
            + "; results appear on the patient page as the worker measures them"
            " (the first within a minute or two)."
        )
    else:
        lines.append(f"All {n_total} demo recordings are in place.")
    return "\n".join(lines)

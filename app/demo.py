"""Demo data for ``bradyscope serve --demo``: a clinician, a rig, a patient followed for two years.

:func:`seed_demo` creates (once; it is idempotent):

- a clinician account ``demo@example.org`` whose random password is kept in
  ``<data_dir>/demo-credentials.txt`` (mode 600) and printed at every start;
- a rig ``demo-rig`` calibrated with the simulator's true rig (640 x 512 px);
- a patient ``DEMO-0001`` with visits over two years, each with a session OFF
  medication and one ON medication: tapping gets smaller, slower, decrements
  more and hesitates more as the disease progresses, the right hand more than
  the left, and medication ON improves it;
- one trial per hand and session, made from a real simulated stereo recording
  (640 x 512 px, 60 fps, 6 s, MPEG-4) uploaded through the service's own trial
  use case, so the worker measures it like any upload.

The recordings are simulated in a background thread, most useful first (the
right hand OFF medication at every visit, so that the trend appears early),
so the pages fill while the server runs. Restarting only adds what is missing.
"""

from __future__ import annotations

import logging
import os
import secrets
import shutil
import tempfile
import threading
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.actors import ROLE_SCOPES, Actor
from app.db import get_sessionmaker
from app.models import Calibration, Patient, RecordingSession, Rig, Trial, User
from app.passwords import hash_password, verify_password
from app.schemas import TrialRatingUpdate
from app.services.trials import create_trial, rate_trial
from app.settings import Settings
from app.storage import Storage
from app.uploads import ParsedUpload, StagedFile
from core.camera import ImageSize, rig_to_dict
from core.simulation.kinematics import TappingScenario
from core.simulation.rig import default_rig
from core.simulation.session import ImagingScenario, simulate_session

log = logging.getLogger(__name__)

DEMO_EMAIL = "demo@example.org"
DEMO_PATIENT = "DEMO-0001"
DEMO_RIG = "demo-rig"
CREDENTIALS_FILE = "demo-credentials.txt"
IMAGE_SIZE = (640, 512)  # px, (width, height)
# Small recordings, so that the whole demo is measured within a couple of minutes: 6 s
# (10 or more taps at every planned frequency), 60 fps, MPEG-4 Part 2 (about 1 MB a video).
FPS = 60.0  # Hz
CLIP_S = 6.0  # s
CODEC = "mp4v"

_threads: list[threading.Thread] = []


@dataclass(frozen=True)
class DemoTrial:
    """One simulated trial of the demo: who taps how (all lengths in mm, rates in Hz)."""

    visit: int
    medication_state: str
    hand: str
    amplitude_mm: float
    frequency_hz: float
    decrement_mm_per_tap: float
    hesitations: tuple[int, ...] = ()
    halts: tuple[tuple[int, float], ...] = ()
    seed: int = 0


@dataclass(frozen=True)
class DemoVisit:
    """A clinic visit: months before today, the clinician's 3.4 ratings of the right hand
    (off, on; the left hand, less affected, one lower), notes."""

    months_ago: int
    rating_off: int
    rating_on: int
    note: str


VISITS: tuple[DemoVisit, ...] = (
    DemoVisit(24, 1, 0, "First instrumented assessment; symptoms mainly right-sided."),
    DemoVisit(12, 2, 1, "Slower tapping on the right; levodopa dose increased."),
    DemoVisit(1, 3, 1, "Clear decrement and hesitations off medication."),
)


def demo_trials() -> list[DemoTrial]:
    """The demo's trials, in the order they are simulated (most informative first)."""
    trials = []
    # (amplitude, frequency, decrement, hesitations, halts) OFF medication per visit.
    right_off = [
        (48.0, 3.0, -0.3, (), ()),
        (40.0, 2.6, -0.7, (7,), ()),
        (32.0, 2.2, -1.1, (3, 6), ((5, 0.5),)),  # pauses that fit in a 6-s clip
    ]
    left_off = [
        (52.0, 3.2, -0.1, (), ()),
        (48.0, 3.0, -0.3, (), ()),
        (43.0, 2.7, -0.5, (8,), ()),
    ]
    seed = 100
    for visit in range(len(VISITS)):
        for hand, table in (("right", right_off), ("left", left_off)):
            amp, freq, dec, hes, halts = table[visit]
            for med in ("off", "on"):
                hes_m: tuple[int, ...]
                halts_m: tuple[tuple[int, float], ...]
                if med == "on":  # levodopa: bigger, faster, less decrement, fewer pauses
                    amp_m, freq_m, dec_m = amp + 7.0, freq + 0.4, dec * 0.5
                    hes_m, halts_m = (hes[:1] if len(hes) > 1 else ()), ()
                else:
                    amp_m, freq_m, dec_m, hes_m, halts_m = amp, freq, dec, hes, halts
                seed += 1
                trials.append(
                    DemoTrial(visit, med, hand, amp_m, freq_m, dec_m, hes_m, halts_m, seed)
                )
    priority = {("right", "off"): 0, ("right", "on"): 1, ("left", "off"): 2, ("left", "on"): 3}
    trials.sort(key=lambda t: (priority[(t.hand, t.medication_state)], t.visit))
    return trials


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


def _demo_rig_doc() -> dict[str, Any]:
    doc = rig_to_dict(default_rig(image_size=ImageSize(*IMAGE_SIZE)))
    # The demo videos are rendered with exactly this rig: its error is zero by construction.
    doc["quality"] = {"rms_px": 0.0, "source": "the simulator's true rig (exact; demo only)"}
    return doc


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
    elif not verify_password(user.password_hash, password):
        user.password_hash = hash_password(password)  # the file is the source of truth
    rig = db.scalars(select(Rig).where(Rig.name == DEMO_RIG)).first()
    if rig is None:
        rig = Rig(name=DEMO_RIG, description="Simulated two-camera rig of the demo (640 x 512 px).")
        db.add(rig)
    db.flush()
    if not any(c.status == "ready" for c in rig.calibrations):
        doc = _demo_rig_doc()
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
                created_by_user_id=user.id,
            )
        )
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
    return {"user_id": user.id, "password": password, "sessions": sessions}


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
                Trial.deleted_at.is_(None),
            )
        ).first()
        if exists is None:
            out.append((trial, session_id))
    return out


class _Stopped(Exception):
    """The server is shutting down: stop simulating."""


def _should_stop(stop_event: threading.Event | None) -> bool:
    # The generator thread is not a daemon (a daemon killed inside the video
    # encoder aborts the process); it stops by itself once the main thread
    # (the server) has ended, or when asked to.
    return (
        stop_event is not None and stop_event.is_set()
    ) or not threading.main_thread().is_alive()


def pauses_that_fit(
    trial: DemoTrial, clip_s: float
) -> tuple[tuple[int, ...], tuple[tuple[int, float], ...]]:
    """The trial's hesitations and halts that leave at least two taps after them in ``clip_s``.

    The taps fit in the clip less its still lead-in and tail (about 0.8 s) and
    the pauses before them; a 10 % margin covers the simulated rhythm's jitter.
    """
    hesitation_s = TappingScenario.hesitation_s
    period_s = 1.0 / trial.frequency_hz
    pauses = sorted(
        [(k, hesitation_s, "hesitation") for k in trial.hesitations]
        + [(k, d, "halt") for k, d in trial.halts]
    )
    lost_s = 0.0
    hesitations: list[int] = []
    halts: list[tuple[int, float]] = []
    for k, duration_s, kind in pauses:
        taps_that_fit = 0.9 * (clip_s - 0.8 - lost_s - duration_s) / period_s
        if k >= taps_that_fit - 2:
            continue
        lost_s += duration_s
        if kind == "hesitation":
            hesitations.append(k)
        else:
            halts.append((k, duration_s))
    return tuple(hesitations), tuple(halts)


def _simulate(
    trial: DemoTrial, out_dir: Path, *, clip_s: float, stop_event: threading.Event | None = None
) -> tuple[Path, Path]:
    hesitations, halts = pauses_that_fit(trial, clip_s)

    def progress(stage: str, done: int, total: int) -> None:
        if _should_stop(stop_event):
            raise _Stopped

    sim = simulate_session(
        out_dir,
        seed=trial.seed,
        progress=progress,
        tapping=TappingScenario(
            duration_s=clip_s,
            fps=FPS,
            amplitude_mm=trial.amplitude_mm,
            frequency_hz=trial.frequency_hz,
            decrement_mm_per_tap=trial.decrement_mm_per_tap,
            amplitude_jitter=0.04,
            hesitations=hesitations,
            halts=halts,
            hand=trial.hand,
        ),
        imaging=ImagingScenario(image_size=ImageSize(*IMAGE_SIZE), codec=CODEC),
    )
    return sim.left_video, sim.right_video


def demo_rating(trial: DemoTrial) -> int:
    """The clinician's 3.4 rating of a demo trial: the visit's for the right hand, one lower left."""
    visit = VISITS[trial.visit]
    rating = visit.rating_off if trial.medication_state == "off" else visit.rating_on
    return rating if trial.hand == "right" else max(0, rating - 1)


def _upload_trial(
    settings: Settings,
    user_id: int,
    session_id: int,
    hand: str,
    left: Path,
    right: Path,
    rating: int | None = None,
) -> int:
    """Store the two videos through the service's trial use case; returns the job id."""
    storage = Storage.from_settings(settings)
    upload = ParsedUpload(storage, fields={"hand": hand})
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
    clip_s: float = CLIP_S,
    stop_event: threading.Event | None = None,
    start: threading.Event | None = None,
) -> int:
    """Simulate and upload the given demo trials one by one; returns how many were queued.

    With ``start``, waits until it is set (or the server has ended) before the first.
    """
    while start is not None and not start.wait(0.2):
        if _should_stop(stop_event):
            return 0
    work = Path(settings.data_dir) / "tmp"
    work.mkdir(parents=True, exist_ok=True)
    done = 0
    for trial, session_id in todo:
        if _should_stop(stop_event):
            break
        tmp = Path(tempfile.mkdtemp(prefix="demo-", dir=work))
        try:
            left, right = _simulate(trial, tmp, clip_s=clip_s, stop_event=stop_event)
            job_id = _upload_trial(
                settings, user_id, session_id, trial.hand, left, right, demo_rating(trial)
            )
            log.info(
                "demo: queued visit %d, %s hand, medication %s (job %d)",
                trial.visit,
                trial.hand,
                trial.medication_state,
                job_id,
            )
            done += 1
        except _Stopped:
            log.info("demo: stopped; the remaining recordings are made at the next start")
            break
        except Exception:
            log.exception("demo: could not prepare a simulated recording; skipping it")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return done


def seed_demo(
    settings: Settings,
    *,
    background: bool = True,
    clip_s: float = CLIP_S,
    max_trials: int | None = None,
    now: datetime | None = None,
    start: threading.Event | None = None,
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
    clip_s : float
        Length of each simulated recording (s).
    max_trials : int, optional
        Simulate at most this many of the missing trials (tests).
    start : threading.Event, optional
        With ``background``: the recordings are simulated once it is set (the
        server sets it when it answers, so that start-up does not share the
        processor with the simulation).
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
                kwargs={"clip_s": clip_s, "start": start},
                name="bradyscope-demo-recordings",
                daemon=False,
            )
            thread.start()
            _threads.append(thread)
        else:
            generate_recordings(settings, seeded["user_id"], todo, clip_s=clip_s)
    n_total = len(demo_trials())
    lines = [
        "Open http://127.0.0.1:8000/ (or the --host/--port you gave) and log in with:",
        f"  e-mail:   {DEMO_EMAIL}",
        f"  password: {seeded['password']}",
        f"  (also in {Path(settings.data_dir) / CREDENTIALS_FILE})",
        f"Demo patient {DEMO_PATIENT}: {len(VISITS)} visits over two years, medication off and on.",
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

"""The demo's simulated patient: what they do at each visit, and the recordings made of it.

:func:`demo_trials` plans the trials (finger tapping of both hands, OFF and ON
medication, at three visits over two years; the other items of the examination at
the last); :func:`simulate_trial` renders one as a stereo recording with the
simulator's true rig placed for its task (:func:`true_rig_doc`, the demo rigs'
calibration); :func:`demo_rating` is the clinician's rating of it; :class:`Simulator`
runs the simulations in one child process. :mod:`app.demo` seeds the rows and uploads
the recordings.
"""

from __future__ import annotations

import math
import multiprocessing
import threading
import traceback
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, cast

from core.camera import ImageSize, rig_to_dict
from core.protocols import marker_diameter_mm
from core.simulation.kinematics import TappingScenario
from core.simulation.rig import default_rig
from core.simulation.session import ImagingScenario, simulate_session
from core.simulation.tasks import TaskScenario, rig_geometry
from core.tasks import Task

IMAGE_SIZE = (640, 512)  # px, (width, height)
# Small recordings, so that the whole demo is measured within a couple of minutes: 6 s or
# the few seconds more that a slow trial's ten cycles need (clip_for), 60 fps, MPEG-4
# Part 2 (about 1 MB a video).
FPS = 60.0  # Hz
CLIP_S = 6.0  # s, the shortest
CODEC = "mp4v"
#: Cycles a demo recording holds at least: the ten each MDS-UPDRS item asks for.
CYCLES = 10
#: The still lead-in and tail of a simulated recording, together (s).
STILL_S = 0.8


def clip_for(frequency_hz: float, pauses_s: float) -> float:
    """The shortest recording (s, in half seconds, at least ``CLIP_S``) that holds ``CYCLES``
    cycles at ``frequency_hz`` and ``pauses_s`` of hesitations and halts, with the margin of
    :func:`pauses_that_fit` (10 %) for the rhythm's jitter."""
    need = STILL_S + pauses_s + CYCLES / (0.9 * frequency_hz)
    return max(CLIP_S, math.ceil(2.0 * need) / 2.0)


@dataclass(frozen=True)
class DemoTrial:
    """One simulated trial of the demo: who moves how.

    ``amplitude`` (the first cycle's) and ``decrement_per_cycle`` are in the task's unit
    (mm; degrees for pronation–supination and leg agility), ``frequency_hz`` in Hz;
    ``hand`` is the side examined (the foot or leg for toe tapping and leg agility);
    ``clip_s`` the recording's length (s, :func:`clip_for`).
    """

    visit: int
    medication_state: str
    hand: str
    amplitude: float
    frequency_hz: float
    decrement_per_cycle: float
    hesitations: tuple[int, ...] = ()
    halts: tuple[tuple[int, float], ...] = ()
    seed: int = 0
    task: Task = Task.FINGER_TAPPING
    clip_s: float = CLIP_S

    @property
    def pauses_s(self) -> float:
        """The planned hesitations and halts, together (s)."""
        return len(self.hesitations) * TappingScenario.hesitation_s + sum(d for _, d in self.halts)


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


#: The other items of the examination at the last visit, OFF medication, the right side:
#: (task, first amplitude in its unit, Hz, change per cycle, hesitations before cycles).
#: Slow, small and shrinking, as the finger tapping of that visit (rated 3).
OTHER_TASKS: tuple[tuple[Task, float, float, float, tuple[int, ...]], ...] = (
    (Task.HAND_MOVEMENTS, 36.0, 1.5, -1.5, (4,)),
    (Task.PRONATION_SUPINATION, 130.0, 1.4, -4.0, ()),
    (Task.TOE_TAPPING, 32.0, 2.0, -1.0, (5,)),
    (Task.LEG_AGILITY, 24.0, 1.5, -0.8, ()),
)


def demo_trials() -> list[DemoTrial]:
    """The demo's trials, in the order they are simulated (most informative first): finger
    tapping at every visit, then the other tasks at the last."""
    trials = []
    # (amplitude, frequency, decrement, hesitations, halts) OFF medication per visit.
    right_off = [
        (48.0, 3.0, -0.3, (), ()),
        (40.0, 2.6, -0.7, (7,), ()),
        (32.0, 2.2, -1.1, (3, 6), ((5, 0.5),)),
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
                trial = DemoTrial(visit, med, hand, amp_m, freq_m, dec_m, hes_m, halts_m, seed)
                trials.append(replace(trial, clip_s=clip_for(freq_m, trial.pauses_s)))
    priority = {("right", "off"): 0, ("right", "on"): 1, ("left", "off"): 2, ("left", "on"): 3}
    trials.sort(key=lambda t: (priority[(t.hand, t.medication_state)], t.visit))
    for task, amp, freq, dec, hes in OTHER_TASKS:
        seed += 1
        trial = DemoTrial(len(VISITS) - 1, "off", "right", amp, freq, dec, hes, (), seed, task)
        trials.append(replace(trial, clip_s=clip_for(freq, trial.pauses_s)))
    return trials


def true_rig_doc(task: Task = Task.FINGER_TAPPING) -> dict[str, Any]:
    """The rig file of the simulator's true rig placed for ``task`` (640 x 512 px): the demo
    rig's calibration, exact for the recordings :func:`simulate_trial` makes."""
    geometry = rig_geometry(task)._asdict()
    doc = rig_to_dict(default_rig(image_size=ImageSize(*IMAGE_SIZE), **geometry))
    # The demo videos are rendered with exactly this rig: its error is zero by construction.
    doc["quality"] = {"rms_px": 0.0, "source": "the simulator's true rig (exact; demo only)"}
    return doc


class SimulationStopped(Exception):
    """The server is shutting down: stop simulating."""


def should_stop(stop_event: threading.Event | None) -> bool:
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
    hesitation_s = TappingScenario.hesitation_s  # TaskScenario's too
    period_s = 1.0 / trial.frequency_hz
    pauses = sorted(
        [(k, hesitation_s, "hesitation") for k in trial.hesitations]
        + [(k, d, "halt") for k, d in trial.halts]
    )
    lost_s = 0.0
    hesitations: list[int] = []
    halts: list[tuple[int, float]] = []
    for k, duration_s, kind in pauses:
        taps_that_fit = 0.9 * (clip_s - STILL_S - lost_s - duration_s) / period_s
        if k >= taps_that_fit - 2:
            continue
        lost_s += duration_s
        if kind == "hesitation":
            hesitations.append(k)
        else:
            halts.append((k, duration_s))
    return tuple(hesitations), tuple(halts)


def simulate_trial(
    trial: DemoTrial,
    out_dir: Path,
    *,
    clip_s: float | None = None,
    stop_event: threading.Event | None = None,
) -> tuple[Path, Path]:
    """Render the trial's two videos into ``out_dir``: ``trial.clip_s`` long, or ``clip_s``
    (tests: shorter, with the pauses that still fit)."""
    clip_s = trial.clip_s if clip_s is None else clip_s
    hesitations, halts = pauses_that_fit(trial, clip_s)

    def progress(stage: str, done: int, total: int) -> None:
        if should_stop(stop_event):
            raise SimulationStopped

    imaging = ImagingScenario(
        image_size=ImageSize(*IMAGE_SIZE),
        codec=CODEC,
        marker_diameter_mm=marker_diameter_mm(trial.task),
    )
    scenario: dict[str, Any]
    if trial.task is Task.FINGER_TAPPING:
        scenario = {
            "tapping": TappingScenario(
                duration_s=clip_s,
                fps=FPS,
                amplitude_mm=trial.amplitude,
                frequency_hz=trial.frequency_hz,
                decrement_mm_per_tap=trial.decrement_per_cycle,
                amplitude_jitter=0.04,
                hesitations=hesitations,
                halts=halts,
                hand=trial.hand,
            )
        }
    else:  # the rig placed for the task (rig_geometry), as the demo's rig of the task
        scenario = {
            "task": TaskScenario(
                task=trial.task,
                duration_s=clip_s,
                fps=FPS,
                amplitude=trial.amplitude,
                frequency_hz=trial.frequency_hz,
                decrement_per_cycle=trial.decrement_per_cycle,
                amplitude_jitter=0.04,
                hesitations=hesitations,
                halts=halts,
                side=trial.hand,
            )
        }
    sim = simulate_session(out_dir, seed=trial.seed, progress=progress, imaging=imaging, **scenario)
    return sim.left_video, sim.right_video


def demo_rating(trial: DemoTrial) -> int:
    """The clinician's rating of a demo trial: the visit's for the right side, one lower left
    (the other tasks are rated as the finger tapping of their visit)."""
    visit = VISITS[trial.visit]
    rating = visit.rating_off if trial.medication_state == "off" else visit.rating_on
    return rating if trial.hand == "right" else max(0, rating - 1)


class Simulator:
    """Simulates demo recordings in one child process, started at the first.

    The simulation is mostly Python (rendering each frame): in the server's process it
    would hold the interpreter's lock against the embedded workers measuring the
    recordings already made, and both would crawl (an analysis took ~3x as long while the
    demo was being simulated: ``bench/bench_startup.py``). ``stop_event`` (or the end of
    the server) stops it at once: the child is terminated. A child that dies (killed, out
    of memory) fails the recording it was making with an error that says so, and the next
    recording starts a new one: with a process pool, the lost task's result would have been
    waited for forever.
    """

    def __init__(self, stop_event: threading.Event | None) -> None:
        self.stop_event = stop_event
        self._proc: Any = None
        self._conn: Any = None

    def simulate(self, trial: DemoTrial, out_dir: Path, clip_s: float | None) -> tuple[Path, Path]:
        if self._proc is not None and not self._proc.is_alive():
            self.close()  # it died between two recordings
        if self._proc is None:
            ctx = multiprocessing.get_context("spawn")
            self._conn, child_conn = ctx.Pipe()
            self._proc = ctx.Process(
                target=_simulate_in_child, args=(child_conn,), name="demo-simulator", daemon=True
            )
            self._proc.start()
            child_conn.close()  # the child's end: its death then ends the pipe here
        self._conn.send((trial, out_dir, clip_s))
        while True:
            if self._conn.poll(0.2):
                try:
                    kind, value = self._conn.recv()
                except (EOFError, OSError):
                    kind, value = "died", None
                if kind == "done":
                    return cast(tuple[Path, Path], value)
                if kind == "error":
                    raise RuntimeError(f"the simulation failed in its process:\n{value}")
            elif self._proc.is_alive():
                if should_stop(self.stop_event):
                    self.close()  # before the caller removes the files the child writes
                    raise SimulationStopped
                continue
            self._proc.join(5.0)
            code = self._proc.exitcode
            self.close()
            raise RuntimeError(
                f"the simulation process ended (exit code {code}) before the recording was "
                "made; the next recording starts a new one"
            )

    def close(self) -> None:
        if self._proc is not None:
            self._proc.terminate()
            self._proc.join()
            self._conn.close()
            self._proc = self._conn = None


def _simulate_in_child(conn: Any) -> None:
    """The simulation child of :class:`Simulator`: each ``(trial, out_dir, clip_s)`` it is
    sent, simulated, and ``("done", (left, right))`` or ``("error", what went wrong)``
    sent back, until the server's end of the pipe closes."""
    while True:
        try:
            trial, out_dir, clip_s = conn.recv()
        except EOFError:
            return
        try:
            result = simulate_trial(trial, out_dir, clip_s=clip_s)
        except Exception:  # raised in the server by Simulator.simulate, and logged
            conn.send(("error", traceback.format_exc()))
        else:
            conn.send(("done", result))

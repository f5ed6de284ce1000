"""The other tasks through the whole pipeline, on realistic simulated recordings.

Realistic imaging as the finger-tapping tests' "messy" recording: 1280x1024,
MPEG-4 compression, 6-ms motion blur, sensor noise and static reflections in
the room. Per task (issue 16): 3D marker RMS <= 0.05 mm, cycle count exact,
amplitude within 1 % (0.5 degree), frequency within 1 %, decrement slope within
10 %, the inserted hesitation and halt at their cycles, and for
pronation–supination the angle within 1 degree RMS through the movement.
Recordings are short (4.5-7 s) with brisk rhythms, to keep the test time modest.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core.camera import ImageSize, read_rig
from core.cycles import task_key
from core.pipeline import Analysis, analyze_recording
from core.simulation.session import ImagingScenario, SimulatedSession, simulate_session
from core.simulation.tasks import TaskScenario
from core.tasks import Task

REALISTIC = ImagingScenario(
    image_size=ImageSize(1280, 1024),
    codec="mp4v",
    exposure_s=0.006,
    noise_sigma=3.0,
    distractors_static=2,
)
SCENARIOS = {
    Task.HAND_MOVEMENTS: TaskScenario(
        task=Task.HAND_MOVEMENTS,
        duration_s=6.0,
        frequency_hz=2.0,
        decrement_per_cycle=-1.0,
        hesitations=(3,),
        halts=((6, 0.5),),
    ),
    Task.PRONATION_SUPINATION: TaskScenario(
        task=Task.PRONATION_SUPINATION,
        duration_s=7.0,
        frequency_hz=1.6,
        decrement_per_cycle=-3.0,
        hesitations=(3,),
        halts=((6, 0.5),),
        side="left",
    ),
    Task.TOE_TAPPING: TaskScenario(
        task=Task.TOE_TAPPING,
        duration_s=4.5,
        frequency_hz=3.0,
        decrement_per_cycle=-1.0,
        hesitations=(3,),
        halts=((6, 0.5),),
    ),
    Task.LEG_AGILITY: TaskScenario(
        task=Task.LEG_AGILITY,
        duration_s=6.0,
        frequency_hz=2.0,
        decrement_per_cycle=-1.0,
        hesitations=(3,),
        halts=((6, 0.5),),
        side="left",
    ),
}


@pytest.fixture(scope="module", params=list(SCENARIOS), ids=lambda t: t.value)
def measured(
    request: pytest.FixtureRequest, run_once: Any
) -> tuple[Task, SimulatedSession, Analysis]:
    """The task's recording and its analysis, made once per test run in whichever xdist
    worker asks first (``run_once``)."""
    task: Task = request.param
    return task, *run_once(f"task-pipeline-{task.value}", lambda out: _measure(task, out))


def _measure(task: Task, out: Path) -> tuple[SimulatedSession, Analysis]:
    scenario = SCENARIOS[task]
    session = simulate_session(
        out,
        seed=17,
        task=scenario,
        # Leg agility's protocol markers (10 mm at 1 m); toe tapping's 5-mm ones are
        # smaller than its protocol's 10 mm (docs/protocols.md), a harder case.
        imaging=replace(REALISTIC, marker_diameter_mm=10.0)
        if task is Task.LEG_AGILITY
        else REALISTIC,
    )
    analysis = analyze_recording(
        read_rig(session.rig_path),
        session.left_video,
        session.right_video,
        task=task,
        side=scenario.side,
    )
    return session, analysis


def test_markers_are_labelled_and_measured_to_0_05_mm(
    measured: tuple[Task, SimulatedSession, Analysis],
) -> None:
    _task, session, analysis = measured
    assert analysis.marker_names == tuple(session.truth["marker_names"])
    truth = np.asarray(session.truth["positions_mm"])
    meas = analysis.status == "measured"
    assert np.mean(meas) > 0.98
    err = np.linalg.norm(analysis.positions_mm - truth, axis=2)
    assert np.sqrt(np.mean(err[meas] ** 2)) <= 0.05  # mm RMS (acceptance)
    assert np.nanmax(err) < 0.5  # mm: no marker ever takes another's label


def test_cycles_amplitude_rhythm_decrement_and_pauses(
    measured: tuple[Task, SimulatedSession, Analysis],
) -> None:
    task, session, analysis = measured
    truth = session.truth
    doc = analysis.result_document()
    assert doc["task"] == task.value
    assert doc["markers"] == truth["marker_names"]
    m = doc["metrics"]
    assert m["amplitude_unit"] == task.amplitude_unit
    assert m["cycle_count"] == truth["cycle_count"] == len(doc["cycles"])  # exact
    true_amp = np.array([c["amplitude"] for c in truth["cycles"]])
    amp = np.array([c[task_key("amplitude_mm", task)] for c in doc["cycles"]])
    if task.amplitude_unit == "deg":
        assert np.max(np.abs(amp - true_amp)) <= 0.5  # degrees
    else:
        assert np.max(np.abs(amp / true_amp - 1)) <= 0.01  # 1 %
    assert abs(m["frequency_hz"] / truth["frequency_hz"] - 1) <= 0.01  # 1 %
    assert abs(m["amplitude_decrement_per_cycle"] / truth["decrement_per_cycle"] - 1) <= 0.10
    events = sorted((e["kind"], e["cycle_index"]) for e in doc["events"] if e["kind"] != "gap")
    assert events == [("halt", 6), ("hesitation", 3)]
    assert doc["metrics_first_10"]["cycle_count"] == min(10, truth["cycle_count"])


def test_the_supination_angle_within_1_degree(
    measured: tuple[Task, SimulatedSession, Analysis],
) -> None:
    task, session, analysis = measured
    if task is not Task.PRONATION_SUPINATION:
        pytest.skip("pronation-supination only")
    assert analysis.task_metrics is not None
    angle = analysis.task_metrics.signal.values
    true_angle = np.asarray(session.truth["signal"])
    ok = np.isfinite(angle)
    assert np.mean(ok) > 0.98
    err = (angle - true_angle)[ok]
    err -= np.median(err)  # both count from their own most pronated position
    assert np.sqrt(np.mean(err**2)) <= 1.0  # degrees RMS (acceptance)
    assert np.max(true_angle) >= 140.0  # through palm up


def test_a_deep_fist_hides_the_finger_marker_from_one_camera(tmp_path: Path) -> None:
    """A fist 8.5 mm deeper than the default turns the finger marker's mount away from the
    left camera at each closure (about 0.13 s): the simulator records it, the analysis
    measures nothing there (one camera is not a 3D point) and keeps the identities."""
    scenario = TaskScenario(
        task=Task.HAND_MOVEMENTS,
        duration_s=2.0,
        frequency_hz=2.0,
        closed_distance_mm=83.5,
        amplitude=40.0,
    )
    session = simulate_session(
        tmp_path, seed=3, task=scenario, imaging=ImagingScenario(image_size=ImageSize(640, 512))
    )
    hidden = session.truth["self_occlusions"]["left"]["finger"]
    assert len(hidden) >= 3  # the rest before the first cycle, then each closure
    assert session.truth["self_occlusions"]["right"]["finger"] == []
    assert session.truth["self_occlusions"]["left"]["wrist"] == []
    analysis = analyze_recording(
        read_rig(session.rig_path),
        session.left_video,
        session.right_video,
        task=Task.HAND_MOVEMENTS,
    )
    meas = analysis.status == "measured"
    for first, last in hidden:
        assert not np.any(meas[first : last + 1, 0])
    truth = np.asarray(session.truth["positions_mm"])
    err = np.linalg.norm(analysis.positions_mm - truth, axis=2)
    assert np.sqrt(np.mean(err[meas] ** 2)) <= 0.05  # mm (640x512, lossless)
    assert np.nanmax(err[meas]) < 0.3  # mm: the finger is never taken for the wrist

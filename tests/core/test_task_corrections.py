"""A clinician's corrections of hand movements, pronation–supination and toe tapping.

The corrected metrics are measured again by the analysis's own code
(:func:`core.cycles.task_signal`, the segmentation and statistics) and are
checked against the simulator's truth with the tolerances of the tasks'
acceptance (tests/core/test_task_metrics.py): cycle count exact, amplitude
within 1 % (0.5 degree), frequency within 1 %, decrement slope within 10 %,
pauses at the right cycle.
"""

from __future__ import annotations

import numpy as np
import pytest

# The scenarios of the tasks' acceptance: at least 10 cycles, a hesitation before cycle 3
# and a halt before cycle 6, the decrement of each task.
from test_task_metrics import NEW_TASKS, _truth

from core.corrections import Corrections, correct_metrics, revised_document, swappable_labels
from core.cycles import COMMON_KEYS, compute_task_metrics
from core.markers_csv import MarkerTable
from core.simulation.tasks import TaskTruth
from core.tasks import Task, task_key

EXCLUDED = 2  # 0-based cycle the clinician excludes


def _table(truth: TaskTruth, *, noise_mm: float = 0.03) -> MarkerTable:
    """markers.csv of the simulated trial, with 3D measurement noise (mm) as measured."""
    rng = np.random.default_rng(9)
    positions = truth.positions_mm + rng.normal(0.0, noise_mm, truth.positions_mm.shape)
    n, m = positions.shape[:2]
    return MarkerTable(
        fps=truth.fps,
        frames=np.arange(n, dtype=np.int64),
        labels=tuple(truth.marker_names),
        positions_mm=positions,
        status=np.full((n, m), "measured"),
        reprojection_px=np.full((n, m), np.nan),
    )


def _within(measured: np.ndarray, true: np.ndarray, task: Task) -> None:
    if task is Task.PRONATION_SUPINATION:
        assert np.max(np.abs(measured - true)) <= 0.5  # degrees
    else:
        assert np.max(np.abs(measured / true - 1)) <= 0.01  # 1 %


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("task", NEW_TASKS, ids=lambda t: t.value)
def test_excluding_a_cycle_and_dismissing_a_pause_match_the_truth(task: Task, side: str) -> None:
    truth = _truth(task, side, seed=5)
    corrections = Corrections(exclude_taps=(EXCLUDED,), dismiss_pauses=(3,))
    corrected = correct_metrics(_table(truth), corrections, task=task, side=side)
    doc = corrected.to_result()
    metrics = doc["metrics"]
    assert set(COMMON_KEYS) <= set(metrics)
    assert metrics["amplitude_unit"] == task.amplitude_unit
    assert metrics["cycle_count"] == len(truth.cycles) - 1  # exact
    kept_truth = [c for c in truth.cycles if c.index != EXCLUDED]
    amp_key = task_key("amplitude_mm", task)
    assert [c["index"] for c in doc["cycles"]] == [c.index for c in kept_truth]
    _within(
        np.array([c[amp_key] for c in doc["cycles"]]),
        np.array([c.amplitude for c in kept_truth]),
        task,
    )
    _within(
        np.array([metrics[task_key("amplitude_mm_mean", task)], metrics["amplitude_mean"]]),
        np.full(2, np.mean([c.amplitude for c in kept_truth])),
        task,
    )
    assert abs(metrics["frequency_hz"] / truth.frequency_hz - 1) <= 0.01  # 1 %
    slope = metrics["amplitude_decrement_per_cycle"]
    assert abs(slope / truth.decrement_per_cycle - 1) <= 0.10  # 10 %
    assert metrics[task_key("amplitude_decrement_mm_per_tap", task)] == slope
    # The hesitation before cycle 3 was dismissed; the halt before cycle 6 stays.
    assert metrics["hesitation_count"] == 0 and metrics["halt_count"] == 1
    assert [(e["kind"], e["cycle_index"]) for e in doc["events"] if e["kind"] != "gap"] == [
        ("halt", 6)
    ]
    assert [(e["kind"], e["cycle_index"]) for e in doc["dismissed_events"]] == [("hesitation", 3)]
    (excluded,) = doc["excluded_taps"]
    assert excluded["index"] == EXCLUDED and amp_key in excluded  # the task's names
    _within(np.array([excluded[amp_key]]), np.array([truth.cycles[EXCLUDED].amplitude]), task)
    assert doc["metrics_first_10"]["cycle_count"] == 10
    assert doc["cycle_analysis"]["unit"] == task.amplitude_unit


@pytest.mark.parametrize("task", NEW_TASKS, ids=lambda t: t.value)
def test_no_correction_gives_the_analysis_numbers(task: Task) -> None:
    """The correction measures through the analysis's code: nothing changed, nothing differs."""
    truth = _truth(task, "right", seed=5)
    table = _table(truth)
    analysis = compute_task_metrics(task, table.positions_mm, table.fps, side="right")
    corrected = correct_metrics(table, Corrections(), task=task, side="right").to_result()
    assert corrected["metrics"] == analysis.to_result()["metrics"]
    assert corrected["cycles"] == analysis.to_result()["cycles"]
    assert corrected["events"] == analysis.to_result()["events"]


def test_the_window_keeps_the_cycles_inside_it() -> None:
    task = Task.TOE_TAPPING
    truth = _truth(task, "right", seed=5)
    inside = truth.cycles[1:8]
    window = (inside[0].t_start_s - 0.02, inside[-1].t_end_s + 0.02)  # s
    corrected = correct_metrics(_table(truth), Corrections(window_s=window), task=task).to_result()
    assert [c["index"] for c in corrected["cycles"]] == [c.index for c in inside]
    assert corrected["metrics"]["cycle_count"] == len(inside)
    outside = {c["index"] for c in corrected["outside_window_taps"]}
    assert outside == {c.index for c in truth.cycles} - {c.index for c in inside}
    _within(
        np.array([corrected["metrics"]["amplitude_mean"]]),
        np.array([np.mean([c.amplitude for c in inside])]),
        task,
    )


def test_a_correction_of_the_wrong_task_fails_loudly() -> None:
    """Trajectories of one task corrected as another: its markers are named, nothing measured."""
    truth = _truth(Task.HAND_MOVEMENTS, "right", seed=5)
    with pytest.raises(ValueError, match="toe, heel and shin"):
        correct_metrics(_table(truth), Corrections(exclude_taps=(1,)), task=Task.TOE_TAPPING)
    with pytest.raises(ValueError, match="thumb and index"):
        correct_metrics(_table(truth), Corrections(exclude_taps=(1,)))


def test_cycle_numbers_in_errors_are_counted_from_1_in_the_task_words() -> None:
    truth = _truth(Task.HAND_MOVEMENTS, "right", seed=5)
    n = len(truth.cycles)
    with pytest.raises(
        ValueError, match=rf"no cycle {n + 1} \(index {n}\) in this recording \(it has {n} cycles"
    ):
        correct_metrics(_table(truth), Corrections(exclude_taps=(n,)), task=Task.HAND_MOVEMENTS)
    with pytest.raises(ValueError, match=r"cycle 2 \(index 1\) has no hesitation or halt"):
        correct_metrics(_table(truth), Corrections(dismiss_pauses=(1,)), task=Task.HAND_MOVEMENTS)


def test_labels_swap_for_two_markers_only() -> None:
    assert swappable_labels(Task.FINGER_TAPPING) == ("thumb", "index")
    assert swappable_labels(Task.HAND_MOVEMENTS) == ("finger", "wrist")
    assert swappable_labels(Task.PRONATION_SUPINATION) is None
    truth = _truth(Task.HAND_MOVEMENTS, "right", seed=5)
    table = _table(truth)
    plain = correct_metrics(table, Corrections(), task=Task.HAND_MOVEMENTS)
    swapped = correct_metrics(table, Corrections(swap_labels=True), task=Task.HAND_MOVEMENTS)
    assert swapped.to_result()["metrics"] == plain.to_result()["metrics"]  # a distance
    base = {"task": "hand_movements", "markers": ["finger", "wrist"], "fps": truth.fps}
    assert revised_document(base, swapped)["markers"] == ["wrist", "finger"]
    for task in (Task.PRONATION_SUPINATION, Task.TOE_TAPPING):
        with pytest.raises(ValueError, match="named by their distances"):
            correct_metrics(
                _table(_truth(task, "right", seed=5)), Corrections(swap_labels=True), task=task
            )

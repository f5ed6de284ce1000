"""A synthetic finger-tapping trial with known truth, for plot, report and export tests.

The thumb rests at a fixed point; the index finger moves along a fixed
direction so that the aperture (thumb–index distance minus the closed
distance) follows one raised-cosine bump per tap with a known amplitude that
shrinks linearly (the decrement), and a known pause (hesitation) after tap 12.
Everything in ``result`` is computed from these known values, not measured.
"""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np

from app.reports.data import CalibrationInfo, ReportData
from core.markers_csv import MarkerTable
from core.simulation.tasks import TaskTruth
from core.version import software_document

FPS = 100.0  # Hz
CLOSED_MM = 18.0  # thumb–index distance with the fingers together (marker offset)


def synthetic_trial(
    *,
    n_taps: int = 20,
    amplitude0_mm: float = 52.0,
    decrement_mm_per_tap: float = -0.8,
    frequency_hz: float = 2.5,
    pause_after_tap: int = 12,
    pause_s: float = 0.6,
    seed: int = 0,
) -> tuple[MarkerTable, dict]:
    """(markers, result.json document) of a synthetic trial; see the module docstring."""
    rng = np.random.default_rng(seed)
    period_s = 1.0 / frequency_hz
    amplitudes = amplitude0_mm + decrement_mm_per_tap * np.arange(n_taps)
    starts = []
    t = 0.3
    for k in range(n_taps):
        starts.append(t)
        t += period_s
        if k == pause_after_tap - 1:
            t += pause_s
    end_s = t + 0.3
    n_frames = int(np.ceil(end_s * FPS))
    time_s = np.arange(n_frames) / FPS
    aperture = np.zeros(n_frames)
    for a_k, t0 in zip(amplitudes, starts, strict=True):
        inside = (time_s >= t0) & (time_s < t0 + period_s)
        phase = (time_s[inside] - t0) / period_s
        aperture[inside] = 0.5 * a_k * (1 - np.cos(2 * np.pi * phase))
    thumb = np.array([10.0, -30.0, 600.0])
    direction = np.array([0.6, -0.8, 0.0])
    pos = np.empty((n_frames, 2, 3))
    pos[:, 0] = thumb
    pos[:, 1] = thumb + (CLOSED_MM + aperture)[:, None] * direction
    pos += rng.normal(scale=0.02, size=pos.shape)  # mm, seeded marker jitter
    status = np.full((n_frames, 2), "measured", dtype="<U12")
    status[200:204, 1] = "interpolated"
    pos[-1, 0] = np.nan
    status[-1, 0] = "missing"
    reproj = np.where(status == "measured", 0.1, np.nan)
    markers = MarkerTable(
        fps=FPS,
        frames=np.arange(n_frames, dtype=np.int64),
        labels=("thumb", "index"),
        positions_mm=pos,
        status=status,
        reprojection_px=reproj,
    )
    v_peak = np.pi * amplitudes * frequency_hz  # mm/s, peak slope of a raised cosine
    taps = [
        {
            "index": k,
            "t_start_s": round(starts[k], 4),
            "t_max_aperture_s": round(starts[k] + period_s / 2, 4),
            "t_end_s": round(starts[k] + period_s, 4),
            "amplitude_mm": float(amplitudes[k]),
            "opening_velocity_mm_s_max": float(v_peak[k]),
            "closing_velocity_mm_s_max": float(v_peak[k]),
        }
        for k in range(n_taps)
    ]
    intervals = np.diff(starts)
    thirds = n_taps // 3
    pause_start = starts[pause_after_tap - 1] + period_s
    metrics = {
        "tap_count": n_taps,
        "frequency_hz": float(1.0 / np.mean(intervals)),
        "amplitude_mm_mean": float(np.mean(amplitudes)),
        "amplitude_mm_cv": float(np.std(amplitudes) / np.mean(amplitudes)),
        "amplitude_decrement_mm_per_tap": decrement_mm_per_tap,
        "amplitude_ratio_last_first_third": float(
            np.mean(amplitudes[-thirds:]) / np.mean(amplitudes[:thirds])
        ),
        "opening_velocity_mm_s_max": float(np.median(v_peak)),
        "closing_velocity_mm_s_max": float(np.median(v_peak)),
        "inter_tap_interval_cv": float(np.std(intervals) / np.mean(intervals)),
        "hesitation_count": 1,
        "halt_count": 0,
    }
    # As core.pipeline writes them: first-10 metrics and located events at the top level.
    # The summary block's values over the first 10 taps (hesitations: the pause comes later
    # unless ``pause_after_tap`` < 10; a linear decrement falls from the first tap on).
    metrics_first_10 = {
        "tap_count": min(n_taps, 10),
        "reliable_tap_count": min(n_taps, 10),
        "amplitude_mm_mean": float(np.mean(amplitudes[:10])),
        "frequency_hz": frequency_hz,
        "opening_velocity_mm_s_max": float(np.mean(v_peak[:10])),
        "hesitation_count": int(pause_after_tap < 10),
        "halt_count": 0,
        "amplitude_decrement_mm_per_tap": decrement_mm_per_tap,
        "amplitude_decrement_onset_tap": 0 if decrement_mm_per_tap < 0 else None,
    }
    events = [
        {
            "kind": "hesitation",
            "tap_index": pause_after_tap,
            "t_start_s": pause_start,
            "duration_s": pause_s,
        }
    ]
    result = {
        "format": "bradyscope.result/1",
        "software": software_document(),
        "fps": FPS,
        "sync": {"offset_frames": 1.25, "method": "auto"},
        "metrics": metrics,
        "metrics_first_10": metrics_first_10,
        "events": events,
        "taps": taps,
        "quality": {
            "tracked_fraction": float(np.mean(status != "missing")),
            "measured_fraction": float(np.mean(status == "measured")),
            "interpolated_fraction": float(np.mean(status == "interpolated")),
            "reprojection_px_median": 0.1,
            "warnings": ["The thumb marker was lost in the last frame."],
        },
    }
    return markers, result


def sample_report_data(*, patient_code: str = "PD-0042", hand: str = "right") -> ReportData:
    """A ReportData around :func:`synthetic_trial`."""
    markers, result = synthetic_trial()
    return ReportData(
        trial_id=7,
        patient_code=patient_code,
        hand=hand,
        recorded_at=datetime(2025, 3, 14, 9, 30, tzinfo=UTC),
        medication_state="off",
        dbs_state="none",
        clinician_rating=2,
        rating_comment="Slowing from the 6th tap.",
        time_since_levodopa_min=720,
        more_affected_side="right",
        clinician="Dr. Demo",
        notes="12 h after last levodopa dose.",
        result=result,
        markers=markers,
        calibration=CalibrationInfo(
            rig_name="clinic-A",
            version=3,
            valid_from=datetime(2025, 1, 2, tzinfo=UTC),
            rms_px=0.21,
            verdict="good",
        ),
        generated_at=datetime(2025, 3, 14, 10, 0, tzinfo=UTC),
    )


def task_trial(
    task: str,
    *,
    side: str = "right",
    duration_s: float = 6.0,
    seed: int = 0,
    amplitude_scale: float = 1.0,
) -> tuple[MarkerTable, dict, TaskTruth]:
    """(markers, result.json, truth) of a simulated trial of a task other than finger tapping.

    The trajectories are the simulator's (``core.simulation.tasks``) with 0.03 mm of
    seeded 3D noise, a hesitation before cycle 3, a halt before cycle 6 and the
    decrement of tests/core/test_task_metrics.py (-1 mm or -3 degrees per cycle); the metrics
    are measured by core (:func:`core.cycles.compute_task_metrics`), and the document
    is laid out as ``core.pipeline`` writes it for such a task.
    """
    from core.cycles import compute_task_metrics
    from core.simulation.tasks import TaskScenario, simulate_task
    from core.tasks import Task

    the_task = Task(task)
    base = TaskScenario(task=the_task)
    scenario = TaskScenario(
        task=the_task,
        duration_s=duration_s,
        side=side,
        amplitude=base.amplitude * amplitude_scale,
        decrement_per_cycle=-3.0 if the_task is Task.PRONATION_SUPINATION else -1.0,
        hesitations=(3,),
        halts=((6, 0.5),),
    )
    truth = simulate_task(scenario, seed=seed)
    rng = np.random.default_rng(seed)
    pos = truth.positions_mm + rng.normal(0.0, 0.03, truth.positions_mm.shape)  # mm
    n, m = pos.shape[:2]
    markers = MarkerTable(
        fps=truth.fps,
        frames=np.arange(n, dtype=np.int64),
        labels=tuple(truth.marker_names),
        positions_mm=pos,
        status=np.full((n, m), "measured"),
        reprojection_px=np.full((n, m), 0.1),
    )
    measured = compute_task_metrics(the_task, pos, truth.fps, side=side).to_result()
    result = {
        "format": "bradyscope.result/1",
        "task": the_task.value,
        "software": software_document(),
        "fps": truth.fps,
        "sync": {"offset_frames": 0.0, "method": "given"},
        "taps": [],
        "markers": list(truth.marker_names),
        "frame_count": n,
        "quality": {
            "tracked_fraction": 1.0,
            "interpolated_fraction": 0.0,
            "reprojection_px_median": 0.1,
            "warnings": [],
        },
        **measured,
    }
    return markers, result, truth

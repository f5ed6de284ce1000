"""Metrics at the frames' real capture times (core.resample): jittered frame times and lost
frames of a free-running camera, against the same tapping sampled evenly (issue 11)."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from core.metrics import TappingMetrics, compute_metrics
from core.resample import uniform_trajectories
from core.simulation.kinematics import TappingScenario, TappingTruth, simulate_tapping

FPS = 60.0
LOST_AFTER = (100, 250, 251, 400)  # frames of the video after which one frame was lost


@cache
def _truth() -> TappingTruth:
    return simulate_tapping(
        TappingScenario(duration_s=10.0, fps=FPS, hesitations=(6,), halts=((14, 0.8),)), seed=3
    )


@cache
def _captured() -> tuple[np.ndarray, np.ndarray]:
    """(times (T,), positions (T, 2, 3)) as a free-running 60-fps camera delivers them:
    1-ms capture jitter, four frames lost, 0.02 mm of noise."""
    truth = _truth()
    rng = np.random.default_rng(5)
    taken = np.setdiff1d(np.arange(len(truth.t_s)), np.array(LOST_AFTER) + 1)
    t = taken / FPS + rng.normal(0, 0.001, len(taken))  # s
    t[0] = 0.0
    positions = truth.model.positions_mm(t)[:, :2] + rng.normal(0, 0.02, (len(t), 2, 3))
    return t, positions


def _per_tap(m: TappingMetrics, key: str) -> np.ndarray:
    return np.array([getattr(tap, key) for tap in m.taps])


def test_metrics_at_real_frame_times_match_even_sampling():
    """Frequency within 1 %, peak speeds within 3 % per tap and 1 % on average (the
    tolerances of docs/metrics.md §6), tap times within a tenth of a frame, events exact."""
    truth = _truth()
    reference = compute_metrics(truth.positions_mm[:, :2], FPS)  # evenly sampled, no loss
    t, positions = _captured()
    even = uniform_trajectories(positions, np.ones(positions.shape[:2], bool), t, FPS)
    assert even.resampled and even.positions_mm.shape == truth.positions_mm[:, :2].shape
    measured = compute_metrics(even.positions_mm, FPS, measured=even.measured)
    got, ref = measured.metrics, reference.metrics
    assert got["tap_count"] == ref["tap_count"] == len(truth.taps)
    assert got["frequency_hz"] == pytest.approx(truth.frequency_hz, rel=0.01)
    assert got["amplitude_mm_mean"] == pytest.approx(ref["amplitude_mm_mean"], rel=0.01)
    for key in ("opening_velocity_mm_s_max", "closing_velocity_mm_s_max"):
        assert got[key] == pytest.approx(ref[key], rel=0.01), key
        err = _per_tap(measured, key) / _per_tap(reference, key) - 1
        assert np.max(np.abs(err)) <= 0.03, key
    shift = _per_tap(measured, "t_start_s") - _per_tap(reference, "t_start_s")
    assert np.max(np.abs(shift)) * FPS <= 0.1  # frames
    assert (got["hesitation_count"], got["halt_count"]) == (1, 1)


def test_the_same_frames_read_as_frame_over_fps_are_measured_wrong():
    """What the test above guards against: frame numbers / fps put a lost frame's motion into
    one interval (a velocity spike) and every later time early by the frames lost."""
    reference = compute_metrics(_truth().positions_mm[:, :2], FPS)
    _, positions = _captured()
    naive = compute_metrics(positions, FPS)
    err = _per_tap(naive, "opening_velocity_mm_s_max") / _per_tap(
        reference, "opening_velocity_mm_s_max"
    )
    assert np.max(np.abs(err - 1)) > 0.3
    shift = _per_tap(naive, "t_start_s")[-3:] - _per_tap(reference, "t_start_s")[-3:]
    assert np.all(np.abs(shift * FPS + len(LOST_AFTER)) < 0.5)  # four frames early


def test_even_frames_are_returned_as_they_are():
    positions = np.arange(5 * 2 * 3, dtype=float).reshape(5, 2, 3)
    measured = np.ones((5, 2), bool)
    for times in (None, np.arange(5) / FPS, 2.0 + np.arange(5) / FPS):
        even = uniform_trajectories(positions, measured, times, FPS)
        assert not even.resampled
        assert even.positions_mm is positions or np.shares_memory(even.positions_mm, positions)
        assert np.array_equal(even.measured, measured)


def test_lost_frames_are_filled_in_and_long_gaps_left_empty():
    t = np.array([0, 1, 2, 4, 5, 6, 20, 21, 22, 23]) / FPS  # one frame lost, then 13 more
    positions = np.repeat(t[:, None, None] * 100.0, 2, axis=1).repeat(3, axis=2)  # 100 mm/s
    measured = np.ones((len(t), 2), bool)
    measured[1, 1] = False  # the tracker filled this one in
    even = uniform_trajectories(positions, measured, t, FPS, max_gap_s=0.1)
    assert even.positions_mm.shape == (24, 2, 3)
    grid = np.arange(24) / FPS
    known = np.isfinite(even.positions_mm[:, 0, 0])
    # The lost frame is interpolated (not measured); 0.1 s = 6 frames is not bridged.
    assert np.array_equal(np.flatnonzero(~known), np.arange(7, 20))
    assert np.allclose(even.positions_mm[known, 0, 0], 100.0 * grid[known])
    assert not even.measured[3].any() and even.measured[[2, 4, 5, 6, 20, 23], :].all()
    assert not even.measured[1, 1] and even.measured[1, 0]
    assert not even.measured[~known].any()


def test_a_late_frame_followed_by_an_early_one_is_not_a_gap():
    """Jitter: frame 3 delivered 0.6 of a period late, frame 4 on time (intervals of 1.6
    and 0.4 periods). No frame was lost, so the instants between them stay measured; a
    frame really lost (after frame 7 here) is not."""
    t = np.array([0, 1, 2, 3.6, 4, 5, 6, 7, 9, 10, 11]) / FPS
    positions = np.repeat(t[:, None, None] * 100.0, 2, axis=1).repeat(3, axis=2)
    even = uniform_trajectories(positions, np.ones((len(t), 2), bool), t, FPS)
    assert even.resampled and even.positions_mm.shape == (12, 2, 3)
    assert even.measured[:8].all() and even.measured[9:].all()
    assert not even.measured[8].any()  # the lost frame's instant: filled in


def test_wrong_shapes_and_times_are_refused():
    positions, measured = np.zeros((3, 2, 3)), np.ones((3, 2), bool)
    with pytest.raises(ValueError, match="one time per frame"):
        uniform_trajectories(positions, measured, np.arange(4) / FPS, FPS)
    with pytest.raises(ValueError, match="increase"):
        uniform_trajectories(positions, measured, np.array([0.0, 0.2, 0.1]), FPS)
    with pytest.raises(ValueError, match="measured"):
        uniform_trajectories(positions, measured[:, :1], None, FPS)

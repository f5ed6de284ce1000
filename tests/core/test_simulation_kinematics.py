"""Ground-truth self-consistency of the finger-tapping kinematic model."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.simulation.kinematics import (
    TappingScenario,
    least_squares_slope,
    simulate_tapping,
    tap_amplitudes_from_positions,
)


@pytest.fixture(scope="module")
def pd_truth():
    """A parkinsonian-looking trial: decrement, one hesitation, one halt, hand marker."""
    scenario = TappingScenario(
        duration_s=10.0,
        amplitude_mm=55.0,
        frequency_hz=2.5,
        decrement_mm_per_tap=-1.2,
        hesitations=(4,),
        halts=((9, 0.6),),
        hand_marker=True,
    )
    return simulate_tapping(scenario, seed=3)


def test_shapes_and_names(pd_truth):
    T = round(10.0 * 100.0)
    assert pd_truth.t_s.shape == (T,)
    assert pd_truth.positions_mm.shape == (T, 3, 3)
    assert pd_truth.marker_names == ("thumb", "index", "hand")
    np.testing.assert_allclose(pd_truth.t_s, np.arange(T) / 100.0, atol=0)
    assert np.all(np.isfinite(pd_truth.positions_mm))


def test_truth_amplitudes_match_trajectories(pd_truth):
    frames = [(tap.frame_start, tap.frame_end) for tap in pd_truth.taps]
    measured = tap_amplitudes_from_positions(pd_truth.positions_mm, frames)
    truth = np.array([tap.amplitude_mm for tap in pd_truth.taps])
    np.testing.assert_allclose(measured, truth, atol=1e-6)  # mm
    # Independent re-computation straight from the 3D distance, INTERFACES.md's definition.
    d = np.linalg.norm(pd_truth.positions_mm[:, 1] - pd_truth.positions_mm[:, 0], axis=1)
    for tap in pd_truth.taps:
        seg = d[tap.frame_start : tap.frame_end + 1]
        assert seg.max() - seg[0] == pytest.approx(tap.amplitude_mm, abs=1e-6)  # mm
        # Sampling at 100 fps misses the continuous peak by at most ~0.1 mm.
        assert tap.amplitude_mm == pytest.approx(tap.amplitude_model_mm, abs=0.1)  # mm
        # The tap starts at a closure: the distance there is the closed distance.
        assert seg[0] == pytest.approx(18.0, abs=0.1)  # mm


def test_aperture_is_exactly_the_model(pd_truth):
    model_aperture = pd_truth.model.aperture_mm(pd_truth.t_s)
    np.testing.assert_allclose(pd_truth.aperture_mm, model_aperture, atol=1e-9)  # mm
    assert pd_truth.aperture_mm.min() == pytest.approx(18.0, abs=1e-9)  # mm closed


def test_frequency_and_decrement(pd_truth):
    taps = pd_truth.taps
    cycles = np.array([t.t_end_s - t.t_start_s for t in taps])
    assert pd_truth.frequency_hz == pytest.approx(1.0 / cycles.mean(), rel=1e-12)
    assert pd_truth.frequency_hz == pytest.approx(2.5, rel=0.05)  # 3 % jitter over ~20 taps
    amps = [t.amplitude_mm for t in taps]
    assert pd_truth.decrement_mm_per_tap == pytest.approx(least_squares_slope(amps), abs=1e-12)
    assert pd_truth.decrement_mm_per_tap == pytest.approx(-1.2, abs=0.02)  # mm/tap, no amp jitter
    assert taps[0].amplitude_mm == pytest.approx(55.0, abs=0.1)  # mm
    # Taps are contiguous except where a pause was inserted.
    for prev, nxt in itertools.pairwise(taps):
        gap = nxt.t_start_s - prev.t_end_s
        expected = {4: 0.25, 9: 0.6}.get(nxt.index, 0.0)
        assert gap == pytest.approx(expected, abs=1e-9)  # s


def test_hesitation_and_halt_placement(pd_truth):
    (hes,) = pd_truth.hesitations
    (halt,) = pd_truth.halts
    assert (hes.tap_index, hes.duration_s) == (4, 0.25)
    assert (halt.tap_index, halt.duration_s) == (9, 0.6)
    assert hes.t_start_s == pytest.approx(pd_truth.taps[3].t_end_s, abs=1e-12)
    assert hes.t_start_s + hes.duration_s == pytest.approx(pd_truth.taps[4].t_start_s, abs=1e-12)
    assert halt.t_start_s + halt.duration_s == pytest.approx(pd_truth.taps[9].t_start_s, abs=1e-12)
    # During the halt the fingers are closed and do not move relative to each other.
    t = pd_truth.t_s
    inside = (t > halt.t_start_s + 0.01) & (t < halt.t_start_s + halt.duration_s - 0.01)
    assert inside.sum() >= 50
    np.testing.assert_allclose(pd_truth.aperture_mm[inside], 18.0, atol=1e-9)  # mm
    speed = np.linalg.norm(np.diff(pd_truth.positions_mm[:, :2], axis=0), axis=2) * 100.0
    assert speed[inside[1:]].max() < 15.0  # mm/s: only the slow hand drift remains


def test_posture_index_above_and_travels_further(pd_truth):
    p = pd_truth.positions_mm
    # y is down in the camera frame: the index marker is higher (smaller y) than the thumb.
    assert np.all(p[:, 1, 1] < p[:, 0, 1])
    index_travel = np.ptp(p[:, 1, 1])
    thumb_travel = np.ptp(p[:, 0, 1])
    assert index_travel > 2.0 * thumb_travel
    # About half a metre in front of the rig.
    assert 400 < p[:, :, 2].min() and p[:, :, 2].max() < 650


def test_motion_is_smooth():
    """C2: halving the time step halves the largest change of acceleration between samples.

    A jump in acceleration (a C1-only model) would keep that change constant.
    """

    def max_acc_step(fps):
        truth = simulate_tapping(TappingScenario(duration_s=3.0, fps=fps, drift_mm=0.0), seed=0)
        acc = np.diff(truth.positions_mm[:, :2], n=2, axis=0) * fps**2  # mm/s^2
        return np.abs(np.diff(acc, axis=0)).max()

    ratio = max_acc_step(1000.0) / max_acc_step(2000.0)
    assert 1.8 < ratio < 2.2


def test_deterministic_and_json_serialisable():
    a = simulate_tapping(TappingScenario(duration_s=2.0), seed=7)
    b = simulate_tapping(TappingScenario(duration_s=2.0), seed=7)
    c = simulate_tapping(TappingScenario(duration_s=2.0), seed=8)
    assert json.dumps(a.to_dict()) == json.dumps(b.to_dict())
    assert not np.array_equal(a.positions_mm, c.positions_mm)


def test_left_hand_is_mirrored():
    right = simulate_tapping(TappingScenario(duration_s=2.0), seed=1)
    left = simulate_tapping(TappingScenario(duration_s=2.0, hand="left"), seed=1)
    np.testing.assert_allclose(left.aperture_mm, right.aperture_mm, atol=1e-9)
    # The left hand is the right one mirrored in x about the hand centre (x = 0 here).
    np.testing.assert_allclose(left.positions_mm[..., 1:], right.positions_mm[..., 1:], atol=1e-9)
    np.testing.assert_allclose(left.positions_mm[..., 0], -right.positions_mm[..., 0], atol=1e-9)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"duration_s": 0},
        {"fps": -1},
        {"amplitude_mm": 0},
        {"frequency_hz": 0},
        {"hand": "middle"},
        {"hesitations": (0,)},
        {"halts": ((3, 0.1),)},
        {"fps": 10.0, "frequency_hz": 3.0},
    ],
)
def test_invalid_scenarios(kwargs):
    with pytest.raises(ValueError):
        TappingScenario(**kwargs)


def test_pause_beyond_last_tap_is_an_error():
    with pytest.raises(ValueError, match="do not fit"):
        simulate_tapping(TappingScenario(duration_s=2.0, hesitations=(40,)), seed=0)


@settings(max_examples=25, deadline=None)
@given(
    amplitude_mm=st.floats(5.0, 100.0),
    frequency_hz=st.floats(1.0, 6.0),
    decrement=st.floats(-2.0, 1.0),
    jitter=st.floats(0.0, 0.2),
    amplitude_jitter=st.floats(0.0, 0.2),
    fps=st.sampled_from([30.0, 60.0, 100.0, 240.0]),
    hand=st.sampled_from(["right", "left"]),
    seed=st.integers(0, 2**31 - 1),
)
def test_truth_is_self_consistent_for_any_scenario(
    amplitude_mm, frequency_hz, decrement, jitter, amplitude_jitter, fps, hand, seed
):
    scenario = TappingScenario(
        duration_s=4.0,
        fps=fps,
        amplitude_mm=amplitude_mm,
        frequency_hz=frequency_hz,
        decrement_mm_per_tap=decrement,
        rhythm_jitter=jitter,
        amplitude_jitter=amplitude_jitter,
        hand=hand,
    )
    truth = simulate_tapping(scenario, seed=seed)
    d = truth.aperture_mm
    assert d.min() == pytest.approx(18.0, abs=1e-9)  # mm: the closed distance
    assert np.all(d >= 18.0 - 1e-9)
    for tap in truth.taps:
        seg = d[tap.frame_start : tap.frame_end + 1]
        assert seg.max() - seg[0] == pytest.approx(tap.amplitude_mm, abs=1e-6)  # mm
        assert tap.amplitude_mm <= tap.amplitude_model_mm + 1e-9  # sampling can only miss the peak
        assert tap.t_start_s < tap.t_max_aperture_s < tap.t_end_s
    for prev, nxt in itertools.pairwise(truth.taps):
        assert nxt.t_start_s == pytest.approx(prev.t_end_s, abs=1e-12)  # no pauses requested
    if truth.taps:
        cycles = [t.t_end_s - t.t_start_s for t in truth.taps]
        assert truth.frequency_hz == pytest.approx(1.0 / np.mean(cycles))
    px_ok = np.all(truth.positions_mm[:, 1, 1] < truth.positions_mm[:, 0, 1])
    assert px_ok  # the index stays above the thumb (y down)

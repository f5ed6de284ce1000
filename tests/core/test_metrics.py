"""Acceptance and property tests of the finger-tapping metrics against simulated truth."""

from __future__ import annotations

import json
from functools import cache

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.metrics import compute_metrics, decrement_onset
from core.simulation.kinematics import TappingScenario, TappingTruth, simulate_tapping

REQUIRED_METRICS = (
    "tap_count",
    "frequency_hz",
    "amplitude_mm_mean",
    "amplitude_mm_cv",
    "amplitude_decrement_mm_per_tap",
    "amplitude_ratio_last_first_third",
    "opening_velocity_mm_s_max",
    "closing_velocity_mm_s_max",
    "inter_tap_interval_cv",
    "hesitation_count",
    "halt_count",
)
REQUIRED_TAP_KEYS = (
    "index",
    "t_start_s",
    "t_max_aperture_s",
    "t_end_s",
    "amplitude_mm",
    "opening_velocity_mm_s_max",
    "closing_velocity_mm_s_max",
)
FEW = settings(
    max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None
)


@cache
def _truth(fps: float = 100.0, seed: int = 11, **kw) -> TappingTruth:
    params = dict(
        duration_s=10.0,
        fps=fps,
        amplitude_mm=50.0,
        frequency_hz=3.0,
        decrement_mm_per_tap=-0.8,
        rhythm_jitter=0.05,
        hesitations=(9,),
        hesitation_s=0.25,
        halts=((20, 0.5),),
        drift_mm=8.0,
    )
    params.update(kw)
    return simulate_tapping(TappingScenario(**params), seed=seed)


@cache
def _measured(fps: float = 100.0, seed: int = 11):
    truth = _truth(fps, seed)
    return truth, compute_metrics(truth.positions_mm, fps)


# --- acceptance on simulated tapping ------------------------------------------------


@pytest.mark.parametrize("fps", [60.0, 100.0, 200.0])
def test_acceptance_against_simulated_truth(fps):
    truth, result = _measured(fps)
    m = result.metrics
    amps = np.array([t.amplitude_mm for t in truth.taps])
    assert m["tap_count"] == len(truth.taps)  # exact
    for tap, true in zip(result.taps, truth.taps, strict=True):
        assert tap.amplitude_mm == pytest.approx(true.amplitude_mm, abs=0.3)  # mm
    assert m["amplitude_mm_mean"] == pytest.approx(amps.mean(), rel=0.01)
    assert m["frequency_hz"] == pytest.approx(truth.frequency_hz, rel=0.01)
    assert m["amplitude_decrement_mm_per_tap"] == pytest.approx(
        truth.decrement_mm_per_tap, rel=0.10
    )


@pytest.mark.parametrize("fps", [60.0, 100.0, 200.0])
def test_hesitation_and_halt_found_at_the_right_taps_and_nothing_else(fps):
    truth, result = _measured(fps)
    events = [e for e in result.events if e["kind"] in ("hesitation", "halt")]
    assert [(e["kind"], e["tap_index"]) for e in events] == [("hesitation", 9), ("halt", 20)]
    hes, halt = events
    (true_hes,), (true_halt,) = truth.hesitations, truth.halts
    assert hes["t_start_s"] == pytest.approx(true_hes.t_start_s, abs=0.03)  # s
    assert halt["t_start_s"] == pytest.approx(true_halt.t_start_s, abs=0.03)  # s
    assert halt["duration_s"] == pytest.approx(0.5, abs=0.03)  # s
    assert result.metrics["hesitation_count"] == 1
    assert result.metrics["halt_count"] == 1


def test_no_false_events_in_regular_tapping():
    truth = _truth(seed=3, hesitations=(), halts=(), rhythm_jitter=0.08)
    result = compute_metrics(truth.positions_mm, truth.fps)
    assert result.metrics["hesitation_count"] == 0
    assert result.metrics["halt_count"] == 0
    assert result.metrics["tap_count"] == len(truth.taps)


def test_halt_with_the_fingers_open_is_found():
    """A freeze at maximal aperture (not a closed pause) is a halt too."""
    truth = _truth(hesitations=(), halts=())
    fps = truth.fps
    k = 12
    t_peak = truth.taps[k].t_max_aperture_s
    t = np.arange(round((truth.t_s[-1] + 0.5) * fps)) / fps
    # Warp time: hold the model still at t_peak for 0.5 s.
    warped = np.where(t < t_peak, t, np.maximum(t_peak, t - 0.5))
    pos = truth.model.positions_mm(warped)
    result = compute_metrics(pos, fps)
    halts = [e for e in result.events if e["kind"] == "halt"]
    assert [e["tap_index"] for e in halts] == [k]
    assert halts[0]["duration_s"] == pytest.approx(0.5, abs=0.05)  # s
    assert result.metrics["hesitation_count"] == 0


def test_velocity_metrics_against_the_model():
    truth, result = _measured()
    t_fine = np.arange(0, truth.t_s[-1], 1e-4)
    v = np.gradient(truth.model.aperture_mm(t_fine), t_fine)
    peaks_open, peaks_close = [], []
    for true in truth.taps:
        o = (t_fine >= true.t_start_s) & (t_fine <= true.t_max_aperture_s)
        c = (t_fine >= true.t_max_aperture_s) & (t_fine <= true.t_end_s)
        peaks_open.append(v[o].max())
        peaks_close.append(-v[c].min())
    m = result.metrics
    assert m["opening_velocity_mm_s_max"] == pytest.approx(np.mean(peaks_open), rel=0.01)
    assert m["closing_velocity_mm_s_max"] == pytest.approx(np.mean(peaks_close), rel=0.01)
    assert m["opening_velocity_mm_s_peak"] == pytest.approx(np.max(peaks_open), rel=0.02)
    # The amplitude shrinks at a constant speed profile, so peak velocity shrinks too.
    assert m["opening_velocity_decrement_mm_s_per_tap"] < 0


def test_ratios_and_percent_decrement_match_their_formulas():
    truth, result = _measured()
    amps = np.array([t.amplitude_mm for t in truth.taps])
    n = len(amps)
    m = result.metrics
    k = n // 3
    assert m["amplitude_ratio_last_first_third"] == pytest.approx(
        amps[-k:].mean() / amps[:k].mean(), rel=0.01
    )
    h = n // 2
    assert m["amplitude_ratio_second_first_half"] == pytest.approx(
        amps[-h:].mean() / amps[:h].mean(), rel=0.01
    )
    assert m["amplitude_decrement_pct_per_tap"] == pytest.approx(
        100 * truth.decrement_mm_per_tap / amps[:3].mean(), rel=0.1
    )
    assert m["amplitude_mm_sd"] == pytest.approx(amps.std(ddof=1), rel=0.02)
    assert m["amplitude_mm_cv"] == pytest.approx(amps.std(ddof=1) / amps.mean(), rel=0.02)


def test_first_10_taps():
    truth, result = _measured()
    f10 = result.metrics_first_10
    amps = np.array([t.amplitude_mm for t in truth.taps[:10]])
    assert f10["tap_count"] == 10
    assert f10["amplitude_mm_mean"] == pytest.approx(amps.mean(), rel=0.01)
    assert f10["hesitation_count"] == 1  # tap 9 is among the first 10
    assert f10["halt_count"] == 0  # tap 20 is not


def test_result_is_json_with_the_interface_keys():
    _, result = _measured()
    doc = result.to_result()
    text = json.dumps(doc, allow_nan=False)
    back = json.loads(text)
    for key in REQUIRED_METRICS:
        assert key in back["metrics"]
    for key in REQUIRED_TAP_KEYS:
        assert key in back["taps"][0]
    assert set(back) >= {"metrics", "taps", "metrics_first_10", "events"}


@pytest.mark.parametrize("n_taps", [0, 1])
def test_zero_or_one_tap_gives_none_not_crash(n_taps):
    truth = _truth()
    fps = truth.fps
    end = round((truth.taps[0].t_end_s + 0.2) * fps) if n_taps else 40
    pos = truth.positions_mm[:end]
    result = compute_metrics(pos, fps)
    doc = result.to_result()
    json.dumps(doc, allow_nan=False)
    m = doc["metrics"]
    assert m["tap_count"] == n_taps
    assert m["inter_tap_interval_cv"] is None
    assert m["amplitude_decrement_mm_per_tap"] is None
    assert m["amplitude_ratio_last_first_third"] is None
    assert m["amplitude_mm_cv"] is None
    assert m["hesitation_count"] == 0 and m["halt_count"] == 0
    if n_taps:
        assert m["amplitude_mm_mean"] == pytest.approx(truth.taps[0].amplitude_mm, abs=0.3)
        assert m["frequency_hz"] is not None
    else:
        assert m["amplitude_mm_mean"] is None and m["frequency_hz"] is None


def test_all_missing_markers_give_empty_metrics():
    result = compute_metrics(np.full((200, 2, 3), np.nan), 100.0)
    assert result.metrics["tap_count"] == 0
    json.dumps(result.to_result(), allow_nan=False)


def test_long_gap_is_reported_and_its_taps_excluded():
    truth = _truth()
    fps = truth.fps
    pos = np.array(truth.positions_mm)
    t = truth.taps
    g0, g1 = round(t[4].t_max_aperture_s * fps), round(t[6].t_max_aperture_s * fps)
    pos[g0:g1, 1] = np.nan
    result = compute_metrics(pos, fps)
    gaps = [e for e in result.events if e["kind"] == "gap"]
    assert len(gaps) == 1
    assert gaps[0]["t_start_s"] == pytest.approx(g0 / fps)
    assert gaps[0]["duration_s"] == pytest.approx((g1 - g0) / fps)
    assert result.metrics["tap_count"] == len(t) - 3
    assert result.metrics["gap_count"] == 1
    # The decrement is still measured over the true tap numbers.
    assert result.metrics["amplitude_decrement_mm_per_tap"] == pytest.approx(
        truth.decrement_mm_per_tap, rel=0.1
    )


def test_filled_in_peak_is_left_out_of_amplitude_statistics():
    truth = _truth()
    fps = truth.fps
    measured = np.ones(truth.positions_mm.shape[:2], bool)
    i = round(truth.taps[3].t_max_aperture_s * fps)
    measured[i - 2 : i + 3, 0] = False
    pos = np.array(truth.positions_mm)
    pos[i - 2 : i + 3] = np.linspace(pos[i - 3], pos[i + 3], 7)[1:-1]  # what the tracker fills
    result = compute_metrics(pos, fps, measured=measured)
    m = result.metrics
    assert m["tap_count"] == len(truth.taps)
    assert m["reliable_tap_count"] == len(truth.taps) - 1
    amps = [t.amplitude_mm for k, t in enumerate(truth.taps) if k != 3]
    assert m["amplitude_mm_mean"] == pytest.approx(np.mean(amps), rel=0.005)


def test_decrement_onset():
    x = np.arange(15, dtype=float)
    plateau = np.where(x <= 6, 50.0, 50.0 - 3.0 * (x - 6))
    rng = np.random.default_rng(0)
    assert decrement_onset(x, plateau + rng.normal(0, 0.5, x.size)) in (5, 6, 7)
    assert decrement_onset(x, 50.0 + rng.normal(0, 0.5, x.size)) is None
    assert decrement_onset(x, 50.0 - 2.0 * x) == 0
    assert decrement_onset(x, 30.0 + 1.0 * x) is None
    assert decrement_onset(x[:4], plateau[:4]) is None
    _, result = _measured()
    assert result.metrics["amplitude_decrement_onset_tap"] in (0, 1, 2)


# --- properties ----------------------------------------------------------------------


@FEW
@given(k=st.floats(0.5, 2.0))
def test_scaling_the_trajectory_scales_amplitudes_and_velocities(k):
    truth, base = _measured()
    centre = truth.positions_mm.mean(axis=(0, 1))
    scaled = compute_metrics(centre + k * (truth.positions_mm - centre), truth.fps)
    mb, ms = base.metrics, scaled.metrics
    assert ms["tap_count"] == mb["tap_count"]
    for key in ("amplitude_mm_mean", "opening_velocity_mm_s_max", "closing_velocity_mm_s_max"):
        assert ms[key] == pytest.approx(k * mb[key], rel=1e-6)
    for a, b in zip(scaled.taps, base.taps, strict=True):
        assert a.amplitude_mm == pytest.approx(k * b.amplitude_mm, rel=1e-6)
        assert a.opening_velocity_mm_s_max == pytest.approx(
            k * b.opening_velocity_mm_s_max, rel=1e-6
        )
    assert ms["frequency_hz"] == pytest.approx(mb["frequency_hz"], rel=1e-9)
    assert ms["amplitude_ratio_last_first_third"] == pytest.approx(
        mb["amplitude_ratio_last_first_third"], rel=1e-6
    )


@FEW
@given(k=st.floats(0.6, 1.6))
def test_stretching_time_divides_frequency(k):
    """The same samples read at fps / k last k times longer."""
    truth, base = _measured()
    slow = compute_metrics(truth.positions_mm, truth.fps / k)
    assert slow.metrics["tap_count"] == base.metrics["tap_count"]
    assert slow.metrics["frequency_hz"] == pytest.approx(base.metrics["frequency_hz"] / k, rel=0.01)
    assert slow.metrics["amplitude_mm_mean"] == pytest.approx(
        base.metrics["amplitude_mm_mean"], rel=0.01
    )
    assert slow.metrics["opening_velocity_mm_s_max"] == pytest.approx(
        base.metrics["opening_velocity_mm_s_max"] / k, rel=0.03
    )


@FEW
@given(seed=st.integers(0, 2**31 - 1), fps=st.sampled_from([60.0, 100.0, 200.0]))
def test_noise_of_0_2_mm_changes_no_tap_count(seed, fps):
    truth, base = _measured(fps)
    rng = np.random.default_rng(seed)
    noisy = truth.positions_mm + rng.normal(0.0, 0.2, truth.positions_mm.shape)  # mm
    result = compute_metrics(noisy, fps)
    assert result.metrics["tap_count"] == base.metrics["tap_count"] == len(truth.taps)
    assert result.metrics["amplitude_mm_mean"] == pytest.approx(
        base.metrics["amplitude_mm_mean"], rel=0.01
    )


@FEW
@given(seed=st.integers(0, 1000), drift=st.floats(0.0, 40.0))
def test_drift_of_the_hand_changes_nothing(seed, drift):
    a = _truth(seed=seed, drift_mm=0.0)
    b = _truth(seed=seed, drift_mm=drift)
    ma = compute_metrics(a.positions_mm, a.fps).metrics
    mb = compute_metrics(b.positions_mm, b.fps).metrics
    for key in ("tap_count", "hesitation_count", "halt_count"):
        assert ma[key] == mb[key]
    assert mb["amplitude_mm_mean"] == pytest.approx(ma["amplitude_mm_mean"], rel=1e-6)
    assert mb["frequency_hz"] == pytest.approx(ma["frequency_hz"], rel=1e-6)

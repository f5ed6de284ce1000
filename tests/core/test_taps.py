"""Tests of tap segmentation against the simulator's ground truth and edge cases."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from core.aperture import aperture_signal
from core.simulation.kinematics import TappingScenario, TappingTruth, simulate_tapping
from core.taps import Tap, segment_recording, segment_taps


@cache
def _truth(fps: float = 100.0, **kw) -> TappingTruth:
    params = dict(
        duration_s=8.0,
        fps=fps,
        amplitude_mm=50.0,
        frequency_hz=3.0,
        decrement_mm_per_tap=-0.8,
        rhythm_jitter=0.05,
        hesitations=(6,),
        halts=((14, 0.5),),
        drift_mm=5.0,
    )
    params.update(kw)
    return simulate_tapping(TappingScenario(**params), seed=7)


def _taps(positions, fps, **kw) -> list[Tap]:
    return segment_taps(aperture_signal(positions, fps, **kw))


@pytest.mark.parametrize("fps", [60.0, 100.0, 200.0])
def test_taps_match_truth(fps):
    truth = _truth(fps)
    taps = _taps(truth.positions_mm, fps)
    assert len(taps) == len(truth.taps)
    for tap, true in zip(taps, truth.taps, strict=True):
        assert tap.amplitude_mm == pytest.approx(true.amplitude_mm, abs=0.3)  # mm
        assert tap.t_start_s == pytest.approx(true.t_start_s, abs=1.5 / fps)  # s
        assert tap.t_max_aperture_s == pytest.approx(true.t_max_aperture_s, abs=1.5 / fps)  # s
        assert tap.t_end_s == pytest.approx(true.t_end_s, abs=1.5 / fps)  # s
    assert [t.index for t in taps] == list(range(len(taps)))
    assert [t.cycle_number for t in taps] == list(range(len(taps)))
    assert all(t.reliable and not t.after_gap for t in taps)


def test_pauses_belong_to_the_following_tap():
    truth = _truth()
    taps = _taps(truth.positions_mm, truth.fps)
    pauses = {t.index: t.pause_before_s for t in taps if t.pause_before_s}
    assert set(pauses) == {6, 14}
    assert pauses[6] == pytest.approx(0.25, abs=0.02)  # s
    assert pauses[14] == pytest.approx(0.5, abs=0.02)  # s
    assert taps[0].pause_before_s is None
    # Intervals include the pause, durations do not.
    assert taps[5].interval_s == pytest.approx(taps[5].duration_s + 0.25, abs=0.02)  # s


def test_per_tap_velocities_against_the_model():
    truth = _truth()
    fps = truth.fps
    taps = _taps(truth.positions_mm, fps)
    t_fine = np.arange(0, 8.0, 1e-4)
    ap_fine = truth.model.aperture_mm(t_fine)
    v_fine = np.gradient(ap_fine, t_fine)
    for tap, true in zip(taps, truth.taps, strict=True):
        opening = (t_fine >= true.t_start_s) & (t_fine <= true.t_max_aperture_s)
        closing = (t_fine >= true.t_max_aperture_s) & (t_fine <= true.t_end_s)
        assert tap.opening_velocity_mm_s_max == pytest.approx(v_fine[opening].max(), rel=0.03)
        assert tap.closing_velocity_mm_s_max == pytest.approx(-v_fine[closing].min(), rel=0.03)
        assert tap.opening_velocity_mm_s_mean == pytest.approx(
            true.amplitude_mm / (true.t_max_aperture_s - true.t_start_s), rel=0.05
        )
        assert tap.opening_velocity_mm_s_max > tap.opening_velocity_mm_s_mean > 0
        assert tap.closing_velocity_mm_s_max > tap.closing_velocity_mm_s_mean > 0


def test_incomplete_first_and_last_taps_are_dropped():
    truth = _truth()
    fps = truth.fps
    # Start in the middle of tap 1's opening, end in the middle of the closing
    # of the last tap but one.
    n = len(truth.taps)
    t1, tl = truth.taps[1], truth.taps[n - 2]
    i0 = round((t1.t_start_s + t1.t_max_aperture_s) / 2 * fps)
    i1 = round((tl.t_max_aperture_s + tl.t_end_s) / 2 * fps)
    taps = _taps(truth.positions_mm[i0:i1], fps)
    assert len(taps) == n - 4
    for tap, true in zip(taps, truth.taps[2 : n - 2], strict=True):
        assert tap.t_max_aperture_s + i0 / fps == pytest.approx(true.t_max_aperture_s, abs=0.015)
        assert tap.amplitude_mm == pytest.approx(true.amplitude_mm, abs=0.3)  # mm


def test_a_gap_drops_the_taps_it_cuts_and_counts_lost_cycles():
    truth = _truth()
    fps = truth.fps
    pos = np.array(truth.positions_mm)
    t = truth.taps
    g0, g1 = round(t[8].t_max_aperture_s * fps), round(t[10].t_max_aperture_s * fps)
    pos[g0:g1, 0] = np.nan  # thumb lost from the peak of tap 8 to the peak of tap 10
    taps = _taps(pos, fps)
    assert len(taps) == len(t) - 3  # taps 8, 9 and 10 are cut
    assert not any(g0 <= tap.i_max < g1 for tap in taps)
    assert not any(tap.i_start < g1 and tap.i_end >= g0 for tap in taps)
    after = taps[8]
    assert after.after_gap and after.cycle_number == 11
    assert taps[7].interval_s is None  # no interval across the gap
    assert after.pause_before_s is None
    assert [tp.cycle_number for tp in taps] == [*range(8), *range(11, len(t))]


def test_filled_in_maximum_makes_a_tap_unreliable():
    truth = _truth()
    fps = truth.fps
    measured = np.ones(truth.positions_mm.shape[:2], bool)
    i = round(truth.taps[4].t_max_aperture_s * fps)
    measured[i - 3 : i + 3, 1] = False
    taps = _taps(truth.positions_mm, fps, measured=measured)
    assert len(taps) == len(truth.taps)
    assert [t.index for t in taps if not t.reliable] == [4]
    assert taps[4].filled_fraction > 0


def test_no_taps_on_still_or_missing_fingers():
    truth = _truth()
    still = np.repeat(truth.positions_mm[:1], 300, axis=0)
    assert _taps(still, 100.0) == []
    assert _taps(np.full((300, 2, 3), np.nan), 100.0) == []
    seg = segment_recording(aperture_signal(still, 100.0))
    assert seg.taps == []


def test_one_tap():
    truth = _truth()
    end = round((truth.taps[1].t_end_s + 0.2) * truth.fps)
    pos = np.array(truth.positions_mm[:end])
    # Keep only tap 1 of the two: hold the fingers closed during tap 0.
    i0, i1 = round(truth.taps[0].t_start_s * 100) - 5, round(truth.taps[0].t_end_s * 100) + 1
    pos[i0:i1] = pos[i0]
    taps = _taps(pos, truth.fps)
    assert len(taps) == 1
    assert taps[0].amplitude_mm == pytest.approx(truth.taps[1].amplitude_mm, abs=0.3)  # mm
    assert taps[0].interval_s is None


def test_small_wobbles_are_not_taps():
    truth = _truth()
    fps = truth.fps
    pos = np.array(truth.positions_mm)
    t = truth.t_s
    # A 1.5-mm, 9-Hz tremor of the index along the opening direction.
    direction = pos[:, 1] - pos[:, 0]
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    pos[:, 1] += 0.75 * np.sin(2 * np.pi * 9.0 * t)[:, None] * direction
    taps = _taps(pos, fps)
    assert len(taps) == len(truth.taps)


def test_threshold_is_relative_so_small_late_taps_still_count():
    truth = _truth(decrement_mm_per_tap=-2.0, hesitations=(), halts=())
    amps = [t.amplitude_mm for t in truth.taps]
    assert min(amps) < 10  # the last taps are small
    taps = _taps(truth.positions_mm, truth.fps)
    assert len(taps) == len(truth.taps)


def test_bad_options_raise():
    ap = aperture_signal(_truth().positions_mm, 100.0)
    with pytest.raises(ValueError, match="min_amplitude_mm"):
        segment_taps(ap, min_amplitude_mm=0)
    with pytest.raises(ValueError, match="still_fraction"):
        segment_taps(ap, still_fraction=1.5)
    with pytest.raises(ValueError, match="relative_amplitude"):
        segment_taps(ap, relative_amplitude=-0.1)


def test_tap_dict_has_the_result_json_keys():
    tap = _taps(_truth().positions_mm, 100.0)[0]
    d = tap.to_dict()
    for key in (
        "index",
        "t_start_s",
        "t_max_aperture_s",
        "t_end_s",
        "amplitude_mm",
        "opening_velocity_mm_s_max",
        "closing_velocity_mm_s_max",
    ):
        assert key in d


def _contact_taps(amps, periods, dwells, fps, *, closed_mm=20.0, lead_s=0.4, tail_s=0.4):
    """Taps that end in a collision: raised-cosine opening, closing that hits the
    thumb at full speed (quarter cosine), then ``dwells[k]`` s in contact before
    tap k. Unlike the simulator's C2 taps, the closure is a sharp corner.
    Returns positions (T, 2, 3) and per-tap (t_start, t_max, t_end, amplitude)."""
    truth, t = [], lead_s
    for a, p, dw in zip(amps, periods, dwells, strict=True):
        t0 = t + dw
        truth.append((t0, t0 + 0.45 * p, t0 + p, a))
        t = t0 + p
    ts = np.arange(int((t + tail_s) * fps)) / fps
    d = np.full(ts.shape, closed_mm)
    for t0, tm, te, a in truth:
        m = (ts >= t0) & (ts < tm)
        d[m] = closed_mm + a * (1 - np.cos(np.pi * (ts[m] - t0) / (tm - t0))) / 2
        m = (ts >= tm) & (ts < te)
        d[m] = closed_mm + a * np.cos(np.pi / 2 * (ts[m] - tm) / (te - tm))
    pos = np.zeros((len(ts), 2, 3))
    pos[:, 1, 0] = d
    return pos, truth


@pytest.mark.parametrize("fps", [60.0, 100.0, 200.0])
def test_sharp_contact_closures(fps):
    rng = np.random.default_rng(1)
    n = 20
    amps = 50.0 - np.arange(n)
    periods = 0.3 * (1 + 0.05 * rng.standard_normal(n))
    dwells = np.full(n, 0.03)
    pos, truth = _contact_taps(amps, periods, dwells, fps)
    taps = _taps(pos, fps)
    assert len(taps) == n
    for tap, (_t0, tm, te, a) in zip(taps, truth, strict=True):
        assert tap.amplitude_mm == pytest.approx(a, abs=0.35)  # mm (sampling of the corner)
        assert tap.t_max_aperture_s == pytest.approx(tm, abs=1.0 / fps)  # s
        # A brisk turn (no pause) splits the 30-ms contact in its middle.
        assert te - 1.0 / fps <= tap.t_end_s <= te + 0.03 + 1.5 / fps  # s


@pytest.mark.parametrize("fps", [60.0, 100.0])
def test_slow_tapping_with_a_dwell_at_every_closure(fps):
    """A slow patient resting ~0.25 s in contact at every tap: no pauses singled
    out, cycles measured closure to closure, small late taps still counted."""
    rng = np.random.default_rng(1)
    n = 15
    amps = np.maximum(40.0 - 2.5 * np.arange(n), 4.0)
    periods = 0.7 * (1 + 0.12 * rng.standard_normal(n))
    dwells = 0.25 * (1 + 0.2 * rng.standard_normal(n))
    dwells[0] = 0.0
    pos, truth = _contact_taps(amps, periods, dwells, fps)
    pos = pos + rng.normal(0.0, 0.1, pos.shape)  # mm
    seg = segment_recording(aperture_signal(pos, fps))
    taps = seg.taps
    assert len(taps) == n
    assert seg.typical_turn_s == pytest.approx(0.25, abs=0.06)  # s
    # Only the excess over the typical dwell (jitter, here <= 0.1 s) is a pause.
    assert max(t.pause_before_s for t in taps[1:]) < 0.15  # s
    # Taps are split in the middle of a dwell that holds no pause, so a cycle
    # runs from about the middle of one dwell to the middle of the next.
    middles = [truth[k][2] + dwells[k + 1] / 2 for k in range(n - 1)]
    got = [t.cycle_s for t in taps[1 : n - 1]]
    np.testing.assert_allclose(got, np.diff(middles), atol=0.06)  # s

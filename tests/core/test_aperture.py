"""Tests of the aperture signal: distance, zero-phase filter, smooth velocity, gaps."""

from __future__ import annotations

import numpy as np
import pytest

from core.aperture import aperture_signal, default_cutoff_hz, true_runs


def _two_markers(distance_mm: np.ndarray, *, direction=(0.6, 0.0, 0.8)) -> np.ndarray:
    """Thumb fixed at (10, -40, 600) mm, index ``distance_mm`` away along ``direction``."""
    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    thumb = np.broadcast_to([10.0, -40.0, 600.0], (len(distance_mm), 3))
    index = thumb + distance_mm[:, None] * d
    return np.stack([thumb, index], axis=1)


def _sine(fps: float, *, f_hz: float = 3.0, dur_s: float = 3.0, amp_mm: float = 20.0):
    t = np.arange(int(dur_s * fps)) / fps
    dist = 40.0 + amp_mm * np.sin(2 * np.pi * f_hz * t)
    vel = amp_mm * 2 * np.pi * f_hz * np.cos(2 * np.pi * f_hz * t)
    return t, dist, vel


@pytest.mark.parametrize("fps", [60.0, 100.0, 200.0])
def test_sine_distance_and_velocity_exact_in_passband(fps):
    t, dist, vel = _sine(fps)
    ap = aperture_signal(_two_markers(dist), fps)
    np.testing.assert_allclose(ap.t_s, t)
    np.testing.assert_allclose(ap.distance_mm, dist, atol=1e-9)  # mm
    inner = slice(int(0.3 * fps), -int(0.3 * fps))  # away from the filter's edges
    np.testing.assert_allclose(ap.filtered_mm[inner], dist[inner], atol=0.02)  # mm
    # 1 % of the 377 mm/s peak velocity
    np.testing.assert_allclose(ap.velocity_mm_s[inner], vel[inner], atol=0.01 * 377)
    assert ap.valid.all()
    assert ap.cutoff_hz == default_cutoff_hz(fps) == 20.0


def _phase_rad(t, x, f_hz):
    design = np.column_stack(
        [np.sin(2 * np.pi * f_hz * t), np.cos(2 * np.pi * f_hz * t), np.ones_like(t)]
    )
    (a, b, _), *_ = np.linalg.lstsq(design, x, rcond=None)
    return np.arctan2(b, a)


def test_filter_is_zero_phase():
    """Convention: a causal filter would delay the signal; ours must not."""
    from scipy.signal import butter, sosfilt

    fps, f_hz = 100.0, 4.0
    t, dist, _ = _sine(fps, f_hz=f_hz, dur_s=4.0)
    ap = aperture_signal(_two_markers(dist), fps)
    inner = slice(50, -50)
    delay_s = (
        _phase_rad(t[inner], dist[inner], f_hz) - _phase_rad(t[inner], ap.filtered_mm[inner], f_hz)
    ) / (2 * np.pi * f_hz)
    assert abs(delay_s) < 1e-4  # s
    # The check is sensitive: the same filter run causally lags by several ms.
    causal = sosfilt(butter(4, 20.0, fs=fps, output="sos"), dist)
    lag_s = (
        _phase_rad(t[inner], dist[inner], f_hz) - _phase_rad(t[inner], causal[inner], f_hz)
    ) / (2 * np.pi * f_hz)
    assert lag_s > 5e-3  # s


def test_rigid_motion_of_the_hand_leaves_the_aperture_unchanged():
    fps = 100.0
    _, dist, _ = _sine(fps)
    pos = _two_markers(dist)
    moved = pos + np.linspace(0, 80, len(dist))[:, None, None] * np.array([1.0, 0.5, -0.2])
    a, b = aperture_signal(pos, fps), aperture_signal(moved, fps)
    np.testing.assert_allclose(b.distance_mm, a.distance_mm, atol=1e-9)  # mm
    np.testing.assert_allclose(b.filtered_mm, a.filtered_mm, atol=1e-9)  # mm


def test_only_thumb_and_index_are_used():
    fps = 100.0
    _, dist, _ = _sine(fps)
    pos = _two_markers(dist)
    hand = np.concatenate([pos, np.full((len(dist), 1, 3), np.nan)], axis=1)
    np.testing.assert_allclose(
        aperture_signal(hand, fps).filtered_mm, aperture_signal(pos, fps).filtered_mm
    )


def test_gap_is_not_bridged():
    fps = 100.0
    _, dist, _ = _sine(fps)
    pos = _two_markers(dist)
    pos[120:160, 1] = np.nan  # index marker lost for 0.4 s
    ap = aperture_signal(pos, fps)
    assert np.isnan(ap.distance_mm[120:160]).all()
    assert np.isnan(ap.filtered_mm[120:160]).all()
    assert np.isnan(ap.velocity_mm_s[120:160]).all()
    assert not ap.valid[120:160].any()
    assert ap.runs() == [(0, 120), (160, len(dist))]
    # Each side filtered on its own: far from the gap edges it is the signal itself.
    np.testing.assert_allclose(ap.filtered_mm[40:100], dist[40:100], atol=0.05)  # mm


def test_filled_in_frames_short_kept_long_treated_as_missing():
    fps = 100.0
    _, dist, _ = _sine(fps)
    pos = _two_markers(dist)
    measured = np.ones((len(dist), 2), bool)
    measured[50:55, 0] = False  # 0.05 s filled in: kept for filtering, not valid
    measured[150:180, 1] = False  # 0.3 s filled in: a gap
    ap = aperture_signal(pos, fps, measured=measured)
    assert np.isfinite(ap.filtered_mm[50:55]).all()
    assert not ap.valid[50:55].any()
    assert np.isnan(ap.filtered_mm[150:180]).all()
    assert ap.valid[:50].all() and ap.valid[55:150].all()
    # A (T,) mask means the same as its (T, 2) form.
    ap1 = aperture_signal(pos, fps, measured=measured.all(axis=1))
    np.testing.assert_array_equal(ap1.valid, ap.valid)


def test_filled_in_stretch_merged_in_one_camera_kept_longer():
    """A closure whose images merged in one camera: 0.3 s filled in, the other camera saw
    both markers in every frame (only their depth interpolated): kept for filtering (never
    valid) up to max_merged_fill_s (here 0.5 s); one frame not merged makes it a gap again."""
    fps = 100.0
    _, dist, _ = _sine(fps)
    pos = _two_markers(dist)
    measured = np.ones((len(dist), 2), bool)
    measured[150:180] = False  # both markers filled in for 0.3 s
    merged = ~measured
    ap = aperture_signal(pos, fps, measured=measured, merged=merged, max_merged_fill_s=0.5)
    assert np.isfinite(ap.filtered_mm[150:180]).all()
    assert not ap.valid[150:180].any()
    np.testing.assert_allclose(ap.filtered_mm[150:180], dist[150:180], atol=0.05)  # mm
    # Longer than the limit (default 0.15 s: a closure), or one frame not merged: a gap.
    short = aperture_signal(pos, fps, measured=measured, merged=merged)
    assert np.isnan(short.filtered_mm[150:180]).all()
    holed = merged.copy()
    holed[165, 1] = False
    ap2 = aperture_signal(pos, fps, measured=measured, merged=holed, max_merged_fill_s=0.5)
    assert np.isnan(ap2.filtered_mm[150:180]).all()
    # One marker measured, the other merged-filled: the frame counts.
    measured2 = np.ones((len(dist), 2), bool)
    measured2[150:180, 1] = False
    sv2 = ~measured2
    ap3 = aperture_signal(pos, fps, measured=measured2, merged=sv2, max_merged_fill_s=0.5)
    assert np.isfinite(ap3.filtered_mm[150:180]).all()


def test_all_missing_gives_all_nan_without_crash():
    pos = np.full((50, 2, 3), np.nan)
    ap = aperture_signal(pos, 100.0)
    assert np.isnan(ap.filtered_mm).all() and not ap.valid.any()
    assert ap.runs() == []


@pytest.mark.parametrize(
    ("shape", "fps", "cutoff", "match"),
    [
        ((100, 3), 100.0, None, "shape"),
        ((100, 1, 3), 100.0, None, "shape"),
        ((100, 2, 2), 100.0, None, "shape"),
        ((100, 2, 3), 0.0, None, "fps"),
        ((100, 2, 3), 100.0, 50.0, "cutoff"),
        ((100, 2, 3), 100.0, -1.0, "cutoff"),
    ],
)
def test_bad_arguments_raise_value_error(shape, fps, cutoff, match):
    with pytest.raises(ValueError, match=match):
        aperture_signal(np.zeros(shape), fps, cutoff_hz=cutoff)


def test_bad_measured_shape_raises():
    with pytest.raises(ValueError, match="measured"):
        aperture_signal(np.zeros((10, 2, 3)), 100.0, measured=np.ones(9, bool))


def test_true_runs():
    assert true_runs(np.array([0, 1, 1, 0, 1], bool)) == [(1, 3), (4, 5)]
    assert true_runs(np.array([], bool)) == []
    assert true_runs(np.ones(3, bool)) == [(0, 3)]


@pytest.mark.parametrize("fps", [60.0, 100.0, 200.0])
def test_noise_estimate(fps):
    t, dist, _ = _sine(fps, dur_s=10.0)
    pos = _two_markers(dist)
    clean = aperture_signal(pos, fps)
    assert clean.noise_mm < 0.01  # mm
    rng = np.random.default_rng(5)
    noisy = aperture_signal(pos + rng.normal(0, 0.2, pos.shape), fps)
    # Distance noise of 0.2 mm per coordinate on each marker: 0.2 * sqrt(2) mm.
    assert noisy.noise_mm == pytest.approx(0.2 * np.sqrt(2), rel=0.15)
    still = aperture_signal(
        _two_markers(np.full_like(t, 40.0)) + rng.normal(0, 0.2, pos.shape), fps
    )
    assert np.nanstd(still.velocity_mm_s) == pytest.approx(still.velocity_noise_mm_s, rel=0.15)

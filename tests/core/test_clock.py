"""The time model (core.clock) on projected ground truth: offset, drift, lost frames,
different frame rates, rolling shutter; the right markers at the left instants."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from core.camera import ImageSize, StereoRig
from core.clock import ClockModel, corrected_times, synchronise
from core.errors import DetectionError
from core.simulation.kinematics import TappingScenario, simulate_tapping
from core.simulation.rig import default_rig
from core.simulation.timing import CameraTiming, camera_clock, rolling_shutter_times
from core.timing import FrameTimes, uniform_times

SIZE = ImageSize(1920, 1080)
DURATION_S = 6.0


def _detections(rig, model, clock, camera, *, noise_px=0.02, seed=0):
    """Per-frame projected markers of one camera (px), with rolling shutter if its rig camera has one."""
    cam = rig.left if camera == "left" else rig.right
    rng = np.random.default_rng(seed)
    out = []
    for t in clock.true_s:
        if cam.readout_ms > 0:
            tm = rolling_shutter_times(cam, model.positions_mm, t, cam.readout_ms * 1e-3, 2)
            pos = model.positions_mm(tm)[[0, 1], [0, 1]]
        else:
            pos = model.positions_mm(np.array([t]))[0]
        px = cam.project(pos)
        out.append(px + rng.normal(0, noise_px, px.shape))
    return out


def _setup(left=CameraTiming(), right=CameraTiming(), *, fps=60.0, rig=None, seed=1):
    truth = simulate_tapping(TappingScenario(duration_s=DURATION_S, fps=fps), seed=seed)
    rig = default_rig(image_size=SIZE) if rig is None else rig
    rig = StereoRig(
        replace(rig.left, readout_ms=left.readout_ms),
        replace(rig.right, readout_ms=right.readout_ms),
    )
    clocks = {
        c: camera_clock(t, fps=fps, duration_s=DURATION_S, rng=np.random.default_rng(i))
        for i, (c, t) in enumerate((("left", left), ("right", right)))
    }
    det = {c: _detections(rig, truth.model, clocks[c], c, seed=i) for i, c in enumerate(clocks)}
    norm = {
        c: [cam.undistort_points(p) for p in det[c]]
        for c, cam in (("left", rig.left), ("right", rig.right))
    }
    times = {}
    for c, t in (("left", left), ("right", right)):
        ck = clocks[c]
        times[c] = (
            FrameTimes(ck.stamp_s, ck.fps, "container")
            if t.vfr
            else uniform_times(len(ck.stamp_s), ck.fps)
        )
    return truth, rig, clocks, det, norm, times


def _run(rig, det, norm, times, **kw):
    return synchronise(
        rig,
        det["left"],
        det["right"],
        norm["left"],
        norm["right"],
        left_times=times["left"],
        right_times=times["right"],
        max_step_px=0.05 * SIZE.width,
        **kw,
    )


def _right_at_left_error_px(truth, rig, clocks, result) -> np.ndarray:
    """Distance (px) of each interpolated right point to the true projection at its left instant."""
    t_true = clocks["left"].true_s
    err = []
    for i, pts in enumerate(result.right_px):
        if len(pts) == 0:
            continue
        want = rig.right.project(truth.model.positions_mm(np.array([t_true[i]]))[0])
        d = np.linalg.norm(pts[:, None, :] - want[None], axis=2).min(axis=1)
        err.extend(d)
    return np.array(err)


def test_offset_and_drift_are_found_and_right_points_are_at_the_left_instants():
    right = CameraTiming(start_s=0.237, drift_ppm=300.0)
    truth, rig, clocks, det, norm, times = _setup(right=right)
    res = _run(rig, det, norm, times)
    assert res.pairing_offset is None  # interpolated, not whole frames
    assert abs(res.model.offset_s - 0.237) < 0.0002  # s
    assert abs(res.model.drift_ppm - 300.0) < 30  # ppm
    assert res.sync["offset_frames"] == pytest.approx(0.237 * 60 / 1.0003, abs=0.02)  # frames
    err = _right_at_left_error_px(truth, rig, clocks, res)
    assert np.sqrt(np.mean(err**2)) < 0.1  # px (0.02 px noise + cubic interpolation at 60 fps)
    assert res.sync["epipolar_px_after"] < 0.2 * res.sync["epipolar_px_before"]
    # Nothing is extrapolated: left frames before the right camera started get no right points.
    first = int(np.argmax([len(p) > 0 for p in res.right_px]))
    assert clocks["left"].true_s[first] >= clocks["right"].true_s[0] - 1e-9


def test_convention_a_late_right_camera_has_a_positive_offset():
    """Swapping which camera starts late must flip the sign (INTERFACES.md: right j = left j + K)."""
    _, rig, _, det, norm, times = _setup(right=CameraTiming(start_s=0.1))
    late_right = _run(rig, det, norm, times).sync["offset_frames"]
    _, rig, _, det, norm, times = _setup(right=CameraTiming(start_s=-0.1))
    early_right = _run(rig, det, norm, times).sync["offset_frames"]
    assert late_right == pytest.approx(6.0, abs=0.02) and early_right == pytest.approx(
        -6.0, abs=0.02
    )


@pytest.mark.parametrize(
    ("camera", "drops"),
    [("right", (100, 181, 290)), ("left", (150,)), ("right", (200, 200)), ("right", (200, 212))],
)
def test_hidden_lost_frames_are_found_within_one_frame(camera, drops):
    timing = CameraTiming(drop_after=drops)
    kw = {camera: timing}
    truth, rig, clocks, det, norm, times = _setup(**kw)
    res = _run(rig, det, norm, times)
    found = res.sync[f"dropped_frames_{camera}"]
    assert len(found) == len(drops)
    assert np.all(np.abs(np.array(found) - np.array(drops)) <= 1)  # frames
    other = "left" if camera == "right" else "right"
    assert res.sync[f"dropped_frames_{other}"] == []
    # The left frame times have the lost frames put back.
    np.testing.assert_allclose(res.left_time_s, clocks["left"].true_s, atol=1.01 / 60)
    err = _right_at_left_error_px(truth, rig, clocks, res)
    # A loss placed one frame off (motion along the epipolar lines there) misplaces the
    # point of one frame; all others are at the left instant.
    assert np.percentile(err, 99) < 0.1  # px
    with_right = np.mean([len(p) > 0 for p in res.right_px])
    assert with_right >= 0.98


def test_variable_frame_rate_timestamps_with_jitter_and_gaps():
    left = CameraTiming(jitter_s=0.0005, vfr=True)
    right = CameraTiming(start_s=0.05, drift_ppm=-200, jitter_s=0.0005, vfr=True, drop_after=(90,))
    truth, rig, clocks, det, norm, times = _setup(left=left, right=right)
    res = _run(rig, det, norm, times)
    assert res.sync["dropped_frames_right"] == [90]  # from the timestamps
    assert abs(res.model.offset_s - 0.05) < 0.0002  # s
    err = _right_at_left_error_px(truth, rig, clocks, res)
    assert np.sqrt(np.mean(err**2)) < 0.1  # px


def test_jittered_timestamps_lose_no_frames_to_jitter():
    """Capture jitter of 15 % of a period (2.5 ms at 60 fps) makes late-then-early pairs
    whose first interval is 1.5 periods: taken for lost frames (5 left, 3 right), the
    right tracks were cut there and 1.4 % of the left frames had no right points."""
    left = CameraTiming(jitter_s=0.0025, vfr=True)
    right = CameraTiming(start_s=0.05, drift_ppm=-200, jitter_s=0.0025, vfr=True, drop_after=(90,))
    truth, rig, clocks, det, norm, times = _setup(left=left, right=right)
    assert np.sum(np.diff(times["left"].t_s) * 60 >= 1.5) >= 3  # the jitter's long intervals
    res = _run(rig, det, norm, times)
    assert res.sync["dropped_frames_left"] == []
    assert res.sync["dropped_frames_right"] == [90]
    # The right camera starts 3 frames late and loses one: no right points there only.
    assert np.mean([len(p) > 0 for p in res.right_px]) >= 0.985
    err = _right_at_left_error_px(truth, rig, clocks, res)
    assert np.sqrt(np.mean(err**2)) < 0.1  # px


def test_different_frame_rates_are_measured_at_the_left_instants():
    truth, rig, clocks, det, norm, times = _setup(
        right=CameraTiming(fps=60.0, start_s=0.04), fps=120.0
    )
    res = _run(rig, det, norm, times)
    assert abs(res.model.offset_s - 0.04) < 0.0002  # s
    assert len(res.right_px) == len(det["left"])
    err = _right_at_left_error_px(truth, rig, clocks, res)
    assert np.sqrt(np.mean(err**2)) < 0.1  # px


def test_rolling_shutter_instants_are_compensated():
    base = default_rig(image_size=SIZE)
    truth, rig, clocks, det, norm, times = _setup(
        left=CameraTiming(readout_ms=15), right=CameraTiming(readout_ms=15), rig=base
    )
    res = _run(rig, det, norm, times, offset_frames=0.0)
    err = _right_at_left_error_px(truth, rig, clocks, res)
    assert np.sqrt(np.mean(err**2)) < 0.1  # px
    assert res.sync["readout_ms"] == [15.0, 15.0]


def test_rolling_shutter_offset_is_estimated_on_rows_apart():
    """Markers on different rows in the two cameras (the right camera pitched 6°), 15 ms
    readout, offset and drift estimated: the left markers are compared at their frame's
    instant, so their rows' delays do not bias the offset."""
    base = default_rig(image_size=SIZE)
    a = np.deg2rad(6.0)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    pitched = StereoRig(
        base.left,
        replace(
            base.right,
            R_cam_from_world=rx @ base.right.R_cam_from_world,
            t_cam_from_world_mm=rx @ base.right.t_cam_from_world_mm,
        ),
    )
    truth, rig, clocks, det, norm, times = _setup(
        left=CameraTiming(readout_ms=15),
        right=CameraTiming(readout_ms=15, start_s=0.02),
        rig=pitched,
    )
    rows = [np.concatenate(det[c])[:, 1].mean() for c in ("left", "right")]
    assert abs(rows[0] - rows[1]) > 100  # px: the two cameras read the markers at other times
    res = _run(rig, det, norm, times)
    assert abs(res.model.offset_s - 0.02) < 0.0002  # s
    assert abs(res.model.drift_ppm) < 30  # ppm
    err = _right_at_left_error_px(truth, rig, clocks, res)
    assert np.sqrt(np.mean(err**2)) < 0.1  # px


def test_a_lab_rig_pairs_whole_frames_as_before():
    _, rig, _, det, norm, times = _setup(right=CameraTiming(start_s=3 / 60))
    res = _run(rig, det, norm, times)
    assert res.pairing_offset == 3
    assert (
        res.right_px is det["right"]
        or all(a is b for a, b in zip(res.right_px, det["right"], strict=False))
        or res.pairing_offset == 3
    )
    assert res.sync["drift_ppm"] == pytest.approx(0, abs=30)
    given = _run(rig, det, norm, times, offset_frames=3)
    assert given.pairing_offset == 3 and given.sync["method"] == "given"


def test_two_unrelated_recordings_are_refused():
    _, rig, _, det, norm, times = _setup(seed=1)
    _, _, _, det2, norm2, times2 = _setup(seed=7)
    with pytest.raises(DetectionError, match="same test"):
        synchronise(
            rig,
            det["left"],
            det2["right"],
            norm["left"],
            norm2["right"],
            left_times=times["left"],
            right_times=times2["right"],
            max_step_px=0.05 * SIZE.width,
        )


def test_clock_model_maps_both_ways():
    m = ClockModel(0.2, 500.0)
    t = np.linspace(0, 10, 7)
    np.testing.assert_allclose(m.left_to_right(m.right_to_left(t)), t, atol=1e-12)
    np.testing.assert_allclose(
        corrected_times(uniform_times(5, 10.0), [1]), [0, 0.1, 0.3, 0.4, 0.5]
    )


def _nearest_epipolar_reference(rig, l_pts, right, rows):
    """The former per-candidate formulation: every pair's lines computed anew, minimum.at."""
    from core.sync import _segment_indices

    r_pts, r_counts = right
    E = rig.essential_matrix
    starts = np.concatenate([[0], np.cumsum(r_counts)]).astype(np.intp)
    idx, owner = _segment_indices(starts[rows], r_counts[rows])
    out = np.full(len(l_pts), np.inf)
    if len(idx) == 0:
        return out
    lp = np.column_stack([l_pts[owner], np.ones(len(owner))])
    rp = np.column_stack([r_pts[idx], np.ones(len(idx))])
    line_r, line_l = lp @ E.T, rp @ E
    alg = np.abs(np.sum(rp * line_r, axis=1))
    f_r = 0.5 * (rig.right.K[0, 0] + rig.right.K[1, 1])
    f_l = 0.5 * (rig.left.K[0, 0] + rig.left.K[1, 1])
    d_r = alg / np.linalg.norm(line_r[:, :2], axis=1) * f_r
    d_l = alg / np.linalg.norm(line_l[:, :2], axis=1) * f_l
    with np.errstate(invalid="ignore"):
        np.minimum.at(out, owner, np.sqrt(0.5 * (d_l**2 + d_r**2)))
    return out


def test_nearest_epipolar_px_all_candidates_at_once_is_the_per_candidate_loop() -> None:
    # The time model's costs compare these distances: all candidates in one pass (each
    # point's epipolar line once) must give the former loop's values bit for bit, NaN
    # (a lost right point) and inf (no partner) included.
    from core.clock import _focal, _nearest_epipolar_px

    rig = default_rig()
    assert _focal(rig.right) == 0.5 * (rig.right.K[0, 0] + rig.right.K[1, 1])
    rng = np.random.default_rng(1)
    for trial in range(60):
        n_l, n_r, n_f, n_c = (int(v) for v in rng.integers([0, 0, 1, 1], [60, 50, 20, 8]))
        l_pts = rng.normal(0, 0.2, (n_l, 2))
        r_counts = rng.multinomial(n_r, np.ones(n_f) / n_f).astype(np.intp)
        r_pts = rng.normal(0, 0.2, (n_r, 2))
        if n_r and trial % 3 == 0:
            r_pts[rng.integers(0, n_r)] = np.nan
        rows = rng.integers(0, n_f, (n_c, n_l)).astype(np.intp)
        want = np.array(
            [_nearest_epipolar_reference(rig, l_pts, (r_pts, r_counts), r) for r in rows]
        ).reshape(n_c, n_l)
        got = _nearest_epipolar_px(rig, l_pts, (r_pts, r_counts), rows)
        assert np.array_equal(got, want, equal_nan=True)
        assert np.array_equal(
            _nearest_epipolar_px(rig, l_pts, (r_pts, r_counts), rows[0]), want[0], equal_nan=True
        )


@pytest.mark.parametrize("readout_ms", [0.0, 12.0])
def test_points_at_times_compiled_gives_the_numpy_formulation_bit_for_bit(readout_ms) -> None:
    # The right markers at the left instants (and every time-model candidate) come from
    # core._geometry.points_at_times: the former numpy formulation's bits
    # (tests/core/geometry_reference.py), at frame times (exact) and between them, across
    # gaps of lost frames, before the first frame and after the last, with tracks of 2, 3
    # and 4+ samples, NaN detections and frames without any.
    from geometry_reference import points_at_times_reference

    from core.clock import points_at_times, track_table
    from core.sync import link_points

    cam = replace(default_rig(image_size=SIZE).right, readout_ms=readout_ms)
    rng = np.random.default_rng(int(readout_ms))
    for trial in range(40):
        n = int(rng.integers(1, 40))
        frames = []
        for _ in range(n):
            k = int(rng.integers(0, 5))
            frames.append(rng.uniform([0, 0], [SIZE.width, SIZE.height], (k, 2)))
        if trial % 4 == 0 and sum(len(f) for f in frames):
            f = next(f for f in frames if len(f))
            f[0] = np.nan
        interval = 1 / 60
        frame_t = np.arange(n) * interval
        if n > 3 and trial % 2:
            frame_t[n // 2 :] += interval  # a lost frame
        links = link_points(frames, max_step_px=2 * SIZE.width)
        table = track_table(frames, frame_t, camera=cam, links=links, interval_s=interval)
        t = np.concatenate(
            [
                rng.uniform(-2 * interval, frame_t[-1] + 2 * interval, 60),
                frame_t[rng.integers(0, n, 10)],
                frame_t[rng.integers(0, n, 5)] + 1e-10,
                [np.nan] if trial % 5 == 0 else [],
            ]
        )
        want = points_at_times_reference(table, t)
        got = points_at_times(table, t)
        assert np.array_equal(got[1], want[1])
        assert got[0].shape == want[0].shape
        assert np.array_equal(got[0], want[0])
        assert got[1].dtype == want[1].dtype
    assert len(want[0])  # the last trial interpolated something


def test_an_offset_beyond_the_search_is_doubted_aloud(monkeypatch):
    """Cameras started 0.55 s apart, beyond the ±0.5 s searched: the best offset inside is a
    tap period off (0.21 s), the views still disagree by about 2 px after it, and the
    analysis says so instead of measuring in silence; within the search, nothing is said."""
    import sys

    monkeypatch.setattr(sys.modules[__name__], "DURATION_S", 5.0)  # a 5-s recording
    _, rig, _, det, norm, times = _setup(right=CameraTiming(start_s=0.55), seed=3)
    res = _run(rig, det, norm, times)
    assert res.sync["epipolar_px_after"] > 1.0  # px
    assert any("still disagree" in w and "0.5 s apart" in w for w in res.warnings)
    _, rig, _, det, norm, times = _setup(right=CameraTiming(start_s=0.237), seed=3)
    res = _run(rig, det, norm, times)
    assert res.sync["epipolar_px_after"] < 0.2  # px
    assert not any("still disagree" in w for w in res.warnings)

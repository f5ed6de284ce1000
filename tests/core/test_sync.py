"""Frame offset from the marker motion: exact integer offsets, static clutter, no motion."""

from __future__ import annotations

import numpy as np
import pytest
from rigs import verging_rig

from core.camera import StereoRig
from core.simulation.kinematics import TappingScenario, simulate_tapping
from core.sync import estimate_offset, given_offset


def make_rig() -> StereoRig:
    return verging_rig()


RIG = make_rig()
TRUTH = simulate_tapping(TappingScenario(duration_s=3.0, fps=100.0, hand_marker=True), seed=3)


def views(offset: int, *, noise_px: float = 0.15, seed: int = 0, clutter: bool = True):
    """Per-frame undistorted detections; right frame j shows left frame j + offset."""
    rng = np.random.default_rng(seed)
    pos = TRUTH.positions_mm  # (T, 3 markers, 3)
    n = pos.shape[0]
    static = np.array([[60.0, 40.0, 520.0], [-70.0, -20.0, 480.0]])  # stereo-consistent reflections
    left, right = [], []
    for i in range(n):
        pl = RIG.left.project(np.vstack([pos[i], static]))
        left.append(pl + rng.normal(0, noise_px, pl.shape))
    for j in range(n):
        k = j + offset
        pts = pos[k] if 0 <= k < n else np.zeros((0, 3))
        pr = RIG.right.project(np.vstack([pts, static]))
        right.append(pr + rng.normal(0, noise_px, pr.shape))
    if clutter:  # flickering random spots
        for arr in (left, right):
            for i in range(0, n, 7):
                arr[i] = np.vstack([arr[i], rng.uniform([0, 0], [1280, 1024], (2, 2))])
    ln = [RIG.left.undistort_points(p) for p in left]
    rn = [RIG.right.undistort_points(p) for p in right]
    return ln, rn


@pytest.mark.parametrize("offset", [-10, -1, 0, 3, 10])
def test_integer_offsets_are_found_exactly(offset: int) -> None:
    ln, rn = views(offset, seed=offset + 20)
    est = estimate_offset(RIG, ln, rn, max_offset_frames=30)
    assert est.offset_frames == offset
    assert abs(est.offset_subframe - offset) <= 0.5  # frames
    assert est.confidence > 0.5
    assert est.method == "auto"
    doc = est.to_result()
    assert doc["offset_frames"] == float(offset) and doc["method"] == "auto"


def test_convention_sign() -> None:
    """Right frame j = left frame j + K: shifting the right list by one frame changes K by one."""
    ln, rn = views(4, clutter=False)
    assert estimate_offset(RIG, ln, rn[1:], max_offset_frames=12).offset_frames == 5
    assert estimate_offset(RIG, ln[1:], rn, max_offset_frames=12).offset_frames == 3


def test_no_motion_gives_zero_confidence() -> None:
    static = np.array([[0.0, 0.0, 500.0], [20.0, 30.0, 510.0]])
    ln = [RIG.left.undistort_points(RIG.left.project(static))] * 200
    rn = [RIG.right.undistort_points(RIG.right.project(static))] * 200
    est = estimate_offset(RIG, ln, rn, max_offset_frames=10)
    assert est.confidence < 0.05


def test_given_offset_and_errors() -> None:
    g = given_offset(-3)
    assert g.offset_frames == -3 and g.method == "given" and g.to_result()["method"] == "given"
    with pytest.raises(ValueError):
        given_offset(float("nan"))
    with pytest.raises(ValueError):
        estimate_offset(RIG, [], [], max_offset_frames=-1)
    est = estimate_offset(RIG, [], [], max_offset_frames=3)
    assert est.confidence == 0.0


def test_subframe_offset_is_refined_and_used() -> None:
    from core.sync import refine_offset

    k_true = 2.4  # frames: cameras not triggered together
    rng = np.random.default_rng(9)
    n = TRUTH.positions_mm.shape[0]
    right_times = (np.arange(n) + k_true) / TRUTH.fps
    right_pos = TRUTH.model.positions_mm(right_times)  # (T, 3, 3) at the right exposures
    left_px = [
        RIG.left.project(TRUTH.positions_mm[i]) + rng.normal(0, 0.1, (3, 2)) for i in range(n)
    ]
    right_px = [RIG.right.project(right_pos[j]) + rng.normal(0, 0.1, (3, 2)) for j in range(n)]
    ln = [RIG.left.undistort_points(p) for p in left_px]
    rn = [RIG.right.undistort_points(p) for p in right_px]
    est = estimate_offset(RIG, ln, rn, max_offset_frames=12)
    assert est.offset_frames == 2 and not est.fractional
    ref = refine_offset(RIG, ln, right_px, est, max_step_px=60.0)
    assert abs(ref.offset_subframe - k_true) < 0.05  # frames
    assert ref.fractional and ref.used_offset == pytest.approx(ref.offset_subframe)
    assert ref.to_result()["offset_frames"] == pytest.approx(k_true, abs=0.05)


def test_points_at_interpolates_along_2d_tracks() -> None:
    from core.sync import link_points, points_at, right_points_for_left_frames

    t = np.arange(20, dtype=float)
    a = np.column_stack([100 + 3 * t + 0.1 * t**2, 200 - 2 * t])  # a moving blob (cubic-exact)
    b = np.tile([[400.0, 300.0]], (20, 1))  # a static one
    frames = [np.vstack([a[i], b[i]]) if i % 2 else np.vstack([b[i], a[i]]) for i in range(20)]
    links = link_points(frames, max_step_px=20.0)
    assert links[0].tolist() == [0, 1] or links[0].tolist() == [1, 0]
    got = points_at(frames, links, 7.25)
    tt = 7.25
    want_a = [100 + 3 * tt + 0.1 * tt**2, 200 - 2 * tt]
    assert min(np.linalg.norm(got - want_a, axis=1)) < 1e-9  # px: exact for a polynomial path
    assert min(np.linalg.norm(got - [400.0, 300.0], axis=1)) < 1e-9
    assert len(points_at(frames, links, -0.5)) == 0 and len(points_at(frames, links, 19.5)) == 0
    paired = right_points_for_left_frames(frames, 20, 0.5, max_step_px=20.0)
    assert len(paired) == 20 and len(paired[0]) == 0  # right time -0.5 does not exist
    np.testing.assert_allclose(sorted(paired[3][:, 0]), sorted([100 + 3 * 2.5 + 0.1 * 6.25, 400.0]))


def test_given_fractional_offset() -> None:
    g = given_offset(-3.3)
    assert g.fractional and g.used_offset == -3.3 and g.offset_frames == -3
    assert given_offset(4.1).used_offset == 4.0  # within 0.2 frame of a whole frame: whole


def test_batched_interpolation_matches_points_at() -> None:
    """_points_at_times (all times at once) gives what points_at gives time by time."""
    from core.sync import _points_at_times, _track_table, link_points, points_at

    rng = np.random.default_rng(5)
    n = 30
    base = rng.uniform(100, 900, (6, 2))
    vel = rng.normal(0, 3, (6, 2))
    frames = []
    for j in range(n):
        alive = rng.random(6) > 0.25  # markers drop out: short tracks, unlinked detections
        pts = base[alive] + j * vel[alive] + rng.normal(0, 0.3, (int(alive.sum()), 2))
        frames.append(pts[rng.permutation(len(pts))])
    links = link_points(frames, max_step_px=15.0)
    times = np.concatenate([rng.uniform(-2, n + 1, 200), [0.0, 3.0, n - 1.0, n - 1.5, n - 0.5]])
    got, counts = _points_at_times(_track_table(frames, links), times)
    assert counts.sum() == len(got)
    parts = np.split(got, np.cumsum(counts)[:-1])
    n_cubic = 0
    for t, part in zip(times, parts, strict=True):
        want = points_at(frames, links, float(t))
        assert part.shape == want.shape
        np.testing.assert_allclose(part, want, rtol=0, atol=1e-9)  # px
        n_cubic += len(want)
    assert n_cubic > 300  # the case exercises interpolation, not only empty results


def test_offset_costs_match_a_per_detection_loop() -> None:
    """The batched costs of estimate_offset equal a plain loop over detections."""
    ln, rn = views(2, seed=7)
    ln, rn = ln[:40], rn[:40]
    est = estimate_offset(RIG, ln, rn, max_offset_frames=3, gate_px=3.0)
    E = RIG.essential_matrix
    f = 0.5 * (RIG.left.K[0, 0] + RIG.left.K[1, 1]), 0.5 * (RIG.right.K[0, 0] + RIG.right.K[1, 1])
    for off, got in zip(est.offsets, est.costs, strict=True):
        costs = []
        for i in range(40):
            if not 0 <= i - off < 40:
                continue
            for p in ln[i][:12]:
                best = np.inf
                for q in rn[i - off][:12]:
                    hl, hr = np.append(p, 1.0), np.append(q, 1.0)
                    lr, ll = E @ hl, E.T @ hr
                    alg = abs(hr @ lr)
                    d = np.hypot(alg / np.hypot(*lr[:2]) * f[1], alg / np.hypot(*ll[:2]) * f[0])
                    best = min(best, d / np.sqrt(2.0))
                costs.append(min(best, 3.0) ** 2 / 9.0)
        assert got == pytest.approx(np.mean(costs), abs=1e-12)


def _link_points_frame_by_frame(frames: list[np.ndarray], max_step_px: float) -> list[np.ndarray]:
    """link_points written as one Hungarian assignment per frame pair, in frame order."""
    from scipy.optimize import linear_sum_assignment

    nxt = [np.full(len(f), -1, dtype=np.intp) for f in frames]
    prev_of = np.full(len(frames[0]), -1, dtype=np.intp)
    for j in range(len(frames) - 1):
        a, b = frames[j], frames[j + 1]
        new_prev = np.full(len(b), -1, dtype=np.intp)
        if len(a) and len(b):
            pred = a.copy()
            has = prev_of >= 0
            pred[has] = 2 * a[has] - frames[j - 1][prev_of[has]]
            d = np.linalg.norm(pred[:, None, :] - b[None, :, :], axis=2)
            cost = np.where(d <= max_step_px, d, 1e9)
            rows, cols = linear_sum_assignment(cost)
            ok = cost[rows, cols] < 1e9
            nxt[j][rows[ok]] = cols[ok]
            new_prev[cols[ok]] = rows[ok]
        prev_of = new_prev
    return nxt


@pytest.mark.parametrize("max_step_px", [8.0, 25.0])
def test_link_points_matches_frame_by_frame_assignment(max_step_px: float) -> None:
    """Crowded, crossing, appearing and vanishing tracks: the same links as frame by frame."""
    from core.sync import link_points

    rng = np.random.default_rng(11)
    base = rng.uniform(0, 120, (8, 2))
    vel = rng.normal(0, 5, (8, 2))
    frames = []
    for j in range(80):
        alive = rng.random(8) > 0.2
        pts = base[alive] + j * vel[alive] + rng.normal(0, 2, (int(alive.sum()), 2))
        frames.append(pts[rng.permutation(len(pts))])
    frames[10] = np.zeros((0, 2))
    want = _link_points_frame_by_frame(frames, max_step_px)
    got = link_points(frames, max_step_px=max_step_px)
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    assert sum(int((w >= 0).sum()) for w in want) > 200  # most detections are linked
    assert link_points([], max_step_px=5.0) == []
    assert link_points([np.ones((2, 2))], max_step_px=5.0)[0].tolist() == [-1, -1]

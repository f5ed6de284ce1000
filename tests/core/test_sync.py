"""Frame offset from the marker motion: exact integer offsets, static clutter, no motion."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from rigs import verging_rig

from core.camera import StereoRig
from core.simulation.kinematics import TappingScenario, simulate_tapping
from core.sync import (
    MAX_POINTS_PER_FRAME,
    _epipolar_costs,
    _flatten,
    _homogeneous,
    _ranks,
    _segment_indices,
    _select_frames,
    estimate_offset,
    given_offset,
)


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


# -- the numpy formulations the compiled loops replaced, kept to compare with ----------

FloatArray = NDArray[np.float64]


def _epipolar_costs_reference(
    E: FloatArray,
    left_pts: FloatArray,
    right: tuple[FloatArray, NDArray[np.intp]],
    right_row: NDArray[np.intp],
    f_left: float,
    f_right: float,
    gate_px: float,
) -> tuple[FloatArray, NDArray[np.intp]]:
    """The cost of estimate_offset as numpy passes over padded tables (before 2026-11-28)."""
    r_pts, r_counts = right
    n_rows = len(r_counts)
    q = max(int(r_counts.max()) if n_rows else 0, 1)
    # Right x, y and epipolar-line norm padded to (Q, R + 1), NaN where missing;
    # column R is the all-NaN partner of detections without a partner frame.
    rows = np.repeat(np.arange(n_rows), r_counts)
    cols = _ranks(r_counts)
    lines_l = _homogeneous(r_pts) @ E  # (N, 3) epipolar lines in the left image
    table = np.full((3, q, n_rows + 1), np.nan)
    table[0, cols, rows] = r_pts[:, 0]
    table[1, cols, rows] = r_pts[:, 1]
    table[2, cols, rows] = np.linalg.norm(lines_l[:, :2], axis=1)
    valid = right_row >= 0
    idx = np.where(valid, right_row, n_rows)
    lines_r = _homogeneous(left_pts) @ E.T  # (L, 3) epipolar lines in the right image
    la, lb, lc = lines_r.T.copy()
    norm_r = np.linalg.norm(lines_r[:, :2], axis=1)
    # s = d_l**2 + d_r**2 of every left detection and candidate, least over the
    # right detections of the paired frame; sqrt(0.5 * s) is non-decreasing in
    # s, so the nearest right detection is the one of least s (NaN, from
    # missing ones, counts as infinitely far). Chunks of candidates keep the
    # temporaries in cache.
    s_min = np.full(idx.shape, np.nan)
    chunk = max(1, 32768 // max(idx.shape[1], 1))
    with np.errstate(divide="ignore", invalid="ignore"):
        for c0 in range(0, idx.shape[0], chunk):
            rows_c = idx[c0 : c0 + chunk]
            s_c = s_min[c0 : c0 + chunk]
            for k in range(q):
                x, y, norm_l = table[0, k][rows_c], table[1, k][rows_c], table[2, k][rows_c]
                # The algebraic error line . (x, y, 1), summed in the order numpy's
                # einsum sums a 3-term dot product; its sign does not matter.
                alg = la * x
                alg += lc
                y *= lb
                alg += y
                d_r = alg / norm_r
                d_r *= f_right
                d_l = np.divide(alg, norm_l, out=norm_l)
                d_l *= f_left
                np.square(d_r, out=d_r)
                np.square(d_l, out=d_l)
                d_l += d_r
                np.fmin(s_c, d_l, out=s_c)
    d_min = np.sqrt(0.5 * s_min)
    d_min = np.where(np.isfinite(d_min), d_min, np.inf)
    cost = np.minimum(d_min, gate_px) ** 2 / gate_px**2  # (C, L)
    n_points = valid.sum(axis=1)
    costs = np.full(len(right_row), np.nan)
    for c in np.flatnonzero(n_points):
        costs[c] = cost[c][valid[c]].mean()
    return costs, n_points


def _link_flat_reference(
    pts: FloatArray,
    counts: NDArray[np.intp],
    starts: NDArray[np.intp],
    frame_of: NDArray[np.intp],
    nxt: NDArray[np.intp],
    max_step_px: float,
) -> None:
    """link_points as rounds over all frame pairs at once (before 2026-11-28)."""
    from scipy.optimize import linear_sum_assignment

    n = len(counts)
    # Every (detection of j, detection of j + 1) pair, frame pair by frame pair.
    n_pairs = counts[:-1] * counts[1:]
    pair_start = np.cumsum(n_pairs) - n_pairs
    fp = np.repeat(np.arange(n - 1), n_pairs)
    r = _ranks(n_pairs)
    width = counts[1:][fp]
    with np.errstate(divide="ignore", invalid="ignore"):
        ia = starts[fp] + r // np.maximum(width, 1)
        ib = starts[fp + 1] + r % np.maximum(width, 1)
    prv = np.full(len(pts), -1, dtype=np.intp)
    fast_ok = max_step_px < 1e6  # gated costs far below the 1e9 of excluded pairs
    todo = np.flatnonzero(n_pairs)
    first = True
    while todo.size:
        sel, sel_fp = _segment_indices(pair_start[todo], n_pairs[todo])
        a, b = ia[sel], ib[sel]
        pred = pts[a].copy()
        pa = prv[a]
        has = pa >= 0
        pred[has] = 2 * pts[a[has]] - pts[pa[has]]
        d = np.linalg.norm(pred - pts[b], axis=1)
        valid = d <= max_step_px
        # Frame pairs where a detection has more than one gated candidate.
        many = (np.bincount(a[valid], minlength=len(pts)) > 1) | (
            np.bincount(b[valid], minlength=len(pts)) > 1
        )
        clash = np.zeros(len(todo), dtype=bool)
        clash[sel_fp[many[a] | many[b]]] = True
        if not fast_ok:
            clash[:] = True
        # In the first round the predecessors are not known yet: a clashing
        # pair whose first frame may have predecessors only gets a guess
        # (mutual nearest candidates) and is solved in the next round.
        guess = clash & first & (todo > 0) & (counts[np.maximum(todo - 1, 0)] > 0)
        nxt[np.flatnonzero(np.isin(frame_of, todo))] = -1
        simple = ~clash[sel_fp] & valid
        nxt[a[simple]] = b[simple]
        if np.any(guess):
            cand = np.flatnonzero(guess[sel_fp] & valid)
            by_a = cand[np.lexsort((d[cand], a[cand]))]
            by_b = cand[np.lexsort((d[cand], b[cand]))]
            best_a = by_a[np.r_[True, a[by_a][1:] != a[by_a][:-1]]]
            best_b = by_b[np.r_[True, b[by_b][1:] != b[by_b][:-1]]]
            mutual = np.intersect1d(best_a, best_b)
            nxt[a[mutual]] = b[mutual]
        seg_start = np.cumsum(n_pairs[todo]) - n_pairs[todo]
        for k in np.flatnonzero(clash & ~guess):
            j = todo[k]
            s0 = seg_start[k]
            dj = d[s0 : s0 + n_pairs[j]].reshape(counts[j], counts[j + 1])
            cost = np.where(dj <= max_step_px, dj, 1e9)
            rows, cols = linear_sum_assignment(cost)
            ok = cost[rows, cols] < 1e9
            nxt[starts[j] + rows[ok]] = starts[j + 1] + cols[ok]
        new_prv = np.full(len(pts), -1, dtype=np.intp)
        linked = nxt >= 0
        new_prv[nxt[linked]] = np.flatnonzero(linked)
        changed = np.union1d(frame_of[new_prv != prv], todo[guess])
        prv = new_prv
        first = False
        todo = changed[(changed < n - 1) & (n_pairs[np.minimum(changed, n - 2)] > 0)]


def _views_with_gaps(seed: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Undistorted normalized views of 60 frames (right j shows left j + 1) with NaN
    detections, empty frames and crowded ones."""
    ln, rn = views(1, seed=seed)
    ln = [p.copy() for p in ln[:60]]
    rn = [p.copy() for p in rn[:60]]
    ln[3] = np.zeros((0, 2))
    rn[5] = np.zeros((0, 2))
    ln[7][0] = np.nan
    rn[9][1] = np.nan
    rn[11] = np.vstack([rn[11]] * 3)  # more than MAX_POINTS_PER_FRAME: cut by _flatten
    return ln, rn


@pytest.mark.parametrize("gate_px", [0.4, 3.0, 1e6])
def test_epipolar_costs_equal_the_numpy_formulation_bit_for_bit(gate_px: float) -> None:
    """The compiled cost (which skips right points beyond the gate) gives the former bits."""
    ln, rn = _views_with_gaps(seed=4)
    left = _flatten(ln, MAX_POINTS_PER_FRAME)
    right = _flatten(rn, MAX_POINTS_PER_FRAME)
    frames = np.arange(0, 60, 2)
    l_pts, l_frame = _select_frames(left, frames)
    offsets = np.arange(-4, 5)
    r_row = l_frame[None, :] - offsets[:, None]
    r_row[(r_row < 0) | (r_row >= 60)] = -1
    r_row[2, ::5] = -1  # detections without a partner frame
    f_l = 0.5 * (RIG.left.K[0, 0] + RIG.left.K[1, 1])
    f_r = 0.5 * (RIG.right.K[0, 0] + RIG.right.K[1, 1])
    E = RIG.essential_matrix
    with np.errstate(invalid="ignore"):
        got = _epipolar_costs(E, l_pts, right, r_row, f_l, f_r, gate_px)
        want = _epipolar_costs_reference(E, l_pts, right, r_row, f_l, f_r, gate_px)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert np.all(np.isfinite(want[0]))
    # The case compares both cut-offs: costs at the gate and below it.
    assert 0.0 < float(np.mean(want[0])) < 1.0 or gate_px == 1e6


@pytest.mark.parametrize("max_step_px", [8.0, 25.0, 1e7])
def test_link_points_equals_the_rounds_formulation(max_step_px: float) -> None:
    """Frame pair by frame pair (compiled) gives the links of the former rounds, NaN
    detections and a gate too wide for the shortcut included."""
    from core.sync import _ranks, link_points

    rng = np.random.default_rng(12)
    base = rng.uniform(0, 120, (7, 2))
    vel = rng.normal(0, 5, (7, 2))
    frames = []
    for j in range(60):
        alive = rng.random(7) > 0.25
        pts = base[alive] + j * vel[alive] + rng.normal(0, 2, (int(alive.sum()), 2))
        frames.append(pts[rng.permutation(len(pts))])
    frames[4] = np.zeros((0, 2))
    frames[9][0] = np.nan
    pts, counts = _flatten(frames)
    starts = np.cumsum(counts) - counts
    frame_of = np.repeat(np.arange(len(counts)), counts)
    nxt = np.full(len(pts), -1, dtype=np.intp)
    _link_flat_reference(pts, counts, starts, frame_of, nxt, max_step_px)
    want = np.where(nxt >= 0, nxt - np.repeat(np.r_[starts[1:], 0], counts), -1)
    got = np.concatenate(link_points(frames, max_step_px=max_step_px))
    np.testing.assert_array_equal(got, want)
    assert np.count_nonzero(want >= 0) > 150
    assert _ranks(counts).shape == (len(pts),)


def test_flatten_takes_every_kind_of_frame() -> None:
    """Frames as float64 arrays (no copy per frame), and as anything np.asarray reads."""
    rng = np.random.default_rng(2)
    f64 = [rng.normal(size=(k, 2)) for k in (3, 0, 2)]
    kinds = {
        "float64": f64,
        "int": [np.array([[1, 2], [3, 4]]), np.zeros((0, 2), dtype=int)],
        "mixed": [f64[0], np.array([[1, 2]])],
        "float32": [a.astype(np.float32) for a in f64],
        "lists": [a.tolist() for a in f64],
        "flat empty": [np.zeros(0), f64[0]],
        "opencv (N, 1, 2)": [a[:, None, :] for a in f64],
        "one frame": [f64[0]],
        "none": [],
    }
    for name, frames in kinds.items():
        flat, counts = _flatten(frames)
        arrays = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in frames]
        want = np.concatenate(arrays) if arrays else np.zeros((0, 2))
        assert flat.dtype == np.float64 and flat.shape == want.shape, name
        np.testing.assert_array_equal(flat, want, err_msg=name)
        assert counts.tolist() == [len(a) for a in arrays], name
        assert counts.dtype == np.intp, name

"""Epipolar matching: exact pairs, distractors, gating, conventions."""

from __future__ import annotations

import numpy as np
import pytest
from rigs import verging_rig

from core.camera import Camera, StereoRig
from core.matching import (
    candidate_pairs,
    concatenate_frames,
    epipolar_distances_px,
    frame_pairs_epipolar_px,
    match_stereo,
)


def make_rig() -> StereoRig:
    return verging_rig()


def test_true_pairs_have_zero_epipolar_distance() -> None:
    rig = make_rig()
    pts = np.random.default_rng(0).uniform([-60, -60, 420], [60, 60, 600], (30, 3))
    ln = rig.left.undistort_points(rig.left.project(pts))
    rn = rig.right.undistort_points(rig.right.project(pts))
    d = epipolar_distances_px(rig, ln, rn)
    assert d.shape == (30, 30)
    assert np.max(np.diag(d)) < 1e-6  # px


def test_one_to_one_with_distractors_and_shuffling() -> None:
    rig = make_rig()
    rng = np.random.default_rng(1)
    # Thumb and index separated vertically (as in the tapping posture).
    markers = np.array([[10.0, -30.0, 500.0], [-5.0, 20.0, 505.0]])
    lp = rig.left.project(markers) + rng.normal(0, 0.1, (2, 2))
    rp = rig.right.project(markers) + rng.normal(0, 0.1, (2, 2))
    # Distractors: random bright spots in each image (not stereo-consistent with the markers).
    lp_all = np.vstack([lp, [[100.0, 100.0], [1200.0, 900.0]]])
    rp_all = np.vstack([[[300.0, 700.0]], rp, [[50.0, 60.0]]])
    m = match_stereo(rig, lp_all, rp_all)
    pairs = set(zip(m.left_index.tolist(), m.right_index.tolist(), strict=True))
    assert {(0, 1), (1, 2)} <= pairs
    assert len(set(m.left_index.tolist())) == len(m) and len(set(m.right_index.tolist())) == len(m)
    assert np.all(m.epipolar_px <= 2.0)  # px (gate)


def test_gate_rejects_far_pairs_and_empty_inputs() -> None:
    rig = make_rig()
    pt = np.array([[0.0, 0.0, 500.0]])
    lp, rp = rig.left.project(pt), rig.right.project(pt)
    assert len(match_stereo(rig, lp, rp + np.array([0.0, 5.0]))) == 0  # 5 px off the epipolar line
    assert len(match_stereo(rig, lp, rp + np.array([0.0, 1.0]))) == 1
    assert len(match_stereo(rig, lp, np.zeros((0, 2)))) == 0
    with pytest.raises(ValueError):
        match_stereo(rig, lp, rp, max_epipolar_px=0)


def test_candidate_pairs_keeps_ambiguous_pairs() -> None:
    """Two points on the same epipolar line both stay candidates (the tracker decides)."""
    rig = make_rig()
    a = np.array([[0.0, 0.0, 500.0]])
    ln = rig.left.undistort_points(rig.left.project(a))
    # A second right point on the epipolar line of a, at another depth.
    b = rig.left.backproject_depth(rig.left.project(a), 560.0)
    rn = rig.right.undistort_points(rig.right.project(np.vstack([a, b])))
    c = candidate_pairs(rig, ln, rn)
    assert sorted(c.right_index.tolist()) == [0, 1]


def test_convention_essential_matrix_direction() -> None:
    """Left points against right points (not the transpose) satisfy the constraint."""
    rig = make_rig()
    pts = np.random.default_rng(2).uniform([-60, -60, 420], [60, 60, 600], (10, 3))
    ln = rig.left.undistort_points(rig.left.project(pts))
    rn = rig.right.undistort_points(rig.right.project(pts))
    assert np.max(np.diag(epipolar_distances_px(rig, ln, rn))) < 1e-6  # px
    assert np.median(np.diag(epipolar_distances_px(rig, rn, ln))) > 1.0  # px: swapped is wrong


@pytest.mark.parametrize("offset", [0, 2, -3])
def test_frame_pairs_match_per_frame_distances(offset: int) -> None:
    """The all-frames pass gives, pair for pair and in order, the per-frame matrices' entries."""
    rig = make_rig()
    rng = np.random.default_rng(3)

    # World points at each left frame; right frame j sees those of left frame j + offset.
    world = [
        rng.uniform([-60, -60, 420], [60, 60, 600], (int(rng.integers(1, 5)), 3)) for _ in range(40)
    ]
    world = [w if k % 4 else w[:0] for k, w in enumerate(world)]  # some frames without markers

    def frames(cam: Camera, idx: range) -> list[np.ndarray]:
        out = []
        for k in idx:
            pts = world[k] if 0 <= k < len(world) else world[1]
            xy = cam.undistort_points(cam.project(pts)) + rng.normal(0, 1e-3, (len(pts), 2))
            if len(xy) and k % 5 == 1:
                xy[0] = np.nan  # a detection that could not be undistorted
            out.append(xy)
        return out

    left, right = frames(rig.left, range(20)), frames(rig.right, range(offset, offset + 18))
    pairs = frame_pairs_epipolar_px(rig, left, right, offset)
    assert len(pairs) == sum(
        len(left[i]) * len(right[i - offset]) for i in range(20) if 0 <= i - offset < 18
    )
    flat_left, flat_right = np.concatenate(left), np.concatenate(right)
    np.testing.assert_array_equal(
        flat_left[pairs.left_row],
        np.concatenate([left[f][[k]] for f, k in zip(pairs.frame, pairs.left_index, strict=True)])
        if len(pairs)
        else np.zeros((0, 2)),
    )
    k = 0
    for i in range(20):
        j = i - offset
        if not 0 <= j < 18:
            assert not np.any(pairs.frame == i)
            continue
        d = epipolar_distances_px(rig, left[i], right[j])
        li, ri = np.nonzero(np.ones(d.shape, bool))
        sel = slice(k, k + d.size)
        np.testing.assert_array_equal(pairs.frame[sel], np.full(d.size, i))
        np.testing.assert_array_equal(pairs.left_index[sel], li)
        np.testing.assert_array_equal(pairs.right_index[sel], ri)
        np.testing.assert_array_equal(flat_right[pairs.right_row[sel]], right[j][ri])
        np.testing.assert_allclose(pairs.epipolar_px[sel], d[li, ri], rtol=1e-9, atol=1e-9)
        k += d.size
    assert k == len(pairs)
    assert np.any(np.isnan(pairs.epipolar_px)) and np.nanmin(pairs.epipolar_px) < 0.1


def test_frame_pairs_without_pairs() -> None:
    rig = make_rig()
    empty = [np.zeros((0, 2))] * 3
    one = [np.zeros((1, 2))] * 3
    assert len(frame_pairs_epipolar_px(rig, empty, one)) == 0
    assert len(frame_pairs_epipolar_px(rig, one, one, offset=5)) == 0
    assert len(frame_pairs_epipolar_px(rig, one, [])) == 0
    assert len(frame_pairs_epipolar_px(rig, one, one, offset=1)) == 2


def test_concatenate_frames() -> None:
    frames = [np.array([[1.0, 2.0], [3.0, 4.0]]), np.zeros((0, 2)), np.array([[5.0, 6.0]])]
    flat, counts = concatenate_frames(frames)
    np.testing.assert_array_equal(flat, [[1, 2], [3, 4], [5, 6]])
    assert counts.tolist() == [2, 0, 1]
    # Lists, integers and 1-D empty frames are converted.
    flat2, counts2 = concatenate_frames([[[1, 2], [3, 4]], np.zeros(0), [(5, 6)]])
    np.testing.assert_array_equal(flat2, flat)
    assert flat2.dtype == np.float64 and counts2.tolist() == [2, 0, 1]
    flat3, counts3 = concatenate_frames([])
    assert flat3.shape == (0, 2) and counts3.shape == (0,)
    with pytest.raises(ValueError):
        concatenate_frames([np.zeros((2, 3))])

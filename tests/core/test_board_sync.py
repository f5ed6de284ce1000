"""The time offset of free-running board recordings (core.board_sync), on projected truth.

Board tracks here are the board's corners projected by a known rig at the true
capture instants of two free-running cameras (core.simulation.timing), with
seeded pixel noise: exact truth, no rendering. The rendered, end-to-end cases
are in tests/core/test_calibration.py.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from core.board_sync import (
    ESTIMATED,
    BoardSync,
    BoardTrack,
    align_numbering,
    board_motion,
    estimate_offset,
    right_at_left_instants,
)
from core.boards import BoardDetection, BoardSpec
from core.camera import ImageSize
from core.simulation.boards import DEFAULT_CHESSBOARD, board_frame_poses, example_rig
from core.simulation.timing import CameraTiming, camera_clock

FPS = 15.0
SIZE = ImageSize(640, 512)
NOISE_PX = 0.03


def _tracks(
    *,
    start_s: float = 0.3,
    drift_ppm: float = 100.0,
    duration_s: float = 6.0,
    pose_interval_s: float = 0.4,
    stride: int = 1,
    board: BoardSpec = DEFAULT_CHESSBOARD,
    seed: int = 3,
) -> tuple[BoardTrack, BoardTrack, list[np.ndarray]]:
    """Left and right tracks of a board moved between held poses, and the true right
    corners at each left frame's instant."""
    rig = example_rig(image_size=SIZE)
    rng = np.random.default_rng(seed)
    clocks = [
        camera_clock(t, fps=FPS, duration_s=duration_s, rng=rng)
        for t in (CameraTiming(), CameraTiming(start_s=start_s, drift_ppm=drift_ppm))
    ]
    tracks = []
    for cam, clock in zip(rig.cameras, clocks, strict=True):
        poses = board_frame_poses(
            rig,
            board,
            seed=seed,
            n_frames=len(clock.true_s),
            fps=FPS,
            pose_interval_s=pose_interval_s,
            times_s=clock.true_s,
        )
        frames = np.arange(0, len(poses), stride)
        dets: list[BoardDetection | None] = []
        for i in frames:
            R, t = poses[i][0]
            px = cam.project(board.object_points() @ R.T + t)
            px = px + rng.normal(0.0, NOISE_PX, px.shape)
            ids = np.arange(board.n_corners, dtype=np.int64)
            dets.append(BoardDetection(ids, px, board.object_points(), cam.image_size))
        tracks.append(
            BoardTrack(
                frames=frames,
                t_s=clock.stamp_s[frames],
                detections=tuple(dets),
                edge_width_px=np.ones(len(frames)),
                fps=FPS,
                image_size=cam.image_size,
            )
        )
    # The truth: the right corners at each left frame's true instant.
    left_times = clocks[0].true_s[tracks[0].frames]
    truth_poses = board_frame_poses(
        rig,
        board,
        seed=seed,
        n_frames=len(left_times),
        fps=FPS,
        pose_interval_s=pose_interval_s,
        times_s=left_times,
    )
    truth = [rig.right.project(board.object_points() @ p[0][0].T + p[0][1]) for p in truth_poses]
    return tracks[0], tracks[1], truth


def test_board_motion_is_still_between_moves():
    left, _right, _ = _tracks()
    motion = board_motion(left, DEFAULT_CHESSBOARD)
    speed = motion.speed
    assert motion.t_s.shape == speed.shape == (len(left) - 1,)
    assert motion.velocity.shape == (len(left) - 1, 4)
    # Frames 0-2 of every 6 (0.4 s at 15 fps) hold still; the board moves during 3-5.
    phase = np.arange(len(speed)) % 6
    assert np.all(speed[phase <= 1] < 0.01)  # board sizes / s: noise only
    assert np.all(speed[(phase >= 3) & (phase <= 4)] > 0.05)  # board sizes / s


@pytest.mark.parametrize("stride", [1, 3])
def test_offset_of_a_late_start_from_the_board_motion(stride):
    left, right, _ = _tracks(stride=stride)
    sync = estimate_offset(left, right, DEFAULT_CHESSBOARD)
    assert sync.method == ESTIMATED
    # The truth: right clock 0 is at left time 0.3 s (4.5 frames); a coarse estimate
    # is good to half the spacing of the searched frames (0.38-0.46 measured at half-frame
    # offsets over 6 seeds; the pairing allows COARSE_UNCERTAINTY = 0.75).
    assert abs(sync.offset_s - 0.3) < 0.5 * stride / FPS  # s
    assert sync.offset_frames == pytest.approx(sync.offset_s * FPS)
    assert sync.correlation > (0.6 if stride == 1 else 0.3)  # 0.78 and 0.44 measured


def test_swapping_the_cameras_negates_the_offset():
    """Convention: the left camera is the reference; the right one starting late is +."""
    left, right, _ = _tracks(start_s=0.3, drift_ppm=0.0)
    forward = estimate_offset(left, right, DEFAULT_CHESSBOARD).offset_s
    backward = estimate_offset(right, left, DEFAULT_CHESSBOARD).offset_s
    assert forward == pytest.approx(0.3, abs=0.5 / FPS)  # s
    assert backward == pytest.approx(-0.3, abs=0.5 / FPS)  # s


def test_a_board_that_never_moves_gives_no_offset():
    left, right, _ = _tracks()
    still = dataclasses.replace(right, detections=(right.detections[0],) * len(right))
    frozen = dataclasses.replace(left, detections=(left.detections[0],) * len(left))
    sync = estimate_offset(frozen, still, DEFAULT_CHESSBOARD)
    assert np.isnan(sync.correlation)


def test_right_corners_at_the_left_instants():
    left, right, truth = _tracks()
    true_sync = BoardSync(0.3, fps_left=FPS, method=ESTIMATED, uncertainty_s=0.0005)
    pairs = right_at_left_instants(left, right, DEFAULT_CHESSBOARD, true_sync, tolerance_px=0.1)
    assert len(pairs) >= 0.3 * len(left)  # the held poses at least
    for p in pairs:
        err = np.linalg.norm(p.detection.corners_px - truth[p.left_index][p.detection.ids], axis=1)
        # px: within the predicted error plus the noise of two interpolated detections.
        assert err.max() <= p.error_px + 4 * NOISE_PX, (p.left_index, err.max(), p.error_px)
    # Told the offset only to half a frame, only the still views remain.
    coarse = dataclasses.replace(true_sync, uncertainty_s=0.5 / FPS)
    still = right_at_left_instants(left, right, DEFAULT_CHESSBOARD, coarse, tolerance_px=0.1)
    assert 0 < len(still) < len(pairs)
    for p in still:
        err = np.linalg.norm(p.detection.corners_px - truth[p.left_index][p.detection.ids], axis=1)
        assert err.max() <= 4 * NOISE_PX  # px


def test_chessboard_numbering_is_aligned_between_frames():
    left, _, _ = _tracks()
    det = left.detections[0]
    assert det is not None
    flipped = det.flipped(DEFAULT_CHESSBOARD)
    again = align_numbering(det, flipped, DEFAULT_CHESSBOARD)
    np.testing.assert_array_equal(again.ids, det.ids)
    np.testing.assert_allclose(again.corners_px, det.corners_px)

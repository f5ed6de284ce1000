"""The verging test rig shared by the matching, sync, tracking and triangulation tests."""

from __future__ import annotations

import cv2
import numpy as np

from core.camera import Camera, ImageSize, StereoRig


def verging_rig(*, distorted: bool = True, right_focal_scale: float = 1.0) -> StereoRig:
    """A verging 1280x1024 rig, 160 mm baseline, converging at 500 mm (like the simulator's).

    ``distorted`` False gives both cameras zero distortion; ``right_focal_scale``
    scales the right camera's focal lengths (a rig whose cameras differ).
    """
    size = ImageSize(1280, 1024)
    K = np.array([[1800.0, 0, 645.0], [0, 1795.0, 508.0], [0, 0, 1]])
    dist_l = np.array([-0.12, 0.08, 0.0005, -0.0003, -0.02]) if distorted else np.zeros(5)
    dist_r = np.array([-0.10, 0.05, -0.0004, 0.0002, 0.0]) if distorted else np.zeros(5)
    angle = np.arctan2(160.0, 500.0)
    R = np.asarray(cv2.Rodrigues(np.array([0.01, -angle, 0.005]))[0], dtype=np.float64)
    c_right = np.array([160.0, 2.0, 0.0])  # right camera centre in the left frame (mm)
    t = -R @ c_right
    k_right = K * [[right_focal_scale], [right_focal_scale], [1]] if right_focal_scale != 1.0 else K
    return StereoRig(
        Camera("left", size, K, dist_l),
        Camera("right", size, k_right, dist_r, R, t),
    )

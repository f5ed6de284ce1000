"""A realistic default stereo rig for simulated recordings.

Two cameras ``baseline_mm`` apart, both turned inwards so that their optical
axes cross ``convergence_mm`` in front of the left camera, on its optical
axis; this is where the simulated hand is placed
(:attr:`~core.simulation.kinematics.TappingScenario.hand_center_mm`).
The two cameras differ slightly (focal length, principal point, distortion,
a small roll and pitch), as two real cameras do.
"""

from __future__ import annotations

import numpy as np

from core.camera import Camera, FloatArray, ImageSize, StereoRig

# 1250 px at 1280 px width: a 54 degree horizontal field of view (e.g. a 6 mm
# lens on a 1/1.8" sensor with 4.8 um pixels); a 5 mm marker at 500 mm is 12.5 px wide.
_FOCAL_PX_AT_1280 = 1250.0
_LEFT_DIST = (-0.10, 0.06, 0.0, 0.0, 0.0)  # mild barrel: ~3.5 % at the image corners
_RIGHT_DIST = (-0.095, 0.055, 0.0003, -0.0002, 0.0)


def _look_at(centre: FloatArray, target: FloatArray) -> FloatArray:
    """``R_cam_from_rig`` of a camera at ``centre`` looking at ``target`` (y down, no roll)."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.vstack([x, y, z])


def _rot_x(a: float) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(a: float) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def default_rig(
    *,
    image_size: ImageSize = ImageSize(1280, 1024),
    baseline_mm: float = 250.0,
    convergence_mm: float = 500.0,
    focal_px: float | None = None,
    distortion: bool = True,
) -> StereoRig:
    """A converging two-camera rig whose world frame is the left camera's.

    Parameters
    ----------
    image_size : ImageSize
        ``(width, height)`` of both cameras.
    baseline_mm : float
        Distance between the optical centres (mm).
    convergence_mm : float
        Distance from the left camera to the point where the optical axes cross
        (mm); that point is ``(0, 0, convergence_mm)`` in the world frame.
    focal_px : float, optional
        Focal length of the left camera (px); default 1250 px scaled with the
        image width (a constant field of view of about 54 degrees).
    distortion : bool
        Mild barrel distortion (default) or none.

    Returns
    -------
    StereoRig
    """
    size = ImageSize(*(int(v) for v in image_size))
    if size.width < 16 or size.height < 16:
        raise ValueError(f"image_size must be at least 16 x 16 px, got {tuple(size)}")
    if not (0 < baseline_mm < 2 * convergence_mm):
        raise ValueError(
            f"need 0 < baseline_mm < 2 * convergence_mm, got {baseline_mm}, {convergence_mm}"
        )
    f = _FOCAL_PX_AT_1280 * size.width / 1280.0 if focal_px is None else float(focal_px)
    if not f > 0:
        raise ValueError(f"focal_px must be positive, got {focal_px}")
    scale = size.width / 1280.0
    cx, cy = (size.width - 1) / 2.0, (size.height - 1) / 2.0
    K_left = np.array([[f, 0.0, cx + 3.0 * scale], [0.0, f, cy - 2.0 * scale], [0.0, 0.0, 1.0]])
    K_right = np.array(
        [[f * 1.004, 0.0, cx - 5.0 * scale], [0.0, f * 1.004, cy + 4.0 * scale], [0.0, 0.0, 1.0]]
    )
    # Rig frame: centres at (-+B/2, 0, 0), axes crossing at (0, 0, h).
    half = baseline_mm / 2.0
    h = np.sqrt(convergence_mm**2 - half**2)
    target = np.array([0.0, 0.0, h])
    c_left, c_right = np.array([-half, 0.0, 0.0]), np.array([half, 0.0, 0.0])
    R_left = _look_at(c_left, target)
    # The right camera is mounted with a small roll and pitch error, as real rigs are.
    R_right = _rot_z(np.deg2rad(0.4)) @ _rot_x(np.deg2rad(-0.3)) @ _look_at(c_right, target)
    t_left = -R_left @ c_left
    t_right = -R_right @ c_right
    R_rl = R_right @ R_left.T
    t_rl = t_right - R_rl @ t_left
    zero = (0.0, 0.0, 0.0, 0.0, 0.0)
    left = Camera("left", size, K_left, np.array(_LEFT_DIST if distortion else zero))
    right = Camera(
        "right", size, K_right, np.array(_RIGHT_DIST if distortion else zero), R_rl, t_rl
    )
    return StereoRig(left, right, {"source": "bradyscope simulator (true rig)"})

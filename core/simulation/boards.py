"""Simulated calibration-board recordings: a known rig filming a moving board.

The truth of a recording is the rig used to render it. Rendering is exact
geometry, not a texture warp by a homography: for every (super-sampled) pixel
the ray through it is found with the rig's own lens model
(:meth:`core.camera.Camera.undistort_points`, once per camera), intersected
with the board plane, and the printed board is sampled there. Pixels are the
mean of ``supersample x supersample`` such samples (anti-aliasing), then a
mild optical blur and sensor noise are added.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from core.boards import BoardSpec
from core.camera import Camera, ImageSize, StereoRig, write_rig
from core.simulation.timing import CameraTiming

FloatArray = NDArray[np.float64]

# OpenCV's type stubs reject some argument types the functions accept.
_cv: Any = cv2

#: Texture resolution of the printed board (texels per mm).
_TEXELS_PER_MM = 8.0
#: White border printed around the pattern, in squares.
_MARGIN_SQUARES = 0.75

DEFAULT_CHESSBOARD = BoardSpec("chessboard", cols=9, rows=6, square_mm=25.0)
DEFAULT_CHARUCO = BoardSpec(
    "charuco", cols=10, rows=7, square_mm=25.0, marker_mm=18.0, dictionary="DICT_4X4_1000"
)


def example_rig(*, image_size: ImageSize = ImageSize(1280, 1024)) -> StereoRig:
    """A realistic rig: 1280x1024 cameras 250 mm apart, converging at about 500 mm.

    Focal lengths near 1400 px (a ~49 degree horizontal field of view) and
    moderate barrel distortion, slightly different for the two cameras.
    Scaled consistently when a smaller ``image_size`` is asked for.
    """
    s = image_size.width / 1280.0
    w, h = image_size
    K_l = np.array(
        [[1400.0 * s, 0, (w - 1) / 2 + 7.5 * s], [0, 1401.5 * s, (h - 1) / 2 - 5.2 * s], [0, 0, 1]]
    )
    K_r = np.array(
        [[1391.0 * s, 0, (w - 1) / 2 - 6.1 * s], [0, 1392.2 * s, (h - 1) / 2 + 4.3 * s], [0, 0, 1]]
    )
    dist_l = np.array([-0.11, 0.085, 0.0004, -0.0003, -0.02])
    dist_r = np.array([-0.12, 0.095, -0.0002, 0.0005, -0.03])
    baseline_mm = 250.0
    converge_mm = 500.0
    half = np.arctan2(baseline_mm / 2, converge_mm)
    # Right camera at x = +250 mm in the left frame, both yawed toward the midline,
    # with a small pitch/roll misalignment as in a real mount.
    R_world_from_left = _rot_y(half)
    R_world_from_right = _rot_y(-half) @ _rot_x(np.deg2rad(0.6)) @ _rot_z(np.deg2rad(-0.4))
    c_left = np.array([-baseline_mm / 2, 0.0, 0.0])
    c_right = np.array([baseline_mm / 2, 1.5, 2.0])
    # Express everything in the left camera frame.
    R_left_from_world = R_world_from_left.T
    R = R_world_from_right.T @ R_world_from_left  # right_from_left
    c_right_in_left = R_left_from_world @ (c_right - c_left)
    t = -R @ c_right_in_left
    left = Camera("left", image_size, K_l, dist_l)
    right = Camera("right", image_size, K_r, dist_r, R, t)
    return StereoRig(left, right)


def _rot_x(a: float) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# -- the printed board ------------------------------------------------------


@dataclass(frozen=True)
class BoardTexture:
    """The printed board as an image: texel ``(i, j)`` covers board ``x`` in
    ``[x0_mm + j / texels_per_mm, x0_mm + (j + 1) / texels_per_mm)`` (same for y)."""

    image: NDArray[np.uint8]
    x0_mm: float
    y0_mm: float
    texels_per_mm: float
    #: Gray level seen where each texel is: black ink ~20, white paper ~215 (float32).
    radiance: NDArray[np.float32]


def board_texture(board: BoardSpec, *, texels_per_mm: float = _TEXELS_PER_MM) -> BoardTexture:
    """Render the printed board (pattern plus a white margin) as a uint8 image."""
    s = board.square_mm
    x_min, y_min, x_max, y_max = board.outline_mm()
    margin = _MARGIN_SQUARES * s
    x0, y0 = x_min - margin, y_min - margin
    width = round((x_max - x_min + 2 * margin) * texels_per_mm)
    height = round((y_max - y_min + 2 * margin) * texels_per_mm)
    tex = np.full((height, width), 255, np.uint8)
    if board.kind == "chessboard":
        xs = x0 + (np.arange(width) + 0.5) / texels_per_mm
        ys = y0 + (np.arange(height) + 0.5) / texels_per_mm
        ix = np.floor((xs - x_min) / s).astype(int)
        iy = np.floor((ys - y_min) / s).astype(int)
        inside_x = (xs >= x_min) & (xs < x_max)
        inside_y = (ys >= y_min) & (ys < y_max)
        black = ((ix[None, :] + iy[:, None]) % 2 == 0) & inside_x[None, :] & inside_y[:, None]
        tex[black] = 0
    else:
        pw = round((x_max - x_min) * texels_per_mm)
        ph = round((y_max - y_min) * texels_per_mm)
        pattern = board.charuco_board().generateImage((pw, ph), marginSize=0, borderBits=1)
        ox = round((x_min - x0) * texels_per_mm)
        oy = round((y_min - y0) * texels_per_mm)
        tex[oy : oy + ph, ox : ox + pw] = pattern
    radiance = (20.0 + tex.astype(np.float32) * np.float32(195.0 / 255.0)).astype(np.float32)
    return BoardTexture(tex, float(x0), float(y0), float(texels_per_mm), radiance)


# -- rendering ---------------------------------------------------------------


class _RayCache:
    """Undistorted normalized rays of every pixel centre of one camera, (H, W, 2) float32."""

    def __init__(self) -> None:
        self._maps: dict[tuple[Any, ...], FloatArray] = {}

    def rays(self, camera: Camera) -> FloatArray:
        key = (tuple(camera.image_size), camera.K.tobytes(), camera.dist.tobytes())
        if key not in self._maps:
            w, h = camera.image_size
            xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
            xy = camera.undistort_points(np.column_stack([xs.ravel(), ys.ravel()]))
            if len(self._maps) > 4:
                self._maps.clear()
            self._maps[key] = xy.reshape(h, w, 2).astype(np.float32)
        return self._maps[key]


_RAYS = _RayCache()


def render_board_view(
    camera: Camera,
    texture: BoardTexture,
    R_cam_from_board: FloatArray,
    t_cam_from_board_mm: FloatArray,
    *,
    board: BoardSpec,
    rng: np.random.Generator,
    supersample: int = 3,
    noise_std: float = 1.5,
    blur_sigma_px: float = 0.5,
    background: float = 120.0,
) -> NDArray[np.uint8]:
    """One gray image ``(H, W)`` uint8 of the board seen by ``camera``.

    Parameters
    ----------
    camera : Camera
        Its pose is ignored: the board pose is given in the camera's frame.
    texture : BoardTexture
        From :func:`board_texture`.
    R_cam_from_board : ndarray, shape (3, 3)
    t_cam_from_board_mm : ndarray, shape (3,)
        Board frame to camera frame: ``x_cam = R @ x_board + t`` (mm).
    board : BoardSpec
        The board, used to bound the region to render.
    rng : numpy.random.Generator
        Sensor noise.
    supersample : int
        Samples per pixel along each axis (anti-aliasing).
    noise_std : float
        Gaussian sensor noise (gray levels).
    blur_sigma_px : float
        Gaussian optical blur (pixels); 0 for none.
    background : float
        Gray level of the scene behind the board.
    """
    R = np.asarray(R_cam_from_board, dtype=np.float64)
    t = np.asarray(t_cam_from_board_mm, dtype=np.float64).reshape(3)
    if R.shape != (3, 3):
        raise ValueError(f"R_cam_from_board must have shape (3, 3), got {R.shape}")
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    w, h = camera.image_size
    img = _background(camera.image_size, background).copy()
    # Region of the image the board (with its margin) can cover.
    x0 = texture.x0_mm
    y0 = texture.y0_mm
    x1 = x0 + texture.image.shape[1] / texture.texels_per_mm
    y1 = y0 + texture.image.shape[0] / texture.texels_per_mm
    gx, gy = np.meshgrid(np.linspace(x0, x1, 25), np.linspace(y0, y1, 25))
    outline = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    cam_pts = outline @ R.T + t
    if np.all(cam_pts[:, 2] <= 0):
        return _finish(img, rng, noise_std, blur_sigma_px)
    pix = Camera("c", camera.image_size, camera.K, camera.dist).project(cam_pts)
    pix = pix[np.all(np.isfinite(pix), axis=1)]
    if np.any(cam_pts[:, 2] <= 0) or len(pix) == 0:
        c0, r0, c1, r1 = 0, 0, w, h
    else:
        c0 = int(np.clip(np.floor(pix[:, 0].min()) - 3, 0, w))
        c1 = int(np.clip(np.ceil(pix[:, 0].max()) + 4, 0, w))
        r0 = int(np.clip(np.floor(pix[:, 1].min()) - 3, 0, h))
        r1 = int(np.clip(np.ceil(pix[:, 1].max()) + 4, 0, h))
    if c1 <= c0 or r1 <= r0:
        return _finish(img, rng, noise_std, blur_sigma_px)
    rays = _RAYS.rays(camera)
    # Pad one pixel so the linear up-sampling of the ray map is centred correctly.
    pc0, pr0 = max(c0 - 1, 0), max(r0 - 1, 0)
    pc1, pr1 = min(c1 + 1, w), min(r1 + 1, h)
    crop = rays[pr0:pr1, pc0:pc1]
    n = supersample
    up_size = ((pc1 - pc0) * n, (pr1 - pr0) * n)
    up = cv2.resize(crop, up_size, interpolation=cv2.INTER_LINEAR) if n > 1 else crop
    # Ray (x, y, 1) meets the plane z_board = 0 at board point G @ (x, y, 1),
    # G = [r1 r2 t]^-1, in front of the camera where the third component is > 0.
    G = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t]))
    # channel by channel: numpy reduces an (N, 2) array along axis 0 about 20x slower
    lo = np.array([crop[..., 0].min(), crop[..., 1].min()])
    hi = np.array([crop[..., 0].max(), crop[..., 1].max()])
    box = np.array([[lo[0], lo[1], 1], [hi[0], lo[1], 1], [lo[0], hi[1], 1], [hi[0], hi[1], 1]])
    in_front = bool(np.all(box @ G[2] > 0))
    tpm = texture.texels_per_mm
    # Board mm -> texture map coordinates (OpenCV: texel j's centre is at j).
    to_tex = np.array([[tpm, 0, -x0 * tpm - 0.5], [0, tpm, -y0 * tpm - 0.5], [0, 0, 1]])
    maps = cv2.perspectiveTransform(up, to_tex @ G)
    if not in_front:
        bw = up[..., 0] * G[2, 0] + up[..., 1] * G[2, 1] + G[2, 2]
        maps[~(bw > 0)] = -1e4
    bg = np.ascontiguousarray(img[pr0:pr1, pc0:pc1], dtype=np.float32)
    dst = cv2.resize(bg, up_size, interpolation=cv2.INTER_NEAREST) if n > 1 else bg.copy()
    # Pixels whose ray misses the printed board keep the background (transparent border).
    _cv.remap(
        texture.radiance,
        maps.astype(np.float32),
        None,
        interpolation=cv2.INTER_LINEAR,
        dst=dst,
        borderMode=cv2.BORDER_TRANSPARENT,
    )
    if n > 1:
        dst = cv2.resize(dst, (pc1 - pc0, pr1 - pr0), interpolation=cv2.INTER_AREA)
    img[pr0:pr1, pc0:pc1] = dst
    return _finish(img, rng, noise_std, blur_sigma_px)


@functools.lru_cache(maxsize=4)
def _background(size: ImageSize, level: float) -> NDArray[np.float32]:
    """A smooth gray scene ``(H, W)`` float32 behind the board."""
    w, h = size
    xs = np.linspace(-1.0, 1.0, w)[None, :]
    ys = np.linspace(-1.0, 1.0, h)[:, None]
    return np.asarray(level + 18.0 * xs - 10.0 * ys, dtype=np.float32)


def _finish(
    img: NDArray[Any], rng: np.random.Generator, noise_std: float, blur_sigma_px: float
) -> NDArray[np.uint8]:
    out: Any = img.astype(np.float32)
    if blur_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_sigma_px)
    if noise_std > 0:
        out += np.float32(noise_std) * rng.standard_normal(size=out.shape, dtype=np.float32)
    np.rint(out, out=out)
    np.clip(out, 0, 255, out=out)
    result: NDArray[np.uint8] = out.astype(np.uint8)
    return result


# -- poses --------------------------------------------------------------------


def _rodrigues(rvec: FloatArray) -> FloatArray:
    R, _ = _cv.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return np.asarray(R, dtype=np.float64)


def _board_centre(board: BoardSpec) -> FloatArray:
    x_min, y_min, x_max, y_max = board.outline_mm()
    return np.array([(x_min + x_max) / 2, (y_min + y_max) / 2, 0.0])


def random_board_poses(
    rig: StereoRig,
    board: BoardSpec,
    n_poses: int,
    *,
    rng: np.random.Generator,
    max_tilt_rad: float = np.deg2rad(40.0),
    distance_range_mm: tuple[float, float] | None = None,
    allow_partial: bool = False,
) -> list[tuple[FloatArray, FloatArray]]:
    """Board poses ``(R_left_from_board, t_left_from_board_mm)`` seen by both cameras.

    Board centres are spread over the left image (coverage), at distances
    around the rig's convergence distance, tilted up to ``max_tilt_rad``
    about both in-plane axes and turned up to 25 degrees in the plane. The
    board faces the midpoint between the two cameras. Unless
    ``allow_partial``, the whole pattern lies inside both images (10 px margin).
    """
    if n_poses < 1:
        raise ValueError(f"n_poses must be >= 1, got {n_poses}")
    c_right = rig.right.center_world_mm
    # Distance scale: where the two optical axes pass closest (convergence).
    axis_r = rig.right.R_cam_from_world.T @ np.array([0.0, 0.0, 1.0])
    converge = _closest_depth(c_right, axis_r)
    if distance_range_mm is None:
        distance_range_mm = (0.75 * converge, 1.3 * converge)
    mid = c_right / 2
    x_min, y_min, x_max, y_max = board.outline_mm()
    outline = np.array([[x_min, y_min, 0], [x_max, y_min, 0], [x_min, y_max, 0], [x_max, y_max, 0]])
    objp = np.vstack([board.object_points(), outline])
    centre = _board_centre(board)
    poses: list[tuple[FloatArray, FloatArray]] = []
    w, h = rig.left.image_size
    tries = 0
    while len(poses) < n_poses:
        tries += 1
        if tries > 2000 * n_poses:
            raise RuntimeError("could not place the board in view of both cameras; the rig is odd")
        u = rng.uniform(0.1 * w, 0.9 * w)
        v = rng.uniform(0.1 * h, 0.9 * h)
        depth = rng.uniform(*distance_range_mm)
        ray = rig.left.undistort_points(np.array([[u, v]]))[0]
        if not np.all(np.isfinite(ray)):
            continue
        p_centre = np.array([ray[0] * depth, ray[1] * depth, depth])
        # Base orientation: board z axis points away from the cameras' midpoint.
        z_axis = p_centre - mid
        z_axis /= np.linalg.norm(z_axis)
        x_axis = np.cross(np.array([0.0, 1.0, 0.0]), z_axis)
        x_axis /= np.linalg.norm(x_axis)
        y_axis = np.cross(z_axis, x_axis)
        R_base = np.column_stack([x_axis, y_axis, z_axis])
        tilt = rng.uniform(-max_tilt_rad, max_tilt_rad, size=2)
        spin = rng.uniform(-np.deg2rad(25.0), np.deg2rad(25.0))
        R = R_base @ _rodrigues(np.array([tilt[0], tilt[1], 0.0])) @ _rot_z(spin)
        t = p_centre - R @ centre
        if not allow_partial:
            ok = True
            for cam in rig.cameras:
                px = cam.project(objp @ R.T + t)
                if not np.all(cam.in_image(px, margin_px=10.0)):
                    ok = False
                    break
            if not ok:
                continue
        poses.append((R, t))
    return poses


def _closest_depth(c_right: FloatArray, axis_right: FloatArray) -> float:
    """Depth along the left optical axis where it passes closest to the right one."""
    a = np.array([0.0, 0.0, 1.0])
    b = axis_right / np.linalg.norm(axis_right)
    w0 = -c_right
    ab = a @ b
    denom = 1 - ab * ab
    if denom < 1e-9:
        return 600.0
    s = (ab * (b @ w0) - (a @ w0)) / denom
    return float(np.clip(s, 200.0, 3000.0))


def _slerp_pose(
    p0: tuple[FloatArray, FloatArray], p1: tuple[FloatArray, FloatArray], s: float
) -> tuple[FloatArray, FloatArray]:
    R0, t0 = p0
    R1, t1 = p1
    rvec, _ = _cv.Rodrigues(R0.T @ R1)
    R = R0 @ _rodrigues(rvec.reshape(3) * s)
    return R, (1 - s) * t0 + s * t1


# -- recordings ---------------------------------------------------------------

BoardChoice = Literal["chessboard", "charuco", "both"]


def board_frame_poses(
    rig: StereoRig,
    board: BoardSpec,
    *,
    seed: int,
    n_frames: int,
    fps: float,
    pose_interval_s: float = 1.0,
    exposure_s: float = 0.0,
    times_s: FloatArray | None = None,
) -> list[list[tuple[FloatArray, FloatArray]]]:
    """Board poses (left-camera frame) during each frame's exposure.

    Key poses come every ``pose_interval_s``; the board holds still for the
    first half of the interval and moves smoothly (cosine ease) to the next
    key pose during the second half. Frame ``i`` is exposed from ``i / fps``
    to ``i / fps + exposure_s``, or from ``times_s[i]`` when given (true
    capture times of a free-running camera, s, on the same clock as the key
    poses; see :mod:`core.simulation.timing`).

    Returns
    -------
    list of list of (R, t)
        Per frame, the pose at the start of the exposure alone when the board
        is still (or ``exposure_s`` is 0), else 5 poses spread over the exposure.
    """
    rng = np.random.default_rng(seed)
    frames_per_key = max(1.0, pose_interval_s * fps)
    if times_s is None:
        starts = np.arange(n_frames) / frames_per_key
    else:
        times = np.asarray(times_s, dtype=np.float64).reshape(-1)
        if times.size == 0 or np.any(times < 0) or not np.all(np.isfinite(times)):
            raise ValueError("times_s must be finite and >= 0")
        starts = times * fps / frames_per_key
    # Keys up to the last frame (one more past it for the move that follows).
    n_keys = (
        int(np.ceil(max(n_frames, float(starts[-1]) * frames_per_key + 1) / frames_per_key)) + 2
    )
    keys = random_board_poses(rig, board, n_keys, rng=rng, allow_partial=board.kind == "charuco")

    def at(k: float) -> tuple[FloatArray, FloatArray]:
        k0 = int(np.floor(k))
        frac = k - k0
        s = 0.0 if frac < 0.5 else 0.5 - 0.5 * np.cos(np.pi * (frac - 0.5) / 0.5)
        return _slerp_pose(keys[k0], keys[min(k0 + 1, n_keys - 1)], float(s))

    frames = []
    for k_start in starts:
        k_end = k_start + exposure_s * fps / frames_per_key
        moving = exposure_s > 0 and (
            (k_start - np.floor(k_start)) >= 0.5 or (k_end - np.floor(k_start)) > 0.5
        )
        if moving:
            frames.append([at(k) for k in np.linspace(k_start, k_end, 5)])
        else:
            frames.append([at(float(k_start))])
    return frames


def render_stereo_frame(
    rig: StereoRig,
    board: BoardSpec,
    texture: BoardTexture,
    pose: tuple[FloatArray, FloatArray] | list[tuple[FloatArray, FloatArray]],
    *,
    rng: np.random.Generator,
    supersample: int = 3,
    noise_std: float = 1.5,
    blur_sigma_px: float = 0.5,
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """The left and right images of a board pose ``(R_left_from_board, t_left_from_board_mm)``.

    A list of poses is the board's path during the exposure: the images are
    their mean (motion blur).
    """
    left, right = (
        render_camera_frame(
            cam,
            board,
            texture,
            pose,
            rng=rng,
            supersample=supersample,
            noise_std=noise_std,
            blur_sigma_px=blur_sigma_px,
        )
        for cam in rig.cameras
    )
    return left, right


def render_camera_frame(
    cam: Camera,
    board: BoardSpec,
    texture: BoardTexture,
    pose: tuple[FloatArray, FloatArray] | list[tuple[FloatArray, FloatArray]],
    *,
    rng: np.random.Generator,
    supersample: int = 3,
    noise_std: float = 1.5,
    blur_sigma_px: float = 0.5,
) -> NDArray[np.uint8]:
    """One camera's image of a board pose ``(R_left_from_board, t_left_from_board_mm)``
    (a list of poses: the mean over the exposure, motion blur); ``cam`` is a rig camera,
    whose pose maps the left camera's frame to its own."""
    poses = pose if isinstance(pose, list) else [pose]
    acc = None
    for R_lb, t_lb in poses:
        R = cam.R_cam_from_world @ R_lb
        t = cam.R_cam_from_world @ t_lb + cam.t_cam_from_world_mm
        single = len(poses) == 1
        img = render_board_view(
            cam,
            texture,
            R,
            t,
            board=board,
            rng=rng,
            supersample=supersample,
            noise_std=noise_std if single else 0.0,
            blur_sigma_px=blur_sigma_px if single else 0.0,
        )
        if single:
            acc = img
        else:
            acc = img.astype(np.float32) if acc is None else acc + img
    assert acc is not None
    if len(poses) > 1:
        acc = _finish(acc / len(poses), rng, noise_std, blur_sigma_px)
    return np.asarray(acc, dtype=np.uint8)


def write_board_recordings(
    rig: StereoRig,
    out_dir: str | Path,
    *,
    seed: int,
    board: BoardChoice = "both",
    duration_s: float = 10.0,
    fps: float = 10.0,
    pose_interval_s: float = 1.0,
    chessboard: BoardSpec = DEFAULT_CHESSBOARD,
    charuco: BoardSpec = DEFAULT_CHARUCO,
    as_images: bool = False,
    supersample: int = 3,
    noise_std: float = 1.5,
    exposure_s: float = 0.0,
    timing: tuple[CameraTiming, CameraTiming] | None = None,
    codec: str = "lossless",
) -> list[Path]:
    """Write simulated stereo board recordings of ``rig`` into ``out_dir``.

    For each board: ``<kind>_left.mkv`` and ``<kind>_right.mkv`` (lossless
    FFV1, or the suffix of ``codec``), or folders ``<kind>_left/`` and
    ``<kind>_right/`` of PNG frames with ``as_images``, plus ``<kind>.json``
    (the board spec, ``BoardSpec.to_dict``). The true rig goes to
    ``rig_true.json``; with ``timing``, the true clocks to ``timing_true.json``.

    Parameters
    ----------
    rig : StereoRig
        The truth. The two cameras may have different image sizes.
    out_dir : str or Path
        Created if needed.
    seed : int
        Poses and noise are reproducible from it.
    board : {"chessboard", "charuco", "both"}
    duration_s, fps : float
        Length (s) and frame rate (Hz) of each recording.
    pose_interval_s : float
        Time between successive board key poses (s); the board holds still for
        half of it and moves during the other half. Use ``1 / fps`` for a new
        pose every frame.
    chessboard, charuco : BoardSpec
        The boards to film.
    as_images : bool
        Write PNG folders instead of videos.
    supersample : int
        Anti-aliasing samples per pixel along each axis.
    noise_std : float
        Sensor noise (gray levels).
    exposure_s : float
        Exposure time (s): frames taken while the board moves are motion-blurred
        over it; 0 for instantaneous (sharp) frames.
    timing : (CameraTiming, CameraTiming), optional
        Free-running cameras (left, right): each captures at its own instants
        (start, frame rate, clock drift, lost frames, jitter; rolling shutter
        and image size are not simulated here: the rig's sizes are used), the
        board moving in true time. ``vfr`` timings need a PyAV ``codec``
        (``"h264"``, ``"vp9"``...). Without it both cameras are triggered
        together at ``i / fps`` (a lab rig).
    codec : str
        A :class:`core.video.VideoWriter` codec.

    Returns
    -------
    list of Path
        The written files/folders: per board left, right, spec; then
        ``rig_true.json`` (and ``timing_true.json``).
    """
    from core.simulation.timing import camera_clock
    from core.video import VideoWriter, video_suffix

    if board not in ("chessboard", "charuco", "both"):
        raise ValueError(f"board must be 'chessboard', 'charuco' or 'both', got {board!r}")
    if chessboard.kind != "chessboard" or charuco.kind != "charuco":
        raise ValueError("chessboard and charuco must be a chessboard and a charuco BoardSpec")
    if not (duration_s > 0 and fps > 0):
        raise ValueError(f"duration_s and fps must be positive, got {duration_s}, {fps}")
    if timing is not None:
        if len(timing) != 2:
            raise ValueError("timing must be a (left, right) pair of CameraTiming")
        if any(t.readout_ms > 0 for t in timing):
            raise ValueError("rolling shutter is not simulated in board recordings")
        if any(t.start_s < 0 for t in timing):
            raise ValueError("camera start times must be >= 0 s")
        if any(t.vfr for t in timing) and not as_images and video_suffix(codec) == ".mkv":
            raise ValueError(
                "variable-frame-rate timestamps need a PyAV codec (h264, hevc, vp9, vp8)"
            )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n_frames = max(1, round(duration_s * fps))
    specs = (
        [chessboard, charuco]
        if board == "both"
        else [chessboard if board == "chessboard" else charuco]
    )
    written: list[Path] = []
    for k, spec in enumerate(specs):
        texture = board_texture(spec)
        rng = np.random.default_rng([seed, k, 1])
        paths = [out / f"{spec.kind}_left", out / f"{spec.kind}_right"]
        if not as_images:
            paths = [p.with_suffix(video_suffix(codec)) for p in paths]
        # Per camera: the board's poses at each written frame and the frame's timestamp.
        if timing is None:
            poses = board_frame_poses(
                rig,
                spec,
                seed=seed * 7919 + k,
                n_frames=n_frames,
                fps=fps,
                pose_interval_s=pose_interval_s,
                exposure_s=exposure_s,
            )
            frames: list[list[Any]] = [poses, poses]
            stamps: list[FloatArray | None] = [None, None]
            rates = [fps, fps]
        else:
            clock_rng = np.random.default_rng([seed, k, 2])
            clocks = [
                camera_clock(t, fps=fps, duration_s=duration_s, rng=clock_rng) for t in timing
            ]
            frames = [
                board_frame_poses(
                    rig,
                    spec,
                    seed=seed * 7919 + k,
                    n_frames=n_frames,
                    fps=fps,
                    pose_interval_s=pose_interval_s,
                    exposure_s=exposure_s,
                    times_s=c.true_s,
                )
                for c in clocks
            ]
            stamps = [c.stamp_s if t.vfr else None for c, t in zip(clocks, timing, strict=True)]
            rates = [c.fps for c in clocks]
        render = functools.partial(
            render_camera_frame,
            board=spec,
            texture=texture,
            rng=rng,
            supersample=supersample,
            noise_std=noise_std,
        )
        if as_images:
            for p in paths:
                p.mkdir(exist_ok=True)
        writers = (
            [None, None]
            if as_images
            else [
                VideoWriter(p, fps=r, image_size=cam.image_size, codec=codec)
                for p, r, cam in zip(paths, rates, rig.cameras, strict=True)
            ]
        )
        try:
            # Left and right frames interleaved (the lab rig's noise draws as before).
            for i in range(max(len(f) for f in frames)):
                for cam, poses_c, stamp, writer, path in zip(
                    rig.cameras, frames, stamps, writers, paths, strict=True
                ):
                    if i >= len(poses_c):
                        continue
                    img = render(cam, pose=poses_c[i])
                    if writer is None:
                        cv2.imwrite(str(path / f"{i:05d}.png"), img)
                    else:
                        writer.write(img, time_s=None if stamp is None else float(stamp[i]))
        finally:
            for w in writers:
                if w is not None:
                    w.close()
        spec_path = out / f"{spec.kind}.json"
        spec_path.write_text(json.dumps(spec.to_dict(), indent=2) + "\n", encoding="utf-8")
        written.extend([*paths, spec_path])
    rig_path = out / "rig_true.json"
    write_rig(rig, rig_path)
    written.append(rig_path)
    if timing is not None:
        timing_path = out / "timing_true.json"
        timing_path.write_text(
            json.dumps(true_clock_map(*timing, fps=fps), indent=2) + "\n", encoding="utf-8"
        )
        written.append(timing_path)
    return written


def true_clock_map(left: CameraTiming, right: CameraTiming, *, fps: float) -> dict[str, Any]:
    """The true map from the right camera's clock to the left one's, as ``core.clock`` states it.

    ``t_left = offset_s + (1 + drift_ppm·1e-6) · t_right`` with both times on
    each camera's own clock, 0 at its first frame (:mod:`core.simulation.timing`).
    """
    scale_l = 1.0 + left.drift_ppm * 1e-6
    scale_r = 1.0 + right.drift_ppm * 1e-6
    fps_left = float(left.fps if left.fps is not None else fps)
    offset_s = (right.start_s - left.start_s) / scale_l
    return {
        "offset_s": offset_s,
        "offset_frames": offset_s * fps_left,
        "drift_ppm": (scale_r / scale_l - 1.0) * 1e6,
        "left": left.to_dict(),
        "right": right.to_dict(),
    }

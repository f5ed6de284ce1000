"""Pinhole camera with OpenCV's lens-distortion model, and the two-camera rig.

Conventions (see ``docs/coordinates.md`` and INTERFACES.md):

- Pixel coordinates are OpenCV's ``(x, y) = (column, row)`` with the origin at
  the centre of the top-left pixel.
- A world point ``X`` (mm) maps to camera coordinates as
  ``x_cam = R_cam_from_world @ X + t_cam_from_world_mm``.
- The world frame of a rig is the left camera's frame.
- ``dist`` holds 4, 5, 8, 12 or 14 coefficients exactly as ``cv2.projectPoints``
  takes them: ``k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tau_x tau_y]]]]``.

Projection is implemented in numpy (it agrees with ``cv2.projectPoints`` to
1e-9 px); undistortion inverts it with Newton's method to machine precision,
which ``cv2.undistortPoints``' fixed-point iteration does not reach under
strong distortion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core.geometry_kernels import _geometry

FloatArray = NDArray[np.float64]

_VALID_DIST_LENGTHS = (4, 5, 8, 12, 14)


class ImageSize(NamedTuple):
    """Image size in pixels, OpenCV's order: ``(width, height)``.

    Build it from a numpy image with :meth:`of_image`, never from
    ``img.shape[:2]`` directly, which is ``(height, width)``.
    """

    width: int
    height: int

    @classmethod
    def of_image(cls, image: NDArray[Any]) -> ImageSize:
        """The size of a numpy image of shape ``(H, W)`` or ``(H, W, C)``."""
        if image.ndim not in (2, 3):
            raise ValueError(f"an image has 2 or 3 dimensions, got shape {image.shape}")
        return cls(width=int(image.shape[1]), height=int(image.shape[0]))


def _as_points(points: ArrayLike, dim: int, name: str) -> FloatArray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}), got {arr.shape}")
    return arr


def _full_dist(dist: FloatArray) -> FloatArray:
    """The 14 OpenCV coefficients, zero-padded."""
    out = np.zeros(14)
    out[: dist.shape[0]] = dist
    return out


def tilt_matrix(tau_x: float, tau_y: float) -> FloatArray:
    """OpenCV's ``computeTiltProjectionMatrix`` (Scheimpflug sensor tilt), (3, 3)."""
    c_x, s_x = np.cos(tau_x), np.sin(tau_x)
    c_y, s_y = np.cos(tau_y), np.sin(tau_y)
    rot_x = np.array([[1.0, 0.0, 0.0], [0.0, c_x, s_x], [0.0, -s_x, c_x]])
    rot_y = np.array([[c_y, 0.0, -s_y], [0.0, 1.0, 0.0], [s_y, 0.0, c_y]])
    rot_xy = rot_y @ rot_x
    proj_z = np.array(
        [
            [rot_xy[2, 2], 0.0, -rot_xy[0, 2]],
            [0.0, rot_xy[2, 2], -rot_xy[1, 2]],
            [0.0, 0.0, 1.0],
        ]
    )
    result: NDArray[np.float64] = proj_z @ rot_xy
    return result


def distort_normalized(xy: FloatArray, dist: FloatArray) -> FloatArray:
    """Apply OpenCV's distortion to normalized coordinates ``(N, 2)``.

    Returns the distorted normalized coordinates (before the camera matrix),
    including the sensor tilt when ``dist`` has 14 coefficients.
    """
    d = _full_dist(dist)
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tau_x, tau_y = d
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    a1 = 2 * x * y
    xd = x * radial + p1 * a1 + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * a1 + s3 * r2 + s4 * r4
    if tau_x != 0.0 or tau_y != 0.0:
        tilt = tilt_matrix(tau_x, tau_y)
        v = tilt @ np.vstack([xd, yd, np.ones_like(xd)])
        inv = np.where(v[2] != 0, 1.0 / v[2], 1.0)
        xd, yd = v[0] * inv, v[1] * inv
    return np.column_stack([xd, yd])


def undistort_normalized(
    xy_distorted: FloatArray, dist: FloatArray, *, max_iter: int = 50, tol: float = 1e-14
) -> FloatArray:
    """Invert :func:`distort_normalized` with Newton's method, ``(N, 2)`` -> ``(N, 2)``.

    Points where the iteration does not converge (outside the region where the
    distortion is invertible) come back as NaN rather than as a wrong value.

    Every point takes each Newton step until all of them have converged. Without
    sensor tilt the loop is compiled (:func:`core._geometry.undistort`, the
    arithmetic below in the same order: the same bits, ``tests/core/geometry_reference.py``
    keeps this formulation and a test compares).
    """
    d = _full_dist(dist)
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tau_x, tau_y = d
    if tau_x == 0.0 and tau_y == 0.0:
        xy = np.ascontiguousarray(xy_distorted, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"xy_distorted must have shape (N, 2), got {xy.shape}")
        return _geometry.undistort(xy, d, max_iter, tol)
    target = np.array(xy_distorted, dtype=np.float64, copy=True)
    if tau_x != 0.0 or tau_y != 0.0:
        inv_tilt = np.linalg.inv(tilt_matrix(tau_x, tau_y))
        v = inv_tilt @ np.vstack([target[:, 0], target[:, 1], np.ones(len(target))])
        target = np.column_stack([v[0] / v[2], v[1] / v[2]])
    x = target[:, 0].copy()
    y = target[:, 1].copy()
    tx, ty = target[:, 0], target[:, 1]
    converged = np.zeros(len(x), dtype=bool)
    for _ in range(max_iter):
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        num = 1 + k1 * r2 + k2 * r4 + k3 * r6
        den = 1 + k4 * r2 + k5 * r4 + k6 * r6
        rad = num / den
        drad = ((k1 + 2 * k2 * r2 + 3 * k3 * r4) * den - num * (k4 + 2 * k5 * r2 + 3 * k6 * r4)) / (
            den * den
        )
        fx = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4 - tx
        fy = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4 - ty
        j11 = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x + 2 * s1 * x + 4 * s2 * r2 * x
        j12 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y + 2 * s1 * y + 4 * s2 * r2 * y
        j21 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y + 2 * s3 * x + 4 * s4 * r2 * x
        j22 = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x + 2 * s3 * y + 4 * s4 * r2 * y
        det = j11 * j22 - j12 * j21
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = (j22 * fx - j12 * fy) / det
            dy = (-j21 * fx + j11 * fy) / det
        x = x - dx
        y = y - dy
        converged = np.abs(fx) + np.abs(fy) < tol
        if np.all(converged | ~np.isfinite(x)):
            break
    # A final residual check: a Newton step may have jumped to another branch.
    check = distort_normalized(np.column_stack([x, y]), dist)
    bad = ~np.all(np.abs(check - np.asarray(xy_distorted)) < 1e-9, axis=1)
    out = np.column_stack([x, y])
    out[bad] = np.nan
    return out


@dataclass(frozen=True)
class Camera:
    """One calibrated camera: intrinsics, distortion and pose.

    Attributes
    ----------
    name : str
        ``"left"`` or ``"right"`` in a rig.
    image_size : ImageSize
        ``(width, height)`` in pixels.
    K : ndarray, shape (3, 3)
        Camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (no skew).
    dist : ndarray, shape (4|5|8|12|14,)
        OpenCV distortion coefficients.
    R_cam_from_world : ndarray, shape (3, 3)
        Rotation from the world (left-camera) frame to this camera.
    t_cam_from_world_mm : ndarray, shape (3,)
        Translation in mm.
    readout_ms : float
        Rolling-shutter readout time from the top row to the bottom row (ms);
        0 for a global shutter. A frame's time is that of its middle row.
    """

    name: str
    image_size: ImageSize
    K: FloatArray
    dist: FloatArray = field(default_factory=lambda: np.zeros(5))
    R_cam_from_world: FloatArray = field(default_factory=lambda: np.eye(3))
    t_cam_from_world_mm: FloatArray = field(default_factory=lambda: np.zeros(3))
    readout_ms: float = 0.0

    def __post_init__(self) -> None:
        K = np.array(self.K, dtype=np.float64)
        dist = np.array(self.dist, dtype=np.float64).reshape(-1)
        R = np.array(self.R_cam_from_world, dtype=np.float64)
        t = np.array(self.t_cam_from_world_mm, dtype=np.float64).reshape(-1)
        size = ImageSize(*(int(v) for v in self.image_size))
        if K.shape != (3, 3):
            raise ValueError(f"K must have shape (3, 3), got {K.shape}")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise ValueError(f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise ValueError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
        if dist.shape[0] not in _VALID_DIST_LENGTHS:
            raise ValueError(f"dist must hold 4, 5, 8, 12 or 14 coefficients, got {dist.shape[0]}")
        if R.shape != (3, 3):
            raise ValueError(f"R_cam_from_world must have shape (3, 3), got {R.shape}")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("R_cam_from_world must be a rotation matrix (orthonormal, det +1)")
        if t.shape != (3,):
            raise ValueError(f"t_cam_from_world_mm must have shape (3,), got {t.shape}")
        if size.width <= 0 or size.height <= 0:
            raise ValueError(f"image_size must be positive (width, height), got {tuple(size)}")
        if not all(np.all(np.isfinite(a)) for a in (K, dist, R, t)):
            raise ValueError("camera parameters must be finite numbers")
        if not 0 <= float(self.readout_ms) <= 1000:
            raise ValueError(f"readout_ms must be in [0, 1000] ms, got {self.readout_ms}")
        object.__setattr__(self, "readout_ms", float(self.readout_ms))
        for a in (K, dist, R, t):
            a.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "R_cam_from_world", R)
        object.__setattr__(self, "t_cam_from_world_mm", t)
        object.__setattr__(self, "image_size", size)

    # -- derived quantities -------------------------------------------------
    @property
    def center_world_mm(self) -> FloatArray:
        """Optical centre in world coordinates, shape (3,)."""
        return -self.R_cam_from_world.T @ self.t_cam_from_world_mm

    @property
    def projection_matrix_normalized(self) -> FloatArray:
        """``[R | t]`` (3, 4): projects world points to undistorted normalized coordinates."""
        return np.hstack([self.R_cam_from_world, self.t_cam_from_world_mm[:, None]])

    def to_camera(self, points_mm: ArrayLike) -> FloatArray:
        """World points ``(N, 3)`` mm to this camera's frame ``(N, 3)`` mm."""
        pts = _as_points(points_mm, 3, "points_mm")
        return pts @ self.R_cam_from_world.T + self.t_cam_from_world_mm

    # -- projection ---------------------------------------------------------
    def project(self, points_mm: ArrayLike) -> FloatArray:
        """Project world points ``(N, 3)`` mm to distorted pixels ``(N, 2)``.

        Points on or behind the camera plane (z <= 0) give NaN.
        """
        cam = self.to_camera(points_mm)
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = cam[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        return self.normalized_to_pixels(distort_normalized(xy, self.dist))

    def normalized_to_pixels(self, xy_distorted: FloatArray) -> FloatArray:
        """Distorted normalized coordinates ``(N, 2)`` to pixels ``(N, 2)``."""
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        return np.column_stack([xy_distorted[:, 0] * fx + cx, xy_distorted[:, 1] * fy + cy])

    def pixels_to_normalized(self, pixels: ArrayLike) -> FloatArray:
        """Pixels ``(N, 2)`` to distorted normalized coordinates ``(N, 2)`` (no undistortion)."""
        px = _as_points(pixels, 2, "pixels")
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        return np.column_stack([(px[:, 0] - cx) / fx, (px[:, 1] - cy) / fy])

    # -- back-projection ----------------------------------------------------
    def undistort_points(self, pixels: ArrayLike) -> FloatArray:
        """Distorted pixels ``(N, 2)`` to undistorted normalized coordinates ``(N, 2)``.

        ``(x, y)`` is the direction ``(x, y, 1)`` in the camera frame. NaN in,
        NaN out; a pixel outside the invertible region of the lens model
        gives NaN.
        """
        return undistort_normalized(self.pixels_to_normalized(pixels), self.dist)

    def undistort_pixels(self, pixels: ArrayLike) -> FloatArray:
        """Distorted pixels ``(N, 2)`` to ideal (distortion-free) pixels ``(N, 2)`` with the same K."""
        return self.normalized_to_pixels(self.undistort_points(pixels))

    def backproject(self, pixels: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Rays through pixels: ``(origins (N, 3) mm, unit directions (N, 3))`` in world frame."""
        xy = self.undistort_points(pixels)
        d_cam = np.column_stack([xy, np.ones(len(xy))])
        d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
        d_world = d_cam @ self.R_cam_from_world  # R^T d for each row
        origins = np.broadcast_to(self.center_world_mm, d_world.shape).copy()
        return origins, d_world

    def backproject_depth(self, pixels: ArrayLike, depth_mm: ArrayLike) -> FloatArray:
        """World points ``(N, 3)`` at camera-frame depth ``z`` (mm) along the pixels' rays."""
        xy = self.undistort_points(pixels)
        z = np.broadcast_to(np.asarray(depth_mm, dtype=np.float64), (len(xy),))
        cam = np.column_stack([xy * z[:, None], z])
        return (cam - self.t_cam_from_world_mm) @ self.R_cam_from_world

    def in_image(self, pixels: ArrayLike, *, margin_px: float = 0.0) -> NDArray[np.bool_]:
        """Which pixels ``(N, 2)`` lie inside the image, ``margin_px`` away from its border."""
        px = _as_points(pixels, 2, "pixels")
        w, h = self.image_size
        with np.errstate(invalid="ignore"):
            return (
                (px[:, 0] >= -0.5 + margin_px)
                & (px[:, 0] <= w - 0.5 - margin_px)
                & (px[:, 1] >= -0.5 + margin_px)
                & (px[:, 1] <= h - 0.5 - margin_px)
            )

    # -- OpenCV interop -----------------------------------------------------
    @property
    def rvec(self) -> FloatArray:
        """Rodrigues vector of ``R_cam_from_world``, shape (3,)."""
        import cv2

        rvec, _ = cv2.Rodrigues(self.R_cam_from_world)
        return np.asarray(rvec, dtype=np.float64).reshape(3)


def skew(v: ArrayLike) -> FloatArray:
    """The cross-product matrix ``[v]_x`` of a 3-vector."""
    x, y, z = np.asarray(v, dtype=np.float64).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


@dataclass(frozen=True)
class StereoRig:
    """Two cameras; the world frame is the left camera's (``R = I, t = 0``).

    ``quality`` is free-form calibration quality (``rms_px`` and friends).
    """

    left: Camera
    right: Camera
    quality: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not np.allclose(self.left.R_cam_from_world, np.eye(3), atol=1e-9) or not np.allclose(
            self.left.t_cam_from_world_mm, 0.0, atol=1e-9
        ):
            raise ValueError("the left camera of a rig must have R = I and t = 0 (world frame)")

    @property
    def cameras(self) -> tuple[Camera, Camera]:
        return (self.left, self.right)

    @property
    def R_right_from_left(self) -> FloatArray:
        return self.right.R_cam_from_world

    @property
    def t_right_from_left_mm(self) -> FloatArray:
        return self.right.t_cam_from_world_mm

    @property
    def baseline_mm(self) -> float:
        """Distance between the two optical centres (mm)."""
        return float(np.linalg.norm(self.right.center_world_mm))

    @property
    def essential_matrix(self) -> FloatArray:
        """``E`` with ``x_right^T E x_left = 0`` for undistorted normalized homogeneous points."""
        return skew(self.t_right_from_left_mm) @ self.R_right_from_left

    def fundamental_matrix(self) -> FloatArray:
        """``F`` with ``u_right^T F u_left = 0`` for undistorted (ideal) pixels."""
        K1_inv = np.linalg.inv(self.left.K)
        K2_inv = np.linalg.inv(self.right.K)
        F = K2_inv.T @ self.essential_matrix @ K1_inv
        result: NDArray[np.float64] = F / np.linalg.norm(F)
        return result

    def swapped(self) -> StereoRig:
        """The same rig seen with left and right exchanged (world frame moves to the old right)."""
        R = self.right.R_cam_from_world
        t = self.right.t_cam_from_world_mm
        new_left = Camera(
            "left", self.right.image_size, self.right.K, self.right.dist,
            readout_ms=self.right.readout_ms,
        )  # fmt: skip
        new_right = Camera(
            "right", self.left.image_size, self.left.K, self.left.dist, R.T, -R.T @ t,
            readout_ms=self.left.readout_ms,
        )  # fmt: skip
        return StereoRig(new_left, new_right, dict(self.quality))


# -- rig file ---------------------------------------------------------------

RIG_FORMAT = "bradyscope.rig/1"


def rig_to_dict(rig: StereoRig) -> dict[str, Any]:
    """The rig as the JSON document of INTERFACES.md (``bradyscope.rig/1``)."""
    cams = []
    for cam in rig.cameras:
        cams.append(
            {
                "name": cam.name,
                "image_size": [cam.image_size.width, cam.image_size.height],
                "K": cam.K.tolist(),
                "dist": cam.dist.tolist(),
                "R": cam.R_cam_from_world.tolist(),
                "t": cam.t_cam_from_world_mm.tolist(),
            }
        )
        if cam.readout_ms > 0:
            cams[-1]["readout_ms"] = cam.readout_ms
    doc: dict[str, Any] = {"format": RIG_FORMAT, "units": "mm", "cameras": cams}
    if rig.quality:
        doc["quality"] = rig.quality
    return doc


# Physical bounds of a rig file (checked by :func:`rig_from_dict`).
MAX_IMAGE_SIDE_PX = 100_000
MAX_FOCAL_IMAGE_RATIO = 50.0
"""A focal length of at most 50 image sides: a field of view of about 1 degree."""
MIN_BASELINE_MM = 1.0
"""Below 1 mm two cameras cannot triangulate a hand at clinical distances."""
MAX_BASELINE_MM = 10_000.0
MAX_TRANSLATION_MM = 100_000.0


def _json_numbers(value: Any, shape: tuple[int, ...], what: str) -> FloatArray:
    """A nested list of JSON numbers of ``shape`` (``-1``: any length) as float64.

    Raises ``ValueError`` naming the entry that is text, true/false, null or not finite.
    """

    def walk(item: Any, depth: int, where: str) -> Any:
        if depth == len(shape):
            if isinstance(item, bool) or not isinstance(item, int | float):
                kind = "the text " + repr(item)[:20] if isinstance(item, str) else repr(item)[:20]
                raise ValueError(f"{where} is {kind}; it must be a JSON number")
            if not math.isfinite(float(item)):
                raise ValueError(f"{where} is {item}; it must be a finite number")
            return float(item)
        if not isinstance(item, list):
            raise ValueError(f"{where} must be a list, not {type(item).__name__}")
        if shape[depth] != -1 and len(item) != shape[depth]:
            raise ValueError(f"{where} must have {shape[depth]} entries, not {len(item)}")
        return [walk(x, depth + 1, f"{where}[{i}]") for i, x in enumerate(item)]

    return np.asarray(walk(value, 0, what), dtype=np.float64)


def _image_size(value: Any) -> ImageSize:
    sides = _json_numbers(value, (2,), "image_size")
    if not all(float(v).is_integer() and 1 <= v <= MAX_IMAGE_SIDE_PX for v in sides):
        raise ValueError(
            f"image_size must be two whole numbers of pixels between 1 and {MAX_IMAGE_SIDE_PX}"
            f" ([width, height]), got {sides.tolist()}"
        )
    return ImageSize(int(sides[0]), int(sides[1]))


def _check_intrinsics(K: FloatArray, size: ImageSize) -> None:
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    longest = max(size.width, size.height)
    for name, f in (("fx", fx), ("fy", fy)):
        if not 0 < f <= MAX_FOCAL_IMAGE_RATIO * longest:
            raise ValueError(
                f"the focal length {name}={f:g} px is impossible for a {size.width}x{size.height}"
                f" image (it must be above 0 and at most {MAX_FOCAL_IMAGE_RATIO:g} x {longest} px)"
            )
    if not (-0.5 <= cx <= size.width - 0.5 and -0.5 <= cy <= size.height - 0.5):
        raise ValueError(
            f"the principal point ({cx:g}, {cy:g}) px lies outside the {size.width}x{size.height}"
            " image"
        )


def rig_from_dict(doc: Any, *, source: str = "the rig file") -> StereoRig:
    """Parse a ``bradyscope.rig/1`` document; raise :class:`RigFileError` if it is unusable.

    Besides the format, the rig must be physically possible: every parameter a
    JSON number (not text such as ``"640"``, not ``true``), finite focal
    lengths above 0 and at most :data:`MAX_FOCAL_IMAGE_RATIO` image sides, the
    principal point inside the image, rotations that are rotation matrices, and
    a baseline between :data:`MIN_BASELINE_MM` and :data:`MAX_BASELINE_MM`.
    """
    from core.errors import RigFileError

    if not isinstance(doc, dict):
        raise RigFileError(f"{source} is not a JSON object; expected a bradyscope rig file.")
    fmt = doc.get("format")
    if fmt is None and "cameras" not in doc:
        raise RigFileError(
            f"{source} is not a rig file: it has neither 'format' nor 'cameras'; upload the"
            " rig.json that 'bradyscope calibrate' wrote."
        )
    if fmt != RIG_FORMAT:
        raise RigFileError(
            f"{source} has format {fmt!r}, but this version of bradyscope reads {RIG_FORMAT!r};"
            " re-export the rig or upgrade bradyscope."
        )
    units = doc.get("units", "mm")
    if units != "mm":
        raise RigFileError(f"{source} is in {units!r}; rig files must be in 'mm'.")
    cams = doc.get("cameras")
    if not isinstance(cams, list) or len(cams) != 2:
        raise RigFileError(f"{source} must list exactly two cameras (left, right).")
    parsed = []
    for i, (cam, expected) in enumerate(zip(cams, ("left", "right"), strict=True)):
        if not isinstance(cam, dict):
            raise RigFileError(f"camera {i} in {source} is not a JSON object.")
        missing = [k for k in ("image_size", "K", "dist", "R", "t") if k not in cam]
        if missing:
            raise RigFileError(f"camera {i} in {source} lacks {', '.join(missing)}.")
        name = cam.get("name", expected)
        if name != expected:
            raise RigFileError(f"camera {i} in {source} is named {name!r}; expected {expected!r}.")
        try:
            size = _image_size(cam["image_size"])
            K = _json_numbers(cam["K"], (3, 3), "K")
            _check_intrinsics(K, size)
            t = _json_numbers(cam["t"], (3,), "t")
            if float(np.linalg.norm(t)) > MAX_TRANSLATION_MM:
                raise ValueError(f"t is {float(np.linalg.norm(t)):g} mm long; that is no rig")
            readout = cam.get("readout_ms")
            parsed.append(
                Camera(
                    name=name,
                    image_size=size,
                    K=K,
                    dist=_json_numbers(cam["dist"], (-1,), "dist"),
                    R_cam_from_world=_json_numbers(cam["R"], (3, 3), "R"),
                    t_cam_from_world_mm=t,
                    readout_ms=0.0
                    if readout is None
                    else float(_json_numbers([readout], (1,), "readout_ms")[0]),
                )
            )
        except (TypeError, ValueError) as exc:
            raise RigFileError(f"camera {name!r} in {source} is invalid: {exc}.") from exc
    quality = doc.get("quality") or {}
    if not isinstance(quality, dict):
        raise RigFileError(f"'quality' in {source} must be a JSON object.")
    try:
        rig = StereoRig(parsed[0], parsed[1], quality)
    except ValueError as exc:
        raise RigFileError(f"{source} is invalid: {exc}.") from exc
    if not MIN_BASELINE_MM <= rig.baseline_mm <= MAX_BASELINE_MM:
        raise RigFileError(
            f"{source} puts the two cameras {rig.baseline_mm:g} mm apart; a stereo rig needs a"
            f" baseline between {MIN_BASELINE_MM:g} and {MAX_BASELINE_MM:g} mm (check the right"
            " camera's t)."
        )
    return rig


def write_rig(rig: StereoRig, path: str | Any) -> None:
    """Write the rig file (pretty-printed JSON)."""
    import json
    from pathlib import Path

    Path(path).write_text(json.dumps(rig_to_dict(rig), indent=2) + "\n", encoding="utf-8")


def read_rig(path: str | Any) -> StereoRig:
    """Read a rig file; raise :class:`RigFileError` with a clear message if it is unusable."""
    import json
    from pathlib import Path

    from core.errors import RigFileError

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise RigFileError(f"cannot read the rig file {p.name}: {exc.strerror}.") from exc
    except UnicodeDecodeError as exc:
        raise RigFileError(
            f"{p.name} is not a text file; expected a bradyscope rig JSON file."
        ) from exc
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RigFileError(
            f"{p.name} is not valid JSON (line {exc.lineno}, column {exc.colno}); expected a rig file."
        ) from exc
    except RecursionError as exc:
        raise RigFileError(
            f"{p.name} is nested too deeply to be a rig file; expected a bradyscope rig JSON file."
        ) from exc
    return rig_from_dict(doc, source=p.name)

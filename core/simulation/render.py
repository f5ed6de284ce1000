"""Camera images of retro-reflective markers under an infrared ring light.

The image model (see ``docs/simulator.md``):

- **Markers** are spheres of radius ``R`` whose image is a bright disc. The
  disc is the first-order (affine) image of the sphere's silhouette cone about
  the *projection of its centre*: a pixel ``q`` is mapped to the angle
  ``a = J^-1 (q - project(C))`` from the viewing ray through the centre, where
  ``J`` (px/rad) is the Jacobian of the full camera projection (distortion
  included) in the plane perpendicular to that ray. The silhouette is
  ``|a| <= asin(R / |C - O|)``. Because the profile is point-symmetric about
  ``project(C)``, the intensity centroid of an isolated, noise-free marker is
  the projection of its centre (up to sampling, well below 0.01 px; the
  neglected second-order terms shift the true perspective silhouette by
  ``~ f (R/D)^2 tan(theta)`` px, 0.02 px for a 5 mm marker at 500 mm seen
  30 degrees off axis).
- The disc is brightest in the middle (slight limb darkening) and its edge is
  the disc convolved with the lens blur and the pixel's box (Gaussian of
  ``sqrt(psf_sigma_px^2 + 1/12)`` px): an analytic, anti-aliased edge.
- **Motion blur**: the image of one frame is the mean of the images at
  ``S`` instants spread evenly over the exposure.
- **Glints** (spurious reflections) use a Gaussian profile instead of a disc.
- **Sensor**: a dark, slightly textured background with ring-light
  vignetting, Gaussian read noise, and shot noise on the bright markers.

Only small patches around the objects are computed; the full frame is the
background plus noise, added with whole-array operations.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import erfc

from core.camera import Camera, FloatArray, ImageSize

DISC = "disc"
GLINT = "glint"
_PROFILES = (DISC, GLINT)
_SQRT2 = np.sqrt(2.0)


@dataclass(frozen=True)
class SphereLayer:
    """Objects to draw into one frame of one camera.

    Attributes
    ----------
    centres_mm : ndarray, shape (S, N, 3)
        World positions (mm) of ``N`` objects at ``S`` instants of the exposure.
    radius_mm : ndarray, shape (N,)
    peak : ndarray, shape (N,)
        Brightness in gray levels above the background; 0 skips an object
        (e.g. occluded). A scalar broadcasts.
    profile : {"disc", "glint"}
    """

    centres_mm: FloatArray
    radius_mm: FloatArray
    peak: FloatArray
    profile: str = DISC

    def __post_init__(self) -> None:
        c = np.asarray(self.centres_mm, dtype=np.float64)
        if c.ndim == 2:
            c = c[None]
        if c.ndim != 3 or c.shape[2] != 3:
            raise ValueError(f"centres_mm must have shape (S, N, 3), got {c.shape}")
        n = c.shape[1]
        r = np.broadcast_to(np.asarray(self.radius_mm, dtype=np.float64), (n,))
        p = np.broadcast_to(np.asarray(self.peak, dtype=np.float64), (n,))
        if np.any(r <= 0):
            raise ValueError(f"radius_mm must be positive, got {r}")
        if self.profile not in _PROFILES:
            raise ValueError(f"profile must be one of {_PROFILES}, got {self.profile!r}")
        object.__setattr__(self, "centres_mm", c)
        object.__setattr__(self, "radius_mm", r)
        object.__setattr__(self, "peak", p)


def _jacobians(camera: Camera, centres_mm: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Projected centres ``(P, 2)``, projection Jacobians ``(P, 2, 2)`` px/rad, distances ``(P,)``.

    The Jacobian maps small angles ``(a1, a2)`` about the viewing ray, along two
    unit vectors perpendicular to it, to pixel displacements (central
    differences through :meth:`Camera.project`, so distortion is included).
    """
    origin = camera.center_world_mm
    ray = centres_mm - origin
    dist = np.linalg.norm(ray, axis=1)
    ray_u = ray / dist[:, None]
    x_axis = camera.R_cam_from_world[0]
    e1 = x_axis[None, :] - (ray_u @ x_axis)[:, None] * ray_u
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(ray_u, e1)
    h = 1e-4  # rad
    step1 = (h * dist)[:, None] * e1
    step2 = (h * dist)[:, None] * e2
    pts = np.concatenate(
        [centres_mm, centres_mm + step1, centres_mm - step1, centres_mm + step2, centres_mm - step2]
    )
    px = camera.project(pts).reshape(5, -1, 2)
    J = np.stack([(px[1] - px[2]) / (2 * h), (px[3] - px[4]) / (2 * h)], axis=2)
    return px[0], J, dist


def draw_spheres(
    canvas: NDArray[np.float32],
    camera: Camera,
    layer: SphereLayer,
    *,
    limb_darkening: float = 0.25,
    psf_sigma_px: float = 0.5,
    shot_noise: tuple[np.random.Generator, float] | None = None,
) -> None:
    """Add the images of spheres (averaged over the exposure) to ``canvas`` in place.

    Parameters
    ----------
    canvas : ndarray, shape (H, W), float32
        Image in gray levels; objects are added to it.
    camera : Camera
    layer : SphereLayer
    limb_darkening : float
        Relative intensity loss at the rim of a disc (0 = flat).
    psf_sigma_px : float
        Standard deviation of the lens blur (px).
    shot_noise : (Generator, gain), optional
        Add Poisson-like noise of standard deviation ``sqrt(gain * signal)``
        (gray levels) to the drawn signal.
    """
    if canvas.ndim != 2 or canvas.dtype != np.float32:
        raise ValueError(f"canvas must be float32 (H, W), got {canvas.dtype} {canvas.shape}")
    patches = sphere_patches(
        ImageSize.of_image(canvas),
        camera,
        layer,
        limb_darkening=limb_darkening,
        psf_sigma_px=psf_sigma_px,
        shot_noise=shot_noise,
    )
    add_patches(canvas, patches)


@dataclass(frozen=True)
class Patch:
    """What one object adds to a frame: float32 gray levels over rows ``y0:y1``, columns
    ``x0:x1``."""

    y0: int
    y1: int
    x0: int
    x1: int
    values: NDArray[np.float32]


def add_patches(canvas: NDArray[np.float32], patches: list[Patch]) -> None:
    """Add ``patches`` to ``canvas`` in place, in their order."""
    for p in patches:
        canvas[p.y0 : p.y1, p.x0 : p.x1] += p.values


def sphere_patches(
    size: ImageSize,
    camera: Camera,
    layer: SphereLayer,
    *,
    limb_darkening: float = 0.25,
    psf_sigma_px: float = 0.5,
    shot_noise: tuple[np.random.Generator, float] | None = None,
) -> list[Patch]:
    """What :func:`draw_spheres` adds to a frame of ``size``, one patch per drawn object in
    drawing order; without shot noise, the same patches every time (a static scene's can
    be kept and added again to each frame)."""
    S, N, _ = layer.centres_mm.shape
    cam_pts = camera.to_camera(layer.centres_mm.reshape(-1, 3)).reshape(S, N, 3)
    in_front = np.all(cam_pts[..., 2] > 3 * layer.radius_mm[None, :], axis=0)
    todo = np.flatnonzero((layer.peak > 0) & in_front)
    patches: list[Patch] = []
    if len(todo) == 0:
        return patches
    sub = layer.centres_mm[:, todo].reshape(-1, 3)
    centre_px, J, dist = _jacobians(camera, sub)
    n = len(todo)
    centre_px = centre_px.reshape(S, n, 2)
    J = J.reshape(S, n, 2, 2)
    alpha = np.arcsin(np.clip(layer.radius_mm[todo][None, :] / dist.reshape(S, n), 0, 1))  # rad
    sigma_px = float(np.sqrt(psf_sigma_px**2 + 1.0 / 12.0))
    for j, obj in enumerate(todo):
        c = centre_px[:, j]  # (S, 2)
        if not np.all(np.isfinite(c)):
            continue
        Jj = J[:, j]  # (S, 2, 2)
        a_j = alpha[:, j]  # (S,)
        # Half extent of the ellipse along x and y, plus the blurred edge.
        ext = np.sqrt(np.sum(Jj**2, axis=2)) * a_j[:, None]  # (S, 2)
        pad = (4.0 * sigma_px + 1.0) if layer.profile == DISC else 0.0
        lo = np.floor(np.min(c - ext * (1.0 if layer.profile == DISC else 4.0), axis=0) - pad)
        hi = np.ceil(np.max(c + ext * (1.0 if layer.profile == DISC else 4.0), axis=0) + pad)
        x0, y0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
        x1, y1 = min(int(hi[0]) + 1, size.width), min(int(hi[1]) + 1, size.height)
        if x1 <= x0 or y1 <= y0:
            continue
        xs = np.arange(x0, x1, dtype=np.float64)
        ys = np.arange(y0, y1, dtype=np.float64)
        dx = xs[None, None, :] - c[:, 0, None, None]  # (S, 1, w)
        dy = ys[None, :, None] - c[:, 1, None, None]  # (S, h, 1)
        Jinv = np.linalg.inv(Jj)  # (S, 2, 2) rad/px
        a1 = Jinv[:, 0, 0, None, None] * dx + Jinv[:, 0, 1, None, None] * dy
        a2 = Jinv[:, 1, 0, None, None] * dx + Jinv[:, 1, 1, None, None] * dy
        r = np.sqrt(a1 * a1 + a2 * a2)  # (S, h, w) rad
        px_per_rad = np.sqrt(np.abs(np.linalg.det(Jj)))[:, None, None]
        if layer.profile == DISC:
            rho = np.minimum(r / a_j[:, None, None], 1.0)
            edge_px = (r - a_j[:, None, None]) * px_per_rad
            img = (1.0 - limb_darkening * rho * rho) * (0.5 * erfc(edge_px / (_SQRT2 * sigma_px)))
        else:
            img = np.exp(-0.5 * (r / a_j[:, None, None]) ** 2)
        patch = (layer.peak[obj] / S) * img.sum(axis=0)
        if shot_noise is not None:
            rng, gain = shot_noise
            patch += np.sqrt(gain * patch) * rng.standard_normal(patch.shape)
        patches.append(Patch(y0, y1, x0, x1, patch.astype(np.float32)))
    return patches


def make_background(
    image_size: ImageSize,
    *,
    rng: np.random.Generator,
    level: float = 14.0,
    texture: float = 5.0,
) -> NDArray[np.float32]:
    """A dark, slightly textured background lit by a ring light, ``(H, W)`` float32 gray levels.

    Smooth blotches (out-of-focus room seen in infrared), a fine texture, and
    vignetting (the ring light lights the middle of the scene best).
    """
    w, h = ImageSize(*image_size)
    coarse = rng.standard_normal((max(h // 64, 2) + 1, max(w // 64, 2) + 1)).astype(np.float32)
    blotches = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 1.2)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((xx - w / 2) / (w / 2)) ** 2 + ((yy - h / 2) / (h / 2)) ** 2
    vignette = 1.0 - 0.35 * r2
    bg = level * vignette + texture * (0.7 * blotches + 1.5 * fine)
    result: NDArray[np.float32] = np.clip(bg, 0.0, 255.0).astype(np.float32)
    return result


class SensorNoise:
    """Gaussian read noise for whole frames, cheap per frame.

    A buffer of ``2 * H * W`` normal deviates is drawn once; each frame takes a
    window starting at a random offset, so consecutive frames get different
    (shifted) noise for the price of a slice.
    """

    def __init__(self, image_size: ImageSize, *, sigma: float, rng: np.random.Generator) -> None:
        if sigma < 0:
            raise ValueError(f"noise sigma must be >= 0, got {sigma}")
        w, h = ImageSize(*image_size)
        self._shape = (h, w)
        self._n = h * w
        self._rng = rng
        self._buffer = (
            (rng.standard_normal(2 * self._n) * sigma).astype(np.float32) if sigma > 0 else None
        )
        self._work: NDArray[np.float32] | None = None  # frame_u8's canvas, made on first use

    def noisy(self, background: NDArray[np.float32]) -> NDArray[np.float32]:
        """A new frame: ``background`` (float32, (H, W)) plus one frame of noise."""
        noise = self._next_noise()
        if noise is None:
            return background.copy()
        return np.asarray(cv2.add(background, noise), dtype=np.float32)

    def frame_u8(self, background: NDArray[np.float32], patches: list[Patch]) -> NDArray[np.uint8]:
        """``to_uint8`` of a new frame (``background`` plus one frame of noise, as
        :meth:`noisy` gives it) with ``patches`` added in their order: the same bytes,
        but the full frame goes through one pass and only the patches' boxes through the
        floating-point canvas."""
        noise = self._next_noise()
        if noise is None:
            out = to_uint8(background)
        else:
            out = np.asarray(cv2.add(background, noise, dtype=cv2.CV_8U), dtype=np.uint8)
        if not patches:
            return out
        if self._work is None:
            self._work = np.empty(self._shape, dtype=np.float32)
        work = self._work
        boxes = [(slice(p.y0, p.y1), slice(p.x0, p.x1)) for p in patches]
        for box in boxes:  # the noisy background where an object lands (boxes may overlap)
            if noise is None:
                work[box] = background[box]
            else:
                np.add(background[box], noise[box], out=work[box])
        add_patches(work, patches)
        for box in boxes:
            out[box] = to_uint8(work[box])
        return out

    def _next_noise(self) -> NDArray[np.float32] | None:
        """One frame of noise (a view of the buffer), or None without noise."""
        if self._buffer is None:
            return None
        off = int(self._rng.integers(0, self._n))
        return self._buffer[off : off + self._n].reshape(self._shape)

    def add_to(self, frame: NDArray[np.float32]) -> None:
        """Add one frame of noise to ``frame`` (float32, (H, W)) in place."""
        noise = self._next_noise()
        if noise is not None:
            frame += noise


def to_uint8(frame: NDArray[np.float32]) -> NDArray[np.uint8]:
    """Round and saturate a float image to 8 bits (``frame`` is left unchanged)."""
    _, positive = cv2.threshold(frame, 0.0, 0.0, cv2.THRESH_TOZERO)
    return np.asarray(cv2.convertScaleAbs(positive), dtype=np.uint8)  # rounds, saturates at 255


def intensity_centroid(patch: ArrayLike, *, x0: int = 0, y0: int = 0) -> FloatArray:
    """Intensity-weighted centroid ``(x, y)`` (px, OpenCV convention) of an image patch."""
    img = np.asarray(patch, dtype=np.float64)
    total = img.sum()
    if not total > 0:
        raise ValueError("the patch has no positive intensity")
    ys, xs = np.indices(img.shape)
    return np.array([(xs * img).sum() / total + x0, (ys * img).sum() / total + y0])

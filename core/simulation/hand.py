"""An infrared-lit hand: skin surfaces, their image under a ring light, markers on them.

Reusable by any task of the simulator (finger tapping here; other MDS-UPDRS
tasks build their own :class:`Capsules`). Three pieces:

- **Geometry** (:class:`Capsules`): the skin at one instant as tapered
  capsules (a segment with a radius at each end) in world coordinates (mm).
  :func:`tapping_hand` builds the hand of the finger-tapping model: index and
  thumb from the joints to the fingertips, their nails under the markers, the
  back of the hand, the curled middle to little fingers, the thenar eminence
  and the forearm.
- **Rendering** (:func:`draw_skin`): each capsule is drawn from the
  projection of its axis (the exact camera model, distortion included) and
  its perspective radius; at a pixel the capsule's surface faces the camera
  by ``h = sqrt(1 - (d / rho)^2)`` (``d`` the distance to the projected axis,
  ``rho`` the projected radius), which gives its depth (a z-buffer decides
  who is in front) and its shading under a light next to the lens
  (``SkinLook``: Lambert with a wrap term for the light that skin scatters
  below its surface, and the inverse square of the distance). Silhouettes are
  anti-aliased over one pixel and the skin image is softened by a Gaussian
  (defocus and lens).
- **Markers over skin** (:func:`composite_spheres`): the markers replace what
  is behind them (they are opaque), are hidden by skin in front of them (per
  pixel, depth against the z-buffer) and by each other (nearer over farther);
  each marker's **visible fraction** (its sharp disc area not hidden by skin
  or by a nearer marker, over the exposure) is returned: the truth of how
  much of it each camera saw.

:func:`overlap_orientation_deg` finds the posture in which the closed
fingertip markers overlap in one camera's image; :func:`nail_glints` adds the
specular highlights of nail polish next to the markers.

Units: mm, px, gray levels; world = the rig's (left camera's) frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.special import erfc

from core.camera import Camera, FloatArray, ImageSize
from core.simulation.kinematics import TappingModel, TappingScenario, simulate_tapping
from core.simulation.render import DISC, GLINT, SphereLayer, _jacobians

_SQRT2 = float(np.sqrt(2.0))
_BOX_SIGMA_PX = float(np.sqrt(1.0 / 12.0))  # a pixel's box, as a Gaussian

# --------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class Capsules:
    """Skin surfaces at one instant: tapered capsules in world coordinates.

    Capsule ``k`` is the union of the spheres centred on the segment
    ``starts_mm[k] -> ends_mm[k]`` with radii varying linearly from
    ``start_radius_mm[k]`` to ``end_radius_mm[k]``.

    Attributes
    ----------
    starts_mm, ends_mm : ndarray, shape (K, 3)
    start_radius_mm, end_radius_mm : ndarray, shape (K,)
    """

    starts_mm: FloatArray
    ends_mm: FloatArray
    start_radius_mm: FloatArray
    end_radius_mm: FloatArray

    def __post_init__(self) -> None:
        a = np.asarray(self.starts_mm, dtype=np.float64).reshape(-1, 3)
        b = np.asarray(self.ends_mm, dtype=np.float64).reshape(-1, 3)
        if a.shape != b.shape:
            raise ValueError(f"starts_mm and ends_mm differ in shape: {a.shape} vs {b.shape}")
        ra = np.broadcast_to(np.asarray(self.start_radius_mm, dtype=np.float64), (len(a),))
        rb = np.broadcast_to(np.asarray(self.end_radius_mm, dtype=np.float64), (len(a),))
        if np.any(ra <= 0) or np.any(rb <= 0):
            raise ValueError("capsule radii must be positive")
        object.__setattr__(self, "starts_mm", a)
        object.__setattr__(self, "ends_mm", b)
        object.__setattr__(self, "start_radius_mm", np.array(ra))
        object.__setattr__(self, "end_radius_mm", np.array(rb))

    def __len__(self) -> int:
        return len(self.starts_mm)


# Hand geometry of the finger-tapping model, hand frame of a right hand (mm): origin at
# the index MCP joint, u distal along the index, v radial ("up", thumb side), w dorsal.
# Rigid parts: (start, end, start radius, end radius).
HAND_RIGID_CAPSULES_MM: tuple[
    tuple[tuple[float, float, float], tuple[float, float, float], float, float], ...
] = (
    # the back of the hand over the metacarpals (index, middle, ring, little)
    ((-85.0, -2.0, -5.0), (-3.0, 0.0, -5.0), 13.0, 13.0),
    ((-85.0, -22.0, -5.0), (-3.0, -22.0, -5.0), 13.0, 13.0),
    ((-85.0, -42.0, -5.0), (-5.0, -42.0, -5.0), 13.0, 12.0),
    ((-85.0, -58.0, -6.0), (-10.0, -60.0, -6.0), 12.0, 11.0),
    # the middle, ring and little fingers curled into the palm
    ((-3.0, -22.0, -5.0), (28.0, -22.0, -30.0), 9.0, 8.5),
    ((28.0, -22.0, -30.0), (8.0, -22.0, -46.0), 8.5, 7.5),
    ((-5.0, -42.0, -5.0), (24.0, -42.0, -29.0), 8.5, 8.0),
    ((24.0, -42.0, -29.0), (6.0, -42.0, -44.0), 8.0, 7.0),
    ((-10.0, -60.0, -6.0), (14.0, -60.0, -26.0), 7.5, 7.0),
    ((14.0, -60.0, -26.0), (0.0, -60.0, -38.0), 7.0, 6.5),
    # the thenar eminence (the base of the thumb)
    ((-80.0, -6.0, -16.0), (-40.0, -12.0, -24.0), 16.0, 12.0),
    # the wrist and the forearm
    ((-85.0, -32.0, -5.0), (-330.0, -40.0, -5.0), 27.0, 33.0),
)
#: The index finger from the MCP joint (origin) to its tip; radius at the joint and the tip.
INDEX_RADII_MM = (9.5, 6.5)
#: The thumb from its base (CMC joint) to its tip.
THUMB_BASE_LOCAL_MM = (-50.0, -10.0, -20.0)
THUMB_RADII_MM = (11.0, 7.5)
#: Finger radius under the nail, and the gap between nail and marker sphere (its base).
NAIL_FINGER_RADIUS_MM = 7.0
MARKER_BASE_MM = 0.5
#: How far the fingertip reaches beyond the point under the marker (mm).
TIP_BEYOND_MARKER_MM = 9.0


def _unit(v: FloatArray) -> FloatArray:
    return np.asarray(v / np.linalg.norm(v, axis=-1, keepdims=True), dtype=np.float64)


def nail_normals_local(model: TappingModel) -> tuple[FloatArray, FloatArray]:
    """Unit dorsal normals of the thumb and index nails in the hand frame ``(3,)`` each.

    The index nail faces w (the back of the hand); the thumb nail faces w
    tilted away from the index (the thumb opposes the index from below), so
    that at a closure the pulps of the two fingertips touch.
    """
    closed = model.local_positions_mm(np.array([-1e3]))[0]  # fingers closed (before any tap)
    towards_thumb = _unit(closed[0] - closed[1])
    w = np.array([0.0, 0.0, 1.0])
    return _unit(w + 0.35 * towards_thumb), w


def tapping_hand(model: TappingModel, t_s: float, *, marker_radius_mm: float) -> Capsules:
    """The skin of the finger-tapping hand at time ``t_s`` (world frame, mm).

    The markers sit on the nails: the finger's axis runs
    ``NAIL_FINGER_RADIUS_MM + MARKER_BASE_MM + marker_radius_mm`` below each
    marker centre (along the nail normal), so every marker trajectory of the
    kinematic model is unchanged and the fingers follow them.

    Parameters
    ----------
    model : TappingModel
    t_s : float
        Time (s).
    marker_radius_mm : float

    Returns
    -------
    Capsules
        Index, thumb, then ``HAND_RIGID_CAPSULES_MM``.
    """
    t = np.array([float(t_s)])
    markers = model.local_positions_mm(t)[0]
    n_thumb, n_index = nail_normals_local(model)
    lift = NAIL_FINGER_RADIUS_MM + MARKER_BASE_MM + marker_radius_mm
    index_nail = markers[1] - lift * n_index
    index_tip = index_nail + TIP_BEYOND_MARKER_MM * _unit(index_nail)
    thumb_base = np.asarray(THUMB_BASE_LOCAL_MM)
    thumb_nail = markers[0] - lift * n_thumb
    thumb_tip = thumb_nail + TIP_BEYOND_MARKER_MM * _unit(thumb_nail - thumb_base)
    rigid = np.array([[*a, *b, ra, rb] for a, b, ra, rb in HAND_RIGID_CAPSULES_MM])
    starts = np.vstack([np.zeros(3), thumb_base, rigid[:, :3]])
    ends = np.vstack([index_tip, thumb_tip, rigid[:, 3:6]])
    world = model.hand_points_mm(t, np.vstack([starts, ends]))[0]
    k = len(starts)
    return Capsules(
        starts_mm=world[:k],
        ends_mm=world[k:],
        start_radius_mm=np.concatenate([[INDEX_RADII_MM[0], THUMB_RADII_MM[0]], rigid[:, 6]]),
        end_radius_mm=np.concatenate([[INDEX_RADII_MM[1], THUMB_RADII_MM[1]], rigid[:, 7]]),
    )


# --------------------------------------------------------------------------- skin image


@dataclass(frozen=True)
class SkinLook:
    """How skin looks under the ring light (see ``docs/simulator.md`` for the sources).

    Attributes
    ----------
    level : float
        Gray level of skin that faces the camera at ``reference_distance_mm``.
    reference_distance_mm : float
        Brightness falls with the inverse square of the distance from it.
    wrap : float
        Brightness at a silhouette relative to a facing surface is
        ``wrap / (1 + wrap)``: skin scatters light below its surface, so its
        edges do not go black as a Lambertian surface's would.
    blur_px : float
        Softness of the skin image (px, Gaussian sigma): lens and defocus.
    """

    level: float
    reference_distance_mm: float = 500.0
    wrap: float = 0.25
    blur_px: float = 0.7

    def __post_init__(self) -> None:
        if not 0 <= self.level <= 255:
            raise ValueError(f"skin level must be in [0, 255], got {self.level}")
        if not self.reference_distance_mm > 0:
            raise ValueError(
                f"reference_distance_mm must be positive, got {self.reference_distance_mm}"
            )
        if not 0 <= self.wrap <= 10:
            raise ValueError(f"wrap must be in [0, 10], got {self.wrap}")
        if not 0 <= self.blur_px <= 10:
            raise ValueError(f"blur_px must be in [0, 10], got {self.blur_px}")


@dataclass(frozen=True)
class SkinImage:
    """The skin drawn into one frame of one camera, for the markers drawn after it.

    Attributes
    ----------
    x0, y0 : int
        Top-left pixel of the patch.
    depth_mm : ndarray, shape (h, w), float32
        Depth (camera z, mm) of the front-most skin, spread by one pixel over
        its anti-aliased silhouettes; ``inf`` where there is no skin.
    coverage : ndarray, shape (h, w), float32
        Softened share of each pixel that skin covers (0-1).
    """

    x0: int
    y0: int
    depth_mm: NDArray[np.float32]
    coverage: NDArray[np.float32]

    def occluding(self, x0: int, y0: int, depth_mm: FloatArray) -> FloatArray:
        """Share of each pixel hidden by skin in front of a surface at ``depth_mm``.

        Parameters
        ----------
        x0, y0 : int
            Top-left pixel of the surface's patch.
        depth_mm : ndarray, shape (..., h, w)
            Depth of the surface at each pixel of the patch.

        Returns
        -------
        ndarray, shape of ``depth_mm``
            0 where nothing hides the surface, up to 1.
        """
        h, w = depth_mm.shape[-2:]
        out = np.zeros(depth_mm.shape, dtype=np.float64)
        sh, sw = self.depth_mm.shape
        ax0, ay0 = max(x0, self.x0), max(y0, self.y0)
        ax1, ay1 = min(x0 + w, self.x0 + sw), min(y0 + h, self.y0 + sh)
        if ax1 <= ax0 or ay1 <= ay0:
            return out
        skin_z = self.depth_mm[ay0 - self.y0 : ay1 - self.y0, ax0 - self.x0 : ax1 - self.x0]
        cov = self.coverage[ay0 - self.y0 : ay1 - self.y0, ax0 - self.x0 : ax1 - self.x0]
        sub = depth_mm[..., ay0 - y0 : ay1 - y0, ax0 - x0 : ax1 - x0]
        out[..., ay0 - y0 : ay1 - y0, ax0 - x0 : ax1 - x0] = np.where(skin_z < sub, cov, 0.0)
        return out


def draw_skin(
    canvas: NDArray[np.float32], camera: Camera, capsules: Capsules, look: SkinLook
) -> SkinImage | None:
    """Draw IR-lit skin into ``canvas`` in place (it replaces what is behind it).

    Parameters
    ----------
    canvas : ndarray, shape (H, W), float32
        Gray levels (the background).
    camera : Camera
    capsules : Capsules
    look : SkinLook

    Returns
    -------
    SkinImage or None
        The depth and coverage of the skin (for :func:`composite_spheres`);
        None when no skin is in the image.
    """
    if canvas.ndim != 2 or canvas.dtype != np.float32:
        raise ValueError(f"canvas must be float32 (H, W), got {canvas.dtype} {canvas.shape}")
    k = len(capsules)
    if k == 0 or look.level <= 0:
        return None
    size = ImageSize.of_image(canvas)
    ends = np.vstack([capsules.starts_mm, capsules.ends_mm])
    z = camera.to_camera(ends)[:, 2].reshape(2, k)
    px = camera.project(ends).reshape(2, k, 2)
    f = 0.5 * (camera.K[0, 0] + camera.K[1, 1])
    radii = np.vstack([capsules.start_radius_mm, capsules.end_radius_mm])  # (2, K) mm
    ok = np.all(z > 10.0, axis=0) & np.all(np.isfinite(px), axis=(0, 2))
    if not np.any(ok):
        return None
    rho = f * radii / np.where(z > 10.0, z, np.inf)  # (2, K) px
    pad = 3.0 * look.blur_px + 2.0
    lo = np.min(px - rho[..., None], axis=0) - pad  # (K, 2)
    hi = np.max(px + rho[..., None], axis=0) + pad
    boxes = np.column_stack(
        [
            np.clip(np.floor(lo[:, 0]), 0, size.width),
            np.clip(np.floor(lo[:, 1]), 0, size.height),
            np.clip(np.ceil(hi[:, 0]) + 1, 0, size.width),
            np.clip(np.ceil(hi[:, 1]) + 1, 0, size.height),
        ]
    ).astype(np.int64)
    ok &= (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    if not np.any(ok):
        return None
    x0, y0 = int(boxes[ok, 0].min()), int(boxes[ok, 1].min())
    x1, y1 = int(boxes[ok, 2].max()), int(boxes[ok, 3].max())
    skin = np.zeros((y1 - y0, x1 - x0), np.float32)
    cov = np.zeros_like(skin)
    zbuf = np.full_like(skin, np.inf)
    z_ref2 = float(look.reference_distance_mm) ** 2
    wrap = float(look.wrap)
    for j in np.flatnonzero(ok):
        bx0, by0, bx1, by1 = (int(v) for v in boxes[j])
        xs = np.arange(bx0, bx1, dtype=np.float32)[None, :]
        ys = np.arange(by0, by1, dtype=np.float32)[:, None]
        ax, ay = (float(v) for v in px[0, j])
        ex, ey = float(px[1, j, 0]) - ax, float(px[1, j, 1]) - ay
        len2 = ex * ex + ey * ey
        dx, dy = xs - np.float32(ax), ys - np.float32(ay)
        if len2 > 1e-9:
            t = np.clip((dx * np.float32(ex) + dy * np.float32(ey)) / np.float32(len2), 0.0, 1.0)
        else:
            t = np.zeros((by1 - by0, bx1 - bx0), np.float32)
        qx, qy = dx - t * np.float32(ex), dy - t * np.float32(ey)
        d = np.sqrt(qx * qx + qy * qy)
        rho_t = np.float32(rho[0, j]) + t * np.float32(rho[1, j] - rho[0, j])
        c = np.clip(rho_t - d + 0.5, 0.0, 1.0)  # anti-aliased over one pixel
        u = np.minimum(d / rho_t, 1.0)
        h = np.sqrt(1.0 - u * u)
        r_mm = np.float32(radii[0, j]) + t * np.float32(radii[1, j] - radii[0, j])
        depth = np.float32(z[0, j]) + t * np.float32(z[1, j] - z[0, j]) - r_mm * h
        shade = (np.float32(look.level) * np.float32(z_ref2)) / (depth * depth)
        shade *= (h + np.float32(wrap)) / np.float32(1.0 + wrap)
        sl = (slice(by0 - y0, by1 - y0), slice(bx0 - x0, bx1 - x0))
        s_sk, s_cov, s_z = skin[sl], cov[sl], zbuf[sl]
        front = depth < s_z
        # nearer than what is there: over; farther: under (order-independent compositing)
        s_sk[...] = np.where(front, shade * c + s_sk * (1.0 - c), s_sk + shade * c * (1.0 - s_cov))
        s_cov[...] = np.where(front, c + s_cov * (1.0 - c), s_cov + c * (1.0 - s_cov))
        s_z[...] = np.where(front & (c >= 0.5), depth, s_z)
    if look.blur_px > 0:
        skin = np.asarray(cv2.GaussianBlur(skin, (0, 0), look.blur_px), dtype=np.float32)
        cov = np.asarray(cv2.GaussianBlur(cov, (0, 0), look.blur_px), dtype=np.float32)
    depth_front = np.asarray(cv2.erode(zbuf, np.ones((3, 3), np.uint8)), dtype=np.float32)
    sub = canvas[y0:y1, x0:x1]
    sub *= 1.0 - cov
    sub += skin
    return SkinImage(x0=x0, y0=y0, depth_mm=depth_front, coverage=cov)


# --------------------------------------------------------------------------- markers


@dataclass
class _Patch:
    x0: int
    y0: int
    alpha: FloatArray  # (S, h, w) blurred coverage, visible part
    value: FloatArray  # (S, h, w) brightness times alpha
    sharp: FloatArray  # (S, h, w) pixel-box coverage (the disc's area)
    hidden_by_skin: FloatArray  # (S, h, w)
    depth: float


def composite_spheres(
    canvas: NDArray[np.float32],
    camera: Camera,
    layer: SphereLayer,
    skin: SkinImage | None,
    *,
    limb_darkening: float = 0.25,
    psf_sigma_px: float = 0.5,
    shot_noise: tuple[np.random.Generator, float] | None = None,
) -> FloatArray:
    """Draw opaque spheres over ``canvas`` (in place), hidden where skin or a nearer
    sphere is in front; return each sphere's visible fraction.

    Same image model as :func:`core.simulation.render.draw_spheres` (first-order
    image of the sphere about the projection of its centre, limb darkening,
    Gaussian edge of ``sqrt(psf_sigma_px^2 + 1/12)`` px, the mean over the
    exposure's sub-samples), but a sphere *replaces* what is behind it
    instead of adding to it.

    Parameters
    ----------
    canvas : ndarray, shape (H, W), float32
    camera : Camera
    layer : SphereLayer
        Disc profile only.
    skin : SkinImage or None
        What :func:`draw_skin` returned for this frame and camera.
    limb_darkening, psf_sigma_px, shot_noise
        As in :func:`~core.simulation.render.draw_spheres`.

    Returns
    -------
    ndarray, shape (N,)
        Visible fraction of each sphere's image (mean over the exposure): 1 when
        nothing hides it, 0 when hidden, not drawn (peak 0) or behind the camera.
    """
    if canvas.ndim != 2 or canvas.dtype != np.float32:
        raise ValueError(f"canvas must be float32 (H, W), got {canvas.dtype} {canvas.shape}")
    if layer.profile != DISC:
        raise ValueError(f"composite_spheres draws discs, got profile {layer.profile!r}")
    size = ImageSize.of_image(canvas)
    S, N, _ = layer.centres_mm.shape
    visible = np.zeros(N)
    cam_pts = camera.to_camera(layer.centres_mm.reshape(-1, 3)).reshape(S, N, 3)
    in_front = np.all(cam_pts[..., 2] > 3 * layer.radius_mm[None, :], axis=0)
    todo = np.flatnonzero((layer.peak > 0) & in_front)
    if len(todo) == 0:
        return visible
    sub = layer.centres_mm[:, todo].reshape(-1, 3)
    centre_px, J, dist = _jacobians(camera, sub)
    n = len(todo)
    centre_px = centre_px.reshape(S, n, 2)
    J = J.reshape(S, n, 2, 2)
    dist = dist.reshape(S, n)
    z_c = cam_pts[:, todo, 2]  # (S, n)
    alpha = np.arcsin(np.clip(layer.radius_mm[todo][None, :] / dist, 0, 1))  # rad
    sigma_px = float(np.sqrt(psf_sigma_px**2 + 1.0 / 12.0))
    patches: dict[int, _Patch] = {}
    for j, obj in enumerate(todo.tolist()):
        c = centre_px[:, j]
        if not np.all(np.isfinite(c)):
            continue
        Jj = J[:, j]
        a_j = alpha[:, j]
        ext = np.sqrt(np.sum(Jj**2, axis=2)) * a_j[:, None]
        pad = 4.0 * sigma_px + 1.0
        lo = np.floor(np.min(c - ext, axis=0) - pad)
        hi = np.ceil(np.max(c + ext, axis=0) + pad)
        x0, y0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
        x1, y1 = min(int(hi[0]) + 1, size.width), min(int(hi[1]) + 1, size.height)
        if x1 <= x0 or y1 <= y0:
            continue
        xs = np.arange(x0, x1, dtype=np.float64)
        ys = np.arange(y0, y1, dtype=np.float64)
        dx = xs[None, None, :] - c[:, 0, None, None]
        dy = ys[None, :, None] - c[:, 1, None, None]
        Jinv = np.linalg.inv(Jj)
        a1 = Jinv[:, 0, 0, None, None] * dx + Jinv[:, 0, 1, None, None] * dy
        a2 = Jinv[:, 1, 0, None, None] * dx + Jinv[:, 1, 1, None, None] * dy
        r = np.sqrt(a1 * a1 + a2 * a2)
        px_per_rad = np.sqrt(np.abs(np.linalg.det(Jj)))[:, None, None]
        rho = np.minimum(r / a_j[:, None, None], 1.0)
        edge_px = (r - a_j[:, None, None]) * px_per_rad
        blurred = 0.5 * erfc(edge_px / (_SQRT2 * sigma_px))
        sharp = 0.5 * erfc(edge_px / (_SQRT2 * _BOX_SIGMA_PX))
        radius = float(layer.radius_mm[obj])
        depth = z_c[:, j, None, None] - radius * np.sqrt(1.0 - rho * rho)
        hidden = skin.occluding(x0, y0, depth) if skin is not None else np.zeros_like(depth)
        vis = 1.0 - hidden
        a_vis = blurred * vis
        value = float(layer.peak[obj]) * (1.0 - limb_darkening * rho * rho) * a_vis
        patches[obj] = _Patch(x0, y0, a_vis, value, sharp, hidden, float(np.mean(z_c[:, j])))
    # visible fractions: nearest first, each hides the farther ones
    order = sorted(patches, key=lambda o: patches[o].depth)
    for i, obj in enumerate(order):
        p = patches[obj]
        seen = p.sharp * (1.0 - p.hidden_by_skin)
        for nearer in order[:i]:
            q = patches[nearer]
            _multiply_overlap(
                seen, p.x0, p.y0, 1.0 - q.sharp * (1.0 - q.hidden_by_skin), q.x0, q.y0
            )
        total = float(p.sharp.sum())
        visible[obj] = float(seen.sum()) / total if total > 0 else 0.0
    # draw: farthest first, each replaces what is behind it
    for obj in reversed(order):
        p = patches[obj]
        a = p.alpha.mean(axis=0)
        val = p.value.mean(axis=0)
        if shot_noise is not None:
            rng, gain = shot_noise
            val = val + np.sqrt(gain * val) * rng.standard_normal(val.shape)
        h, w = a.shape
        dst = canvas[p.y0 : p.y0 + h, p.x0 : p.x0 + w]
        dst *= (1.0 - a).astype(np.float32)
        dst += val.astype(np.float32)
    return visible


def _multiply_overlap(
    target: FloatArray, tx0: int, ty0: int, factor: FloatArray, fx0: int, fy0: int
) -> None:
    """``target *= factor`` where the two patches (``(S, h, w)``, top-left pixels) overlap."""
    th, tw = target.shape[-2:]
    fh, fw = factor.shape[-2:]
    ax0, ay0 = max(tx0, fx0), max(ty0, fy0)
    ax1, ay1 = min(tx0 + tw, fx0 + fw), min(ty0 + th, fy0 + fh)
    if ax1 <= ax0 or ay1 <= ay0:
        return
    f = factor[..., ay0 - fy0 : ay1 - fy0, ax0 - fx0 : ax1 - fx0]
    if f.shape[0] != target.shape[0]:  # different numbers of exposure sub-samples
        f = f.mean(axis=0, keepdims=True)
    target[..., ay0 - ty0 : ay1 - ty0, ax0 - tx0 : ax1 - tx0] *= f


# --------------------------------------------------------------------------- glints


def nail_glints(
    model: TappingModel,
    camera: Camera,
    t_s: float,
    *,
    marker_radius_mm: float,
    peak: float,
) -> SphereLayer:
    """Specular highlights of nail polish next to the thumb and index markers.

    The nail is a patch of the finger's cylinder under the marker; its
    highlight (light next to the lens) lies on the line of the cylinder whose
    normal points at the camera. On each nail the two ends of that line that
    the marker does not cover, 2.5-3.5 mm from the marker's centre along the
    finger, shine as small Gaussian glints, brightest when the nail faces the
    camera and fading as it turns away (gone beyond ~40 degrees).

    Returns
    -------
    SphereLayer
        Glint profile, 4 objects (two per nail), brightness 0 when not seen.
    """
    t = np.array([float(t_s)])
    markers = model.local_positions_mm(t)[0]
    n_thumb, n_index = nail_normals_local(model)
    base = np.asarray(THUMB_BASE_LOCAL_MM)
    lift = NAIL_FINGER_RADIUS_MM + MARKER_BASE_MM + marker_radius_mm
    local_pts = []
    for marker, normal, root in ((markers[0], n_thumb, base), (markers[1], n_index, np.zeros(3))):
        axis_pt = marker - lift * normal
        along = _unit(axis_pt - root)
        side = np.cross(along, normal)
        local_pts.append((axis_pt, along, normal, side))
    # world geometry of both nails: axis point, axis direction, normal, side
    pts = np.vstack([np.vstack([a, a + d, a + n, a + s]) for a, d, n, s in local_pts])
    world = model.hand_points_mm(t, pts)[0].reshape(2, 4, 3)
    centres, peaks = [], []
    cam_o = camera.center_world_mm
    for g in world:
        a, d, nrm, sd = g[0], _unit(g[1] - g[0]), _unit(g[2] - g[0]), _unit(g[3] - g[0])
        view = _unit(cam_o - a)
        # rotate the normal about the axis until it faces the camera: the angle needed
        v_perp = view - (view @ d) * d
        if np.linalg.norm(v_perp) < 1e-9:
            centres += [a, a]
            peaks += [0.0, 0.0]
            continue
        v_perp = _unit(v_perp)
        phi = float(np.arctan2(v_perp @ sd, v_perp @ nrm))  # rad around the cylinder
        surf_n = np.cos(phi) * nrm + np.sin(phi) * sd
        surface = a + NAIL_FINGER_RADIUS_MM * surf_n
        # the highlight is on the nail when the facing line is within ~40 deg of its middle,
        # and as bright as the line faces the camera along the finger (tilt)
        tilt = float(view @ d)
        strength = np.exp(-0.5 * (phi / np.deg2rad(25.0)) ** 2) * np.exp(-0.5 * (tilt / 0.25) ** 2)
        for s in (-1.0, 1.0):
            centres.append(surface + s * (marker_radius_mm + 0.8) * d)
            peaks.append(peak * float(strength))
    return SphereLayer(np.array(centres)[None], np.full(len(centres), 0.45), np.array(peaks), GLINT)


# --------------------------------------------------------------------------- postures


def closed_marker_separation_mm(
    scenario: TappingScenario, camera: Camera, *, seed: int = 0
) -> tuple[float, bool]:
    """How far apart ``camera`` sees the two fingertip markers at the first closure.

    Returns
    -------
    separation_mm : float
        Distance between the two projected marker centres, converted to mm at
        the markers' depth (compare with the marker diameter: less = overlap).
    index_in_front : bool
        Whether the index marker is the nearer one.
    """
    lead_in = replace(scenario, duration_s=1.0, drift_mm=0.0, hesitations=(), halts=())
    model = simulate_tapping(lead_in, seed=seed).model
    pts = model.positions_mm(np.array([0.0]))[0, :2]  # fingers closed during the lead-in
    px = camera.project(pts)
    z = camera.to_camera(pts)[:, 2]
    f = 0.5 * (camera.K[0, 0] + camera.K[1, 1])
    sep = float(np.linalg.norm(px[1] - px[0]) * np.mean(z) / f)
    return sep, bool(z[1] < z[0])


def overlap_orientation_deg(
    scenario: TappingScenario,
    camera: Camera,
    *,
    separation_mm: float,
    index_in_front: bool = True,
) -> tuple[float, float, float]:
    """The hand rotation (``TappingScenario.orientation_deg``) that makes the closed
    thumb and index markers overlap in ``camera``'s image.

    The thumb-to-index direction at a closure is turned, by the smallest
    rotation, until it makes an angle ``beta`` with the camera's viewing ray
    (the index in front of the thumb, or behind it); ``beta`` is adjusted on
    the model (a few secant steps) until the two marker centres project
    ``separation_mm`` apart at their depth. A camera looking along the
    opening direction sees the markers overlap at every closure and separate
    as the fingers open.

    Parameters
    ----------
    scenario : TappingScenario
        Its own ``orientation_deg`` is ignored (replaced).
    camera : Camera
    separation_mm : float
        Wanted distance between the two marker centres seen from the camera
        (mm at their depth): the marker diameter makes them touch, less overlap.
    index_in_front : bool

    Returns
    -------
    tuple of 3 floats
        Rotation vector (degrees) in the hand frame.
    """
    if not 0 <= separation_mm < scenario.closed_distance_mm:
        raise ValueError(
            f"separation_mm must be in [0, {scenario.closed_distance_mm}), got {separation_mm}"
        )
    base = replace(scenario, orientation_deg=(0.0, 0.0, 0.0))
    model = simulate_tapping(
        replace(base, duration_s=1.0, drift_mm=0.0, hesitations=(), halts=()), seed=0
    ).model
    mirror = np.diag([-1.0, 1.0, 1.0]) if scenario.hand == "left" else np.eye(3)
    R0 = model.R_world_from_hand  # of the right hand; a left hand is mirrored in world x
    closed = model.local_positions_mm(np.array([-1e3]))[0]
    e = R0 @ _unit(closed[1] - closed[0])  # thumb -> index, (unmirrored) world
    pts = model.positions_mm(np.array([0.0]))[0, :2]
    ray = mirror @ _unit(pts.mean(axis=0) - camera.center_world_mm)
    axis_dir = -ray if index_in_front else ray
    side = e - (e @ axis_dir) * axis_dir
    if np.linalg.norm(side) < 1e-9:
        side = np.cross(axis_dir, [1.0, 0.0, 0.0])
    side = _unit(side)

    def orientation(beta: float) -> tuple[float, float, float]:
        goal = np.cos(beta) * axis_dir + np.sin(beta) * side
        axis = np.cross(e, goal)
        s = float(np.linalg.norm(axis))
        if s < 1e-12:
            return (0.0, 0.0, 0.0)
        rotvec_world = axis / s * float(np.arctan2(s, float(e @ goal)))
        # R0 @ rot(local) == rot(world) @ R0  <=>  local = R0^T world
        return tuple(float(v) for v in np.rad2deg(R0.T @ rotvec_world))  # type: ignore[return-value]

    def error(beta: float) -> float:
        sep, _ = closed_marker_separation_mm(
            replace(base, orientation_deg=orientation(beta)), camera
        )
        return sep - separation_mm

    b0 = float(np.arcsin(separation_mm / scenario.closed_distance_mm))
    b1 = b0 * 1.1 + 1e-3
    e0, e1 = error(b0), error(b1)
    for _ in range(8):
        if abs(e1) < 0.01 or e1 == e0:  # mm
            break
        b0, b1, e0 = b1, b1 - e1 * (b1 - b0) / (e1 - e0), e1
        e1 = error(b1)
    return orientation(b1)

"""Markers whose images merged (or touch) in one camera, measured along their rays from the other.

At a closure seen along the opening direction the two fingertip markers' images
overlap in one camera while the other camera sees them apart. The detector
sets such a blob aside (it is not one whole disc, ``core.markers``) and keeps
the pixels around it (an :class:`ImagePatch`; also around two blobs closer
than a diameter + 4 px, whose centres pull each other). Here each marker is
put on its ray from the clear camera (two known image coordinates each), and
the patch gives the remaining coordinate of each: it is fitted by two opaque
blurred discs of one radius (scaled by the depth ratio), the nearer one over
the farther, over a planar background,

``m = P + (A_b - P) Phi_b (1 - Phi_f) + (A_f - P) Phi_f``,
``Phi_k = Phi((R rho_k - |x - c_k|) / s)``, ``c_k = q_k + t_k u_k``,

where ``q_k + t u_k`` is marker ``k``'s epipolar line in the patch (the
projection of its ray, straight over a few pixels) and ``P = B0 + Bx x + By
y``: 9 unknowns ``(t_0, t_1, R, s, A_0, A_1, B0, Bx, By)``, Levenberg-Marquardt
with the analytic Jacobian, both depth orders tried. Each fitted centre, with
the clear camera's detection, is a stereo observation like any other
(:func:`measure_merged`). A marker that the other one hides for the most part
(:data:`MIN_VISIBLE` of its disc or less left) is not measured: along its line
only a thin crescent would place it. ``docs/markers.md`` has the figures.

This runs only in the frames whose patches the detector kept (the set-aside
and touching blobs), never on the per-frame path.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.special import ndtr

from core.camera import Camera, StereoRig
from core.markers import ImagePatch

FloatArray = NDArray[np.float64]

#: A marker less visible than this share of its disc (the other one in front) is not measured.
MIN_VISIBLE = 0.5
#: A fit whose residual RMS over the contrast exceeds this is not two markers (a glint or a
#: third marker in the patch, a wrong pair of lines). Two markers on skin with a finger's
#: edge under them: 0.07-0.14 (tests/core/test_merged.py); the overlap recordings: ~0.045.
MAX_RESIDUAL = 0.2
#: Pixels darker than the fitted discs by more than this share of their contrast are taken
#: as hidden by skin in front (a finger's edge) and left out of a second fit.
HIDDEN_DEFICIT = 0.07
HIDDEN_ROUNDS = 2
#: A fitted radius off the camera's typical one by more than this share is no marker's.
MAX_RADIUS_CHANGE = 0.3
#: An epipolar line passing farther than this many diameters from the patch's blob is not
#: one of its markers.
LINE_REACH_DIAMETERS = 1.0
#: Depths (mm along the ray) searched for the part of an epipolar line inside a patch.
_DEPTHS_MM = np.geomspace(100.0, 5000.0, 160)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_N_PAR = 9


@dataclass(frozen=True)
class TwoDiscs:
    """What :func:`fit_two_discs` found.

    Attributes
    ----------
    centres_px : ndarray, shape (2, 2)
        Disc centres (image px, OpenCV ``(x, y)``), one per line.
    front : int
        Which disc is in front (0 or 1).
    visible : ndarray, shape (2,)
        Share of each disc's area not hidden by the other one.
    radius_px : float
        Fitted radius at the reference depth (px).
    residual : float
        RMS residual over the fitted contrast.
    """

    centres_px: FloatArray
    front: int
    visible: FloatArray
    radius_px: float
    residual: float


def _model(
    p: FloatArray,
    xs: FloatArray,
    ys: FloatArray,
    q: FloatArray,
    u: FloatArray,
    rho: FloatArray,
    front: int,
) -> tuple[FloatArray, FloatArray]:
    """Model values and Jacobian ``(n, 9)`` of two opaque discs, ``front`` over the other."""
    R, s = p[2], p[3]
    plane = p[6] + p[7] * xs + p[8] * ys
    Phi, phi, along, v = [], [], [], []
    for k in range(2):
        dx = xs - (q[k, 0] + p[k] * u[k, 0])
        dy = ys - (q[k, 1] + p[k] * u[k, 1])
        r = np.sqrt(dx * dx + dy * dy) + 1e-9
        vk = (R * rho[k] - r) / s
        Phi.append(ndtr(vk))
        phi.append(np.exp(-0.5 * vk * vk) * _INV_SQRT_2PI)
        along.append((dx * u[k, 0] + dy * u[k, 1]) / r)  # -dr/dt
        v.append(vk)
    f, b = front, 1 - front
    level = (p[4], p[5])
    m = plane + (level[b] - plane) * Phi[b] * (1.0 - Phi[f]) + (level[f] - plane) * Phi[f]
    d_phi = [np.empty(0), np.empty(0)]
    d_phi[f] = (level[f] - plane) - (level[b] - plane) * Phi[b]
    d_phi[b] = (level[b] - plane) * (1.0 - Phi[f])
    jac = np.zeros((len(xs), _N_PAR))
    for k in range(2):
        g = d_phi[k] * phi[k] / s
        jac[:, k] = g * along[k]
        jac[:, 2] += g * rho[k]
        jac[:, 3] -= g * v[k]
    jac[:, 4 + f] = Phi[f]
    jac[:, 4 + b] = Phi[b] * (1.0 - Phi[f])
    d_plane = 1.0 - Phi[b] * (1.0 - Phi[f]) - Phi[f]
    jac[:, 6] = d_plane
    jac[:, 7] = d_plane * xs
    jac[:, 8] = d_plane * ys
    return m, jac


def _hidden_share(d: float, r_front: float, r_back: float) -> float:
    """Share of the back disc's area (radius ``r_back``) behind the front one, centres ``d`` apart."""
    if d >= r_front + r_back:
        return 0.0
    if d <= abs(r_front - r_back):
        return 1.0 if r_front >= r_back else (r_front / r_back) ** 2
    a = r_front * r_front * math.acos((d * d + r_front**2 - r_back**2) / (2 * d * r_front))
    b = r_back * r_back * math.acos((d * d + r_back**2 - r_front**2) / (2 * d * r_back))
    c = 0.5 * math.sqrt(
        (-d + r_front + r_back)
        * (d + r_front - r_back)
        * (d - r_front + r_back)
        * (d + r_front + r_back)
    )
    return (a + b - c) / (math.pi * r_back * r_back)


def fit_two_discs(
    pixels: NDArray[np.uint8],
    x0: int,
    y0: int,
    lines_q_px: FloatArray,
    lines_u: FloatArray,
    *,
    radius_px: float,
    radius_ratio: FloatArray | None = None,
    start_t_px: FloatArray | None = None,
    depth_mm: FloatArray | None = None,
    depth_per_px: FloatArray | None = None,
    mask_hidden: bool = True,
) -> TwoDiscs:
    """Two opaque blurred discs, each centred on its own line, fitted to an image patch.

    Parameters
    ----------
    pixels : ndarray, shape (h, w), uint8
        The patch; its top-left pixel is image pixel ``(x0, y0)``.
    x0, y0 : int
    lines_q_px : ndarray, shape (2, 2)
        A point of each disc's line (image px).
    lines_u : ndarray, shape (2, 2)
        Unit direction of each line.
    radius_px : float
        Starting radius (px).
    radius_ratio : ndarray, shape (2,), optional
        Each disc's radius over the fitted one (its reference depth over its
        depth); default 1.
    start_t_px : ndarray, shape (2,), optional
        Starting positions along the lines (px from ``lines_q_px``); default 0.
    depth_mm, depth_per_px : ndarray, shape (2,), optional
        Each disc's depth (mm) at ``lines_q_px`` and its change per px along its
        line: the nearer disc is drawn in front. Without them both orders are
        fitted and the better kept (two equally bright discs look nearly the
        same either way, so the order, and ``visible``, may then be wrong).

    Returns
    -------
    TwoDiscs

    Raises
    ------
    ValueError
        For arrays of the wrong shape or a patch too small to hold two discs.
    """
    img = np.asarray(pixels)
    q = np.asarray(lines_q_px, dtype=np.float64)
    u = np.asarray(lines_u, dtype=np.float64)
    if img.ndim != 2 or img.shape[0] < 5 or img.shape[1] < 5:
        raise ValueError(f"pixels must be a 2-D patch of at least 5x5, got shape {img.shape}")
    if q.shape != (2, 2) or u.shape != (2, 2):
        raise ValueError(f"lines_q_px and lines_u must be (2, 2), got {q.shape}, {u.shape}")
    if not radius_px > 0:
        raise ValueError(f"radius_px must be > 0, got {radius_px}")
    rho = np.ones(2) if radius_ratio is None else np.asarray(radius_ratio, dtype=np.float64)
    t0 = np.zeros(2) if start_t_px is None else np.asarray(start_t_px, dtype=np.float64)
    h, w = img.shape
    # coordinates relative to the patch centre keep the plane's terms well scaled
    xc, yc = x0 + 0.5 * (w - 1), y0 + 0.5 * (h - 1)
    ys, xs = np.mgrid[0:h, 0:w]
    xs_f = xs.ravel() + (x0 - xc)
    ys_f = ys.ravel() + (y0 - yc)
    z = img.ravel().astype(np.float64)
    qc = q - np.array([xc, yc])
    border = np.concatenate((img[0], img[-1], img[1:-1, 0], img[1:-1, -1])).astype(np.float64)
    bg0 = float(np.median(border))
    top = float(np.percentile(z, 99))

    keep = np.ones(len(z), bool)

    def solve(front: int, p0: FloatArray | None = None) -> tuple[float, FloatArray]:
        if p0 is None:
            p0 = np.array([t0[0], t0[1], radius_px, 0.7, top, top, bg0, 0.0, 0.0])
        xk, yk, zk = xs_f[keep], ys_f[keep], z[keep]

        def residual(p: FloatArray) -> FloatArray:
            return _model(p, xk, yk, qc, u, rho, front)[0] - zk

        def jacobian(p: FloatArray) -> FloatArray:
            return _model(p, xk, yk, qc, u, rho, front)[1]

        sol = least_squares(residual, p0, jac=jacobian, method="lm", xtol=1e-6, max_nfev=60)
        return float(sol.cost), sol.x

    def without_hidden(front: int, p: FloatArray) -> tuple[float, FloatArray]:
        # Skin in front of part of a disc (a finger's edge): pixels far darker than the
        # fitted discs are hidden, not background; fitted again without them.
        keep[:] = True
        m = _model(p, xs_f, ys_f, qc, u, rho, front)[0]
        contrast = max(min(p[4], p[5]) - float(np.median(border)), 1e-9)
        hidden = m - z > HIDDEN_DEFICIT * contrast
        if not np.any(hidden) or np.count_nonzero(~hidden) < 4 * _N_PAR:
            return math.nan, p
        keep[:] = ~hidden
        return solve(front, p)

    best: tuple[float, FloatArray, int] | None = None
    if depth_mm is None:
        for front in (0, 1):  # equally bright flat discs: the union, nearly the same either way
            cost, p = solve(front)
            if best is None or cost < best[0]:
                best = (cost, p, front)
    else:
        # the nearer one in front: start from the depths at the lines' points, and
        # fit again with the other order when the fitted positions say otherwise
        dz = np.asarray(depth_mm, dtype=np.float64)
        slope = np.zeros(2) if depth_per_px is None else np.asarray(depth_per_px, np.float64)
        front = int(np.argmin(dz + slope * t0))
        cost, p = solve(front)
        if int(np.argmin(dz + slope * p[:2])) != front:
            front = 1 - front
            cost, p = solve(front)
        best = (cost, p, front)
    assert best is not None
    if mask_hidden:
        for _ in range(HIDDEN_ROUNDS):
            cost_m, p_m = without_hidden(best[2], best[1])
            if not np.isfinite(cost_m):
                break
            best = (cost_m, p_m, best[2])
    cost, p, front = best
    centres = q + p[:2, None] * u
    radius = abs(float(p[2]))
    radii = radius * rho
    d = float(np.linalg.norm(centres[0] - centres[1]))
    visible = np.ones(2)
    back = 1 - front
    visible[back] = 1.0 - _hidden_share(d, float(radii[front]), float(radii[back]))
    contrast = max(min(p[4], p[5]) - (p[6]), 1e-9)
    rms = math.sqrt(2.0 * cost / max(int(np.count_nonzero(keep)), 1))
    return TwoDiscs(centres, front, visible, radius, rms / contrast)


# ------------------------------------------------------------------ along the recording


@dataclass(frozen=True)
class MergedMeasurement:
    """Detections of both cameras with the merged images measured (:func:`measure_merged`).

    Attributes
    ----------
    left_px, right_px : list of ndarray (N_f, 2)
        Per frame of each video: the detections, those of a measured patch
        replaced by the fitted marker centres.
    left_measured, right_measured : list of ndarray (N_f,), bool
        Which rows are such fitted centres (the tracker uses them even where
        two markers' images touch).
    frames_left, frames_right : int
        Frames of each camera in which a patch was measured.
    """

    left_px: list[FloatArray]
    right_px: list[FloatArray]
    left_measured: list[NDArray[np.bool_]]
    right_measured: list[NDArray[np.bool_]]
    frames_left: int
    frames_right: int


def _lines_in_patch(
    cam_other: Camera, cam: Camera, points_px: FloatArray, centre_px: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Each point's epipolar line in ``cam`` near ``centre_px``: the ray's point whose
    projection is nearest the centre (its projection ``q``), the unit direction ``u``,
    the distance from the centre (px), the depth in ``cam`` at ``q`` (mm) and its change
    per px along ``u``."""
    origin, direction = cam_other.backproject(points_px)
    n, k = len(points_px), len(_DEPTHS_MM)
    pts = origin[:, None, :] + _DEPTHS_MM[None, :, None] * direction[:, None, :]
    proj = cam.project(pts.reshape(-1, 3)).reshape(n, k, 2)
    d2 = np.sum((proj - centre_px) ** 2, axis=2)
    d2 = np.where(np.isfinite(d2), d2, np.inf)
    i = np.argmin(d2, axis=1)
    lo, hi = _DEPTHS_MM[np.maximum(i - 1, 0)], _DEPTHS_MM[np.minimum(i + 1, k - 1)]
    # refine: the nearest point of the chord between the neighbouring samples
    a = cam.project(origin + lo[:, None] * direction)
    b = cam.project(origin + hi[:, None] * direction)
    ab = b - a
    length = np.linalg.norm(ab, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = ab / length[:, None]
        t = np.sum((centre_px - a) * u, axis=1)
    q = a + t[:, None] * u
    dist = np.abs(np.sum(np.column_stack([-u[:, 1], u[:, 0]]) * (centre_px - q), axis=1))
    s = lo + np.clip(t / np.where(length > 0, length, np.nan), 0, 1) * (hi - lo)
    depth = cam.to_camera(origin + s[:, None] * direction)[:, 2]
    z_lo = cam.to_camera(origin + lo[:, None] * direction)[:, 2]
    z_hi = cam.to_camera(origin + hi[:, None] * direction)[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = (z_hi - z_lo) / length
    return q, u, dist, depth, slope


def _start_positions(q: FloatArray, u: FloatArray, points_px: FloatArray) -> FloatArray:
    """Starting position along each of two lines: the blob of the patch nearest to it
    (two blobs: the assignment nearer in sum), projected on it; one blob: its projection."""
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros(2)
    normal = np.column_stack([-u[:, 1], u[:, 0]])
    off = np.abs(np.einsum("kj,kpj->kp", normal, pts[None, :, :] - q[:, None, :]))  # (2, P)
    if len(pts) >= 2:
        pick = [0, 1]
        best = math.inf
        for i in range(len(pts)):
            for j in range(len(pts)):
                if i != j and off[0, i] + off[1, j] < best:
                    best, pick = off[0, i] + off[1, j], [i, j]
    else:
        pick = [0, 0]
    return np.array([float(np.dot(pts[pick[k]] - q[k], u[k])) for k in range(2)])


def measure_patch(
    cam_other: Camera, cam: Camera, patch: ImagePatch, other_px: FloatArray
) -> list[tuple[int, FloatArray]]:
    """The markers of one patch of camera ``cam`` that detections of ``cam_other`` place.

    Parameters
    ----------
    cam_other, cam : Camera
        The clear camera and the patch's camera.
    patch : ImagePatch
    other_px : ndarray, shape (N, 2)
        The clear camera's detections in the paired frame (px).

    Returns
    -------
    list of (int, ndarray (2,))
        ``(index into other_px, centre px in the patch camera)`` of each marker
        measured: of the (at most four) detections whose epipolar lines pass within
        ``LINE_REACH_DIAMETERS`` of the patch's blob, the pair that two discs fit
        best, each marker that is at least ``MIN_VISIBLE`` visible; none when the
        fit fails the residual or radius checks.
    """
    if len(other_px) < 2:
        return []
    img = patch.pixels
    h, w = img.shape
    bright = img >= 0.5 * (float(img.max()) + float(np.median(img)))
    yy, xx = np.nonzero(bright)
    if len(xx) == 0:
        return []
    blob = np.array([xx.mean() + patch.x0, yy.mean() + patch.y0])
    q, u, dist, depth, slope = _lines_in_patch(cam_other, cam, other_px, blob)
    near = np.flatnonzero(
        np.isfinite(dist) & (dist <= LINE_REACH_DIAMETERS * patch.diameter_px) & (depth > 0)
    )
    if len(near) < 2:
        return []
    near = near[np.argsort(dist[near])][:4]
    best: tuple[float, int, int, TwoDiscs] | None = None
    for ia in range(len(near)):
        for ib in range(ia + 1, len(near)):
            a, b = int(near[ia]), int(near[ib])
            ref = 0.5 * (depth[a] + depth[b])
            start = _start_positions(q[[a, b]], u[[a, b]], patch.points_px)
            try:
                fit = fit_two_discs(
                    img,
                    patch.x0,
                    patch.y0,
                    q[[a, b]],
                    u[[a, b]],
                    radius_px=0.5 * patch.diameter_px,
                    radius_ratio=ref / depth[[a, b]],
                    start_t_px=start,
                    depth_mm=depth[[a, b]],
                    depth_per_px=slope[[a, b]],
                )
            except ValueError:
                continue
            if best is None or fit.residual < best[0]:
                best = (fit.residual, a, b, fit)
    if best is None or not best[0] <= MAX_RESIDUAL:
        return []
    _, a, b, fit = best
    if not abs(fit.radius_px / (0.5 * patch.diameter_px) - 1.0) <= MAX_RADIUS_CHANGE:
        return []
    # the centres must stay in the patch and near their blob (a fit that ran off is no fit)
    inside = np.all(
        (fit.centres_px >= [patch.x0, patch.y0])
        & (fit.centres_px <= [patch.x0 + w - 1, patch.y0 + h - 1]),
        axis=1,
    )
    out = []
    for k, idx in enumerate((a, b)):
        if inside[k] and fit.visible[k] >= MIN_VISIBLE:
            out.append((idx, fit.centres_px[k]))
    return out


def measure_merged(
    rig: StereoRig,
    left_px: Sequence[FloatArray],
    right_px: Sequence[FloatArray],
    left_patches: dict[int, list[ImagePatch]],
    right_patches: dict[int, list[ImagePatch]],
    offset_frames: int,
) -> MergedMeasurement:
    """Measure the markers of every kept patch from the other camera's detections.

    Parameters
    ----------
    rig : StereoRig
    left_px, right_px : sequence of ndarray (N_f, 2)
        Detections per frame of each video (px).
    left_patches, right_patches : dict of int to list of ImagePatch
        The patches each camera's detection kept, by that video's frame.
    offset_frames : int
        Right frame ``j`` was taken with left frame ``j + offset_frames``.

    Returns
    -------
    MergedMeasurement
        A patch whose two markers are placed by two detections of the other
        camera (their epipolar lines pass through it) and fit two discs
        (:data:`MAX_RESIDUAL`) has its detections replaced by the fitted
        centres of the markers visible enough (:data:`MIN_VISIBLE`). Patches
        seen in both cameras of a pair of frames are left alone.
    """
    out_px = [[np.asarray(f, dtype=np.float64).reshape(-1, 2) for f in left_px],
              [np.asarray(f, dtype=np.float64).reshape(-1, 2) for f in right_px]]  # fmt: skip
    flags = [
        [np.zeros(len(f), bool) for f in out_px[0]],
        [np.zeros(len(f), bool) for f in out_px[1]],
    ]
    counts = [0, 0]
    cams = rig.cameras
    for ci, patches in enumerate((left_patches, right_patches)):
        other_patches = right_patches if ci == 0 else left_patches
        for frame, plist in sorted(patches.items()):
            other = frame - offset_frames if ci == 0 else frame + offset_frames
            if not 0 <= other < len(out_px[1 - ci]) or other_patches.get(other):
                continue
            other_px = np.asarray((right_px if ci == 0 else left_px)[other], dtype=np.float64)
            found: list[FloatArray] = []
            replaced: set[int] = set()
            for patch in plist:
                got = measure_patch(cams[1 - ci], cams[ci], patch, other_px.reshape(-1, 2))
                if got:
                    found.extend(c for _, c in got)
                    replaced.update(int(i) for i in patch.detections)
            if not found:
                continue
            keep = [i for i in range(len(out_px[ci][frame])) if i not in replaced]
            out_px[ci][frame] = np.vstack([out_px[ci][frame][keep], np.array(found)])
            flags[ci][frame] = np.r_[np.zeros(len(keep), bool), np.ones(len(found), bool)]
            counts[ci] += 1
    return MergedMeasurement(out_px[0], out_px[1], flags[0], flags[1], counts[0], counts[1])

"""The marker search and measurement as first written, with OpenCV and numpy calls.

A test oracle for the compiled search of ``core/_blobs.pyx``:
``tests/core/test_markers.py`` checks that :func:`core.markers.detect_markers`
gives the same detections (centroid method, no static background) as this
formulation, field by field.  Kept as it was when ``core.markers`` ran it
(see that module's docstring for the method); only the centre-method and
background options and the support's rectangle shortcut were taken out, and the
split of a neighbour by distance uses exact Euclidean distances (it used the 3x3
chamfer metric, whose float sums round differently in OpenCV and in C).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from core.markers import (
    _MARGIN_PX,
    _POOL,
    FloatArray,
    MarkerDetections,
    MarkerParams,
    _centroid,
    _pooled_regions,
    _ring_radius,
)

_MAX_SEEDS_PER_REGION = 64
_SIZE_TOL_PX = 0.5
_DISC5 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
_ONES3 = np.ones((3, 3), np.uint8)
_RING_DX = np.array([1, 1, 0, -1, -1, -1, 0, 1])
_RING_DY = np.array([0, 1, 1, 1, 0, -1, -1, -1])


@dataclass
class _Blob:
    xy_px: tuple[float, float]
    diameter_px: float
    peak: float
    roundness: float
    background: float
    area_px: float
    fill: float
    cov: tuple[float, float, float]
    quality: float
    flatness: float


@dataclass
class _Measured:
    """Outcome of measuring one seed: its core (a mask at ``(x0, y0)``) and maybe a blob."""

    core: NDArray[np.uint8] | None
    x0: int
    y0: int
    blob: _Blob | None


def detect_reference(
    image: NDArray[np.uint8],
    *,
    params: MarkerParams = MarkerParams(),
    search_xy_px: NDArray[Any] | None = None,
    search_radius_px: float | None = None,
) -> MarkerDetections:
    """``detect_markers`` (centroid method, no background) in the original formulation."""
    radius_px = float(params.search_radius_px if search_radius_px is None else search_radius_px)
    image = np.ascontiguousarray(image)
    measured: list[_Measured] = []
    if search_xy_px is None:
        bg, sigma = _background_and_noise(image[::8, ::8])
        thr = bg + max(0.5 * params.min_contrast, 4.0 * sigma)
        for x0, y0, x1, y1 in _full_frame_regions(image, thr, params):
            measured.extend(_search_region(image, (x0, y0, x1, y1), thr, params, measured))
    else:
        pts = np.asarray(search_xy_px, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"search_xy_px must have shape (K, 2), got {pts.shape}")
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        # seeds are blob maxima: within the radius plus a streak's half length
        reach = radius_px + 0.5 * params.diameter_px_max
        windows = _merged_windows(pts, reach, image.shape)
        if windows:
            bg, sigma = _background_and_noise(image[::16, ::16])
            thr = bg + max(0.5 * params.min_contrast, 4.0 * sigma)
        r2 = radius_px**2
        for (x0, y0, x1, y1), group in windows:
            found = _search_region(image, (x0, y0, x1, y1), thr, params, measured)
            centres = group.tolist()
            for m in found:
                if m.blob is not None:
                    bx, by = m.blob.xy_px
                    if min((gx - bx) ** 2 + (gy - by) ** 2 for gx, gy in centres) > r2:
                        m.blob = None  # outside the search discs; keep the core as "seen"
            measured.extend(found)
    return _to_detections([m.blob for m in measured if m.blob is not None])


def _background_and_noise(sample: NDArray[np.uint8]) -> tuple[float, float]:
    """Median and noise sigma (gray levels) of a uint8 sample, from its histogram.

    Sigma comes from the lower half only (median minus first quartile), since
    the bright blobs are outliers on the upper side.
    """
    cum = np.cumsum(np.bincount(sample.ravel(), minlength=256))
    n = int(cum[-1])
    q25, q50 = np.searchsorted(cum, [(n + 3) // 4, (n + 1) // 2]).tolist()
    sigma = max((q50 - q25) / 0.6745, 0.7)  # 0.7: quantisation floor
    return float(q50), float(sigma)


def _merged_windows(
    pts: FloatArray, reach: float, shape: tuple[int, ...]
) -> list[tuple[tuple[int, int, int, int], FloatArray]]:
    """Square windows ``(x0, y0, x1, y1)`` of half-size ``reach`` around the points,
    overlapping ones merged into their bounding box, with the points of each."""
    h, w = shape[0], shape[1]
    boxes: list[list[float]] = []
    groups: list[list[int]] = []
    for i, (x, y) in enumerate(pts.tolist()):
        boxes.append([x - reach, y - reach, x + reach, y + reach])
        groups.append([i])
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]:
                    boxes[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                    groups[i] += groups.pop(j)
                    boxes.pop(j)
                    merged = True
                    break
            if merged:
                break
    out = []
    for (bx0, by0, bx1, by1), g in zip(boxes, groups, strict=True):
        x0, x1 = max(0, math.floor(bx0)), min(w, math.ceil(bx1) + 1)
        y0, y1 = max(0, math.floor(by0)), min(h, math.ceil(by1) + 1)
        if x1 - x0 >= 3 and y1 - y0 >= 3:
            out.append(((x0, y0, x1, y1), pts[g]))
    return out


def _full_frame_regions(
    image: NDArray[np.uint8], thr: float, params: MarkerParams
) -> list[tuple[int, int, int, int]]:
    """Regions ``(x0, y0, x1, y1)`` (half-open, px) around the bright components."""
    h, w = image.shape
    t = min(math.floor(thr), 254)
    _, binary = cv2.threshold(image, t, 255, cv2.THRESH_BINARY)
    hp, wp = -(-h // _POOL), -(-w // _POOL)
    if hp * _POOL != h or wp * _POOL != w:
        binary = cv2.copyMakeBorder(binary, 0, hp * _POOL - h, 0, wp * _POOL - w,
                                    cv2.BORDER_CONSTANT, value=0)  # fmt: skip
    # max-pooling in two 2x2 steps (OpenCV's fast path): a mean is > 0 when any
    # of its pixels is set (255 / 4 rounds to 64, 64 / 4 to 16)
    half_size = cv2.resize(binary, (wp * 2, hp * 2), interpolation=cv2.INTER_AREA)
    pooled = cv2.resize(half_size, (wp, hp), interpolation=cv2.INTER_AREA)
    return _pooled_regions(pooled, h, w)


def _smooth(image: NDArray[np.uint8], x0: int, y0: int, x1: int, y1: int) -> NDArray[np.float32]:
    """3x3 mean of ``image[y0:y1, x0:x1]`` computed with one pixel of real context.

    The values do not depend on the rectangle (only on the image), so the
    full-frame and the windowed paths see the same numbers.
    """
    h, w = image.shape
    px0, py0, px1, py1 = max(0, x0 - 1), max(0, y0 - 1), min(w, x1 + 1), min(h, y1 + 1)
    sm = cast("NDArray[np.float32]", cv2.boxFilter(image[py0:py1, px0:px1], cv2.CV_32F, (3, 3),
                                                 borderType=cv2.BORDER_REPLICATE))  # fmt: skip
    return sm[y0 - py0 : y1 - py0, x0 - px0 : x1 - px0]


def _search_region(
    image: NDArray[np.uint8],
    region: tuple[int, int, int, int],
    thr: float,
    params: MarkerParams,
    known: list[_Measured],
) -> list[_Measured]:
    """Seeds (local maxima above ``thr``) of one region, each blob measured once."""
    x0, y0, x1, y1 = region
    sm = _smooth(image, x0, y0, x1, y1)
    if float(sm.max()) <= thr:  # no seed (most full-frame regions: a noise pixel above thr)
        return []
    # local maxima above thr: the 3x3 maximum only over the bounding box of the
    # pixels above thr plus one pixel of context (the same values as over the
    # whole region), compared at those pixels only (few, unlike the region's)
    above = (sm > thr).view(np.uint8)
    bx, by, bw, bh = cv2.boundingRect(above)
    cx0, cy0 = max(0, bx - 1), max(0, by - 1)
    part = sm[cy0 : by + bh + 1, cx0 : bx + bw + 1]
    flat = part.ravel()
    idx = np.flatnonzero(above[cy0 : by + bh + 1, cx0 : bx + bw + 1])
    vals = flat[idx]
    keep_max = vals >= cv2.dilate(part, _ONES3).ravel()[idx]
    idx, vals = idx[keep_max], vals[keep_max]
    if idx.size == 0:
        return []
    ys, xs = np.divmod(idx, part.shape[1])
    ys += cy0
    xs += cx0
    if ys.size > 1:
        # cheap pre-check of the local contrast against 8 pixels at the distance of
        # the measurement ring, so that a bright textured area (lit skin) does not
        # cost one measurement per noise maximum
        h, w = image.shape
        r = _ring_radius(params)
        gy = np.minimum(np.maximum(ys[:, None] + (y0 + r * _RING_DY[None, :]), 0), h - 1)
        gx = np.minimum(np.maximum(xs[:, None] + (x0 + r * _RING_DX[None, :]), 0), w - 1)
        ring = np.sort(image[gy, gx], axis=1).astype(np.float32)
        keep = vals - 0.5 * (ring[:, 3] + ring[:, 4]) >= 0.8 * params.min_contrast
        ys, xs, vals = ys[keep], xs[keep], vals[keep]
    order = np.lexsort((xs, ys, -vals))
    seeds_y, seeds_x = (ys[order] + y0).tolist(), (xs[order] + x0).tolist()

    taken = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)

    def mark(m: _Measured) -> None:
        if m.core is None:
            return
        ch, cw = m.core.shape
        ax0, ay0 = max(x0, m.x0), max(y0, m.y0)
        ax1, ay1 = min(x1, m.x0 + cw), min(y1, m.y0 + ch)
        if ax0 < ax1 and ay0 < ay1:
            taken[ay0 - y0 : ay1 - y0, ax0 - x0 : ax1 - x0] |= m.core[
                ay0 - m.y0 : ay1 - m.y0, ax0 - m.x0 : ax1 - m.x0
            ]

    for m in known:
        mark(m)
    out: list[_Measured] = []
    cache = (sm, x0, y0)
    for sy, sx in zip(seeds_y, seeds_x, strict=True):
        if taken[sy - y0, sx - x0]:
            continue
        m = _measure(image, sx, sy, params, cache)
        taken[sy - y0, sx - x0] = 1
        mark(m)
        if m.core is not None:
            out.append(m)
        if len(out) >= _MAX_SEEDS_PER_REGION:
            break
    return out


# ------------------------------------------------------------------- measurement


def _measure(
    image: NDArray[np.uint8],
    sx: int,
    sy: int,
    params: MarkerParams,
    cache: tuple[NDArray[np.float32], int, int] | None = None,
) -> _Measured:
    """Measure the blob around seed pixel ``(sx, sy)``; deterministic given the image.

    ``cache`` is a smoothed region ``(sm, x0, y0)`` to slice from when the
    window lies inside it (same values as :func:`_smooth` would give).
    """
    h, w = image.shape
    half = _ring_radius(params)
    half_limit = math.ceil(params.diameter_px_max * params.max_elongation) + _MARGIN_PX + 2
    reseeds = 0
    while True:
        x0, x1 = max(0, sx - half), min(w, sx + half + 1)
        y0, y1 = max(0, sy - half), min(h, sy + half + 1)
        sm = None
        if cache is not None:
            csm, cx0, cy0 = cache
            if cx0 <= x0 and cy0 <= y0 and x1 <= cx0 + csm.shape[1] and y1 <= cy0 + csm.shape[0]:
                sm = csm[y0 - cy0 : y1 - cy0, x0 - cx0 : x1 - cx0]
        if sm is None:
            sm = _smooth(image, x0, y0, x1, y1)
        win = image[y0:y1, x0:x1]
        ring = np.concatenate((win[0], win[-1], win[1:-1, 0], win[1:-1, -1]))
        ring.sort()
        n_ring = ring.size
        bg = 0.5 * (float(ring[(n_ring - 1) // 2]) + float(ring[n_ring // 2]))
        lx, ly = sx - x0, sy - y0
        contrast = float(sm[ly, lx]) - bg
        if contrast < params.min_contrast:
            return _Measured(None, x0, y0, None)
        mask = (sm > bg + 0.5 * contrast).view(np.uint8)
        # the core: the 8-connected half-maximum region of the seed, filled with 2
        area, _, _, (bx, by, bw, bh) = cv2.floodFill(mask, None, (lx, ly), 2, flags=8)
        core = (mask == 2).view(np.uint8)
        # measure from the core's maximum (first in raster order), so that every
        # seed of the same blob gives the same result
        _, peak_val, _, (mx_l, my_l) = cv2.minMaxLoc(sm, mask=core)
        if (mx_l != lx or my_l != ly) and reseeds < 2:
            sx, sy, reseeds = mx_l + x0, my_l + y0, reseeds + 1
            continue
        # the core lies in its bounding box: moments of that box (shifted back)
        mom = cv2.moments(core[by : by + bh, bx : bx + bw], binaryImage=True)
        diameter, roundness, fill, cov = _shape(mom)
        margin = max(_MARGIN_PX, math.ceil(0.5 * diameter))
        need = margin + 3 + max(lx - bx, bx + bw - 1 - lx, ly - by, by + bh - 1 - ly)
        fits_x = (lx >= need or x0 == 0) and (x1 - 1 - lx >= need or x1 == w)
        fits_y = (ly >= need or y0 == 0) and (y1 - 1 - ly >= need or y1 == h)
        if fits_x and fits_y:
            break
        too_large = area > params.max_elongation * params.diameter_px_max**2
        if too_large or need > half_limit:  # a glare blob
            return _Measured(core, x0, y0, None)
        half = need

    peak = peak_val - bg
    touches_border = (
        (bx == 0 and x0 == 0) or (by == 0 and y0 == 0)
        or (bx + bw == x1 - x0 and x1 == w) or (by + bh == y1 - y0 and y1 == h)
    )  # fmt: skip
    measured = _Measured(core, x0, y0, None)
    if (
        peak < params.min_contrast
        or not params.diameter_px_min - _SIZE_TOL_PX
        <= diameter
        <= params.diameter_px_max + _SIZE_TOL_PX
        or roundness * params.max_elongation < 1.0
        or fill < params.min_fill
        or (touches_border and params.reject_border)
    ):
        return measured

    # support of the centre estimators: the blob down to 10 % of its peak, at most
    # ``margin`` beyond the core, grown by 2 px; other blobs masked out
    sigma = max((float(ring[(3 * n_ring) // 4]) - float(ring[n_ring // 4])) / 1.349, 0.7)
    low_mask = (sm > bg + max(1.5 * sigma, 0.1 * peak)).view(np.uint8)
    k = 2 * margin + 1
    e = margin + 3
    sx0, sy0 = max(0, bx - e), max(0, by - e)
    sx1, sy1 = min(x1 - x0, bx + bw + e), min(y1 - y0, by + bh + e)
    # other blobs above this one's half maximum (mask == 1; the core is 2) or low
    # pixels beyond the core's reach: counted first, masks only built when needed
    has_neighbour = cv2.countNonZero(mask) > area
    sup = _support_full(core, mask, low_mask, k, has_neighbour)[sy0:sy1, sx0:sx1].view(bool)
    sub = np.subtract(win[sy0:sy1, sx0:sx1], bg, dtype=np.float64)
    cx, cy = _centroid(sub, sup, peak)
    # pixels of the core above 75 % of the peak (uint8 > t is uint8 > floor(t),
    # which is how cv2.threshold compares a uint8 image)
    t75 = bg + 0.75 * peak
    if t75 < 255:
        cb = core[by : by + bh, bx : bx + bw]
        hi = cv2.threshold(win[by : by + bh, bx : bx + bw], max(t75, -1.0), 1, cv2.THRESH_BINARY)[1]
        flatness = cv2.countNonZero(hi & cb) / area
    else:
        flatness = 0.0
    quality = (
        roundness
        * min(fill, 1.0)
        * min(1.0, flatness / 0.6)
        * min(1.0, peak / (3.0 * params.min_contrast))
    )
    measured.blob = _Blob(
        xy_px=(cx + sx0 + x0, cy + sy0 + y0),
        diameter_px=diameter,
        peak=peak,
        roundness=roundness,
        background=bg,
        area_px=float(area),
        fill=fill,
        cov=cov,
        quality=quality,
        flatness=flatness,
    )
    return measured


#: Build the centre's support on its rectangle only when no neighbour is near (the
#: same pixels as on the whole window; False: always the whole window, for tests).
def _support_full(
    core: NDArray[np.uint8],
    mask: NDArray[np.uint8],
    low_mask: NDArray[np.uint8],
    k: int,
    has_neighbour: bool,
) -> NDArray[np.uint8]:
    """Support of the centre estimators on the whole measurement window (0/1 uint8).

    The low mask within ``(k - 1) / 2`` px of the core, grown by 2 px; low
    pixels beyond that reach and other cores (``mask == 1``) masked out, a
    neighbour split off by distance.
    """
    near = cast("NDArray[np.uint8]", cv2.dilate(core, _square_kernel(k)))
    low_near = low_mask & near
    support = cast("NDArray[np.uint8]", cv2.dilate(low_near, _DISC5))
    if has_neighbour or cv2.countNonZero(low_mask) > cv2.countNonZero(low_near):
        outside = low_mask & (1 - near)
        other_cores = (mask == 1).view(np.uint8)
        others = outside | other_cores
        support &= 1 - cast("NDArray[np.uint8]", cv2.dilate(others, _DISC5))
        if has_neighbour:  # split by distance
            d_own = cv2.distanceTransform(1 - core, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            d_other = cv2.distanceTransform(1 - other_cores, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            support &= (d_own < d_other).view(np.uint8)
        support |= core
    return support


_SQUARE_KERNELS: dict[int, NDArray[np.uint8]] = {}


def _square_kernel(k: int) -> NDArray[np.uint8]:
    """``np.ones((k, k), np.uint8)``, cached (one allocation per size, not per blob)."""
    kern = _SQUARE_KERNELS.get(k)
    if kern is None:
        kern = _SQUARE_KERNELS.setdefault(k, np.ones((k, k), np.uint8))
    return kern


def _shape(mom: dict[str, float]) -> tuple[float, float, float, tuple[float, float, float]]:
    """Minor-axis diameter, roundness, fill and ``(xx, xy, yy)`` moments of a binary blob.

    ``mom`` are ``cv2.moments`` of the mask.  Each pixel counts as a unit
    square (hence the 1/12 px^2 added to the variances), so that a tiny blob is
    not reported as a line.
    """
    area = mom["m00"]
    cxx = mom["mu20"] / area + 1.0 / 12
    cyy = mom["mu02"] / area + 1.0 / 12
    cxy = mom["mu11"] / area
    tr, det = cxx + cyy, cxx * cyy - cxy * cxy
    disc = math.sqrt(max(0.25 * tr * tr - det, 0.0))
    lam_max, lam_min = 0.5 * tr + disc, max(0.5 * tr - disc, 1e-12)
    diameter = 4.0 * math.sqrt(lam_min)
    roundness = math.sqrt(lam_min / lam_max)
    fill = area / (4.0 * math.pi * math.sqrt(lam_min * lam_max))
    return diameter, roundness, fill, (cxx, cxy, cyy)


def _to_detections(blobs: list[_Blob | None]) -> MarkerDetections:
    kept: list[_Blob] = []
    for b in blobs:
        if b is None:
            continue
        if any((b.xy_px[0] - k.xy_px[0]) ** 2 + (b.xy_px[1] - k.xy_px[1]) ** 2 < 1.0 for k in kept):
            continue
        kept.append(b)
    if not kept:
        return MarkerDetections.empty()
    cov = np.array([[[b.cov[0], b.cov[1]], [b.cov[1], b.cov[2]]] for b in kept], dtype=np.float64)
    return MarkerDetections(
        xy_px=np.array([b.xy_px for b in kept], dtype=np.float64),
        diameter_px=np.array([b.diameter_px for b in kept], dtype=np.float64),
        peak=np.array([b.peak for b in kept], dtype=np.float64),
        roundness=np.array([b.roundness for b in kept], dtype=np.float64),
        background=np.array([b.background for b in kept], dtype=np.float64),
        area_px=np.array([b.area_px for b in kept], dtype=np.float64),
        fill=np.array([b.fill for b in kept], dtype=np.float64),
        shape_cov_px2=cov,
        quality=np.array([b.quality for b in kept], dtype=np.float64),
        flatness=np.array([b.flatness for b in kept], dtype=np.float64),
    )


# ------------------------------------------------------------------ centre estimators

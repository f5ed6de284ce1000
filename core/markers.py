"""Detection of retro-reflective markers with sub-pixel centres.

Under an infrared ring light a retro-reflective sphere appears as a bright,
anti-aliased disc on a dark background (a short streak when it moves during
the exposure).  :func:`detect_markers` finds such blobs in a uint8 gray image
and measures each one:

1. **Candidates.**  Full frame: the image is thresholded at
   ``background + max(min_contrast / 2, 4 sigma)`` (background and noise
   ``sigma`` from a histogram of a sub-sampled frame), the binary image is
   max-pooled 4x4 and the bounding boxes of its outer contours give small
   regions of the full-resolution image.  Windowed (``search_xy_px`` given):
   one region around each predicted position (overlapping ones merged), same
   threshold from every 16th pixel.  In a region, the local maxima of the
   3x3-smoothed image above the threshold whose contrast against 8 pixels at
   the measurement ring's distance reaches 0.8 ``min_contrast`` are the
   seeds, brightest first.
2. **Measurement** (the same code for both paths, so they agree): a window
   around the seed, the local background as the median of the window's border,
   the peak of the smoothed image, and the *core*: the connected half-maximum
   region containing the seed.  Its second moments give ``diameter_px`` (minor
   axis), ``roundness`` (minor / major axis) and ``fill`` (area over the area
   of the moment ellipse); ``flatness`` tells a sphere's flat-topped disc from
   a Gaussian glint.  Implausible blobs are rejected (see
   :class:`MarkerParams`).  Seeds that fall inside a measured core are not
   measured again.
3. **Sub-pixel centre** on the blob's support: the pixels above 10 % of the
   peak within half a diameter of the core, grown by 2 px, with other blobs
   masked out (a neighbour above half maximum is split off by distance).  One
   of three estimators: ``"centroid"`` (default; background-subtracted
   intensity-weighted centroid of ``max(I - bg - 0.1 peak, 0)``),
   ``"radial"`` (Parthasarathy's radial-symmetry centre, closed form) or
   ``"disc_fit"`` (Levenberg-Marquardt fit of a Gaussian-blurred disc).
   ``bench/bench_markers.py`` compares them; ``docs/markers.md`` has the
   figures behind the default.

Pixel coordinates are OpenCV's: ``(x, y) = (column, row)``, origin at the
centre of the top-left pixel.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

CENTRE_METHODS = ("centroid", "radial", "disc_fit")

_POOL = 4  # max-pooling factor of the full-frame candidate mask
_MARGIN_PX = 3  # support of the centre estimators beyond the half-maximum core
_MAX_SEEDS_PER_REGION = 64
_SIZE_TOL_PX = 0.5  # pixelisation of the measured diameter, allowed beyond the limits
_DISC5 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
_ONES3 = np.ones((3, 3), np.uint8)
_RING_DX = np.array([1, 1, 0, -1, -1, -1, 0, 1])  # 8 directions, times the ring radius
_RING_DY = np.array([0, 1, 1, 1, 0, -1, -1, -1])


@dataclass(frozen=True)
class MarkerParams:
    """What a plausible marker looks like in the image.

    Parameters
    ----------
    diameter_px_min, diameter_px_max : float
        Accepted range of the blob's diameter (px), measured as the minor axis
        of its half-maximum region, so a motion streak keeps its width; 0.5 px
        of pixelisation error is allowed beyond either limit.
    min_contrast : float
        Minimal peak above the local background (gray levels, after a 3x3
        mean) for a blob to count.
    max_elongation : float
        Largest major/minor axis ratio of the half-maximum region; 4 lets
        through a streak about 3.3 diameters long (motion blur) and rejects
        line-like glints.
    min_fill : float
        Smallest ratio of the half-maximum area to the area of its moment
        ellipse (1 for a disc or a streak); rejects ragged or hollow blobs.
    search_radius_px : float
        Default radius (px) of the windowed search around predicted positions.
    centre_method : str
        Sub-pixel centre estimator: ``"centroid"`` (default: as accurate as
        the others on clean, noisy and compressed images, the most robust next
        to distractors, and the cheapest; see ``docs/markers.md``),
        ``"radial"`` or ``"disc_fit"``.
    reject_border : bool
        Reject blobs whose half-maximum region touches the image border (their
        centre would be biased towards the inside).
    """

    diameter_px_min: float = 3.0
    diameter_px_max: float = 40.0
    min_contrast: float = 20.0
    max_elongation: float = 4.0
    min_fill: float = 0.6
    search_radius_px: float = 25.0
    centre_method: str = "centroid"
    reject_border: bool = True

    def __post_init__(self) -> None:
        if not (0 < self.diameter_px_min <= self.diameter_px_max):
            raise ValueError(
                "need 0 < diameter_px_min <= diameter_px_max, got "
                f"{self.diameter_px_min}, {self.diameter_px_max}"
            )
        if not self.min_contrast > 0:
            raise ValueError(f"min_contrast must be > 0, got {self.min_contrast}")
        if not self.max_elongation >= 1:
            raise ValueError(f"max_elongation must be >= 1, got {self.max_elongation}")
        if not 0 <= self.min_fill <= 1:
            raise ValueError(f"min_fill must be in [0, 1], got {self.min_fill}")
        if not self.search_radius_px > 0:
            raise ValueError(f"search_radius_px must be > 0, got {self.search_radius_px}")
        if self.centre_method not in CENTRE_METHODS:
            raise ValueError(
                f"centre_method must be one of {CENTRE_METHODS}, got {self.centre_method!r}"
            )


def params_for(
    marker_diameter_mm: float,
    focal_px: float,
    distance_mm: tuple[float, float],
    **overrides: Any,
) -> MarkerParams:
    """Marker parameters for a sphere of known size seen at a range of distances.

    Parameters
    ----------
    marker_diameter_mm : float
        Diameter of the retro-reflective sphere (mm).
    focal_px : float
        Focal length of the camera (px).
    distance_mm : tuple of float
        ``(nearest, farthest)`` distance (mm) of the marker from the camera.
    **overrides
        Any other :class:`MarkerParams` field.

    Returns
    -------
    MarkerParams
        Diameter limits from the projected sizes with 40 % slack below (small
        markers lose their anti-aliased rim at half maximum) and 30 % + 2 px
        above (defocus and blur widen them); default search radius 1.3 largest
        diameters + 10 px.
    """
    z_near, z_far = (float(v) for v in distance_mm)
    if not (marker_diameter_mm > 0 and focal_px > 0 and 0 < z_near <= z_far):
        raise ValueError(
            "need marker_diameter_mm > 0, focal_px > 0 and 0 < nearest <= farthest distance, "
            f"got {marker_diameter_mm}, {focal_px}, {distance_mm}"
        )
    d_small_px = focal_px * marker_diameter_mm / z_far
    d_large_px = focal_px * marker_diameter_mm / z_near
    values: dict[str, Any] = {
        "diameter_px_min": max(1.5, 0.6 * d_small_px),
        "diameter_px_max": 1.3 * d_large_px + 2.0,
        "search_radius_px": 1.3 * d_large_px + 10.0,
    }
    values.update(overrides)
    return MarkerParams(**values)


@dataclass(frozen=True)
class MarkerDetections:
    """Markers found in one image; row ``i`` of every array is marker ``i``.

    Attributes
    ----------
    xy_px : ndarray, shape (N, 2), float64
        Sub-pixel centres, OpenCV ``(x, y)``, origin at the centre of the
        top-left pixel.
    diameter_px : ndarray, shape (N,)
        Minor axis of the half-maximum region (px): the width of the marker,
        also for a motion streak.
    peak : ndarray, shape (N,)
        Background-subtracted peak of the 3x3-smoothed image (gray levels).
    roundness : ndarray, shape (N,)
        Minor / major axis of the half-maximum region (1 = disc).
    background : ndarray, shape (N,)
        Local background level (gray levels).
    area_px : ndarray, shape (N,)
        Pixel count of the half-maximum region.
    fill : ndarray, shape (N,)
        Half-maximum area over the area of its moment ellipse (1 = disc or
        streak, lower for ragged shapes).
    shape_cov_px2 : ndarray, shape (N, 2, 2)
        Second moments of the half-maximum region (px^2), ``[[xx, xy], [xy,
        yy]]``; its main axis is the direction of a motion streak.
    flatness : ndarray, shape (N,)
        Share of the half-maximum region above 75 % of the peak: about 0.8-1
        for a sphere's disc (flat-topped), 0.42 for a Gaussian glint.
    quality : ndarray, shape (N,)
        Score in [0, 1]: ``roundness * min(fill, 1) * min(1, flatness / 0.6)
        * min(1, peak / (3 * min_contrast))``.  Use it to rank candidates, not
        to reject them.
    """

    xy_px: FloatArray
    diameter_px: FloatArray
    peak: FloatArray
    roundness: FloatArray
    background: FloatArray = field(default_factory=lambda: np.zeros(0))
    area_px: FloatArray = field(default_factory=lambda: np.zeros(0))
    fill: FloatArray = field(default_factory=lambda: np.zeros(0))
    shape_cov_px2: FloatArray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    quality: FloatArray = field(default_factory=lambda: np.zeros(0))
    flatness: FloatArray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return int(self.xy_px.shape[0])

    @classmethod
    def empty(cls) -> MarkerDetections:
        """No marker."""
        z = np.zeros(0)
        return cls(xy_px=np.zeros((0, 2)), diameter_px=z, peak=z.copy(), roundness=z.copy(),
                   background=z.copy(), area_px=z.copy(), fill=z.copy(),
                   shape_cov_px2=np.zeros((0, 2, 2)), quality=z.copy(),
                   flatness=z.copy())  # fmt: skip


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


# --------------------------------------------------------------------------- public


def detect_markers(
    image: NDArray[Any],
    *,
    params: MarkerParams = MarkerParams(),
    search_xy_px: NDArray[Any] | None = None,
    search_radius_px: float | None = None,
    background: NDArray[Any] | None = None,
) -> MarkerDetections:
    """Find bright round markers and their sub-pixel centres in a gray image.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8
        Gray frame.
    params : MarkerParams
        Size, contrast and shape limits and the centre estimator.
    search_xy_px : ndarray, shape (K, 2), optional
        Predicted marker positions (px, OpenCV ``(x, y)``).  When given, only
        markers whose centre lies within ``search_radius_px`` of one of them
        are looked for (fast path for tracking).  Rows with NaN are skipped.
        ``None``: search the full frame.
    search_radius_px : float, optional
        Radius (px) of the windowed search; default
        ``params.search_radius_px``.
    background : ndarray, shape (H, W), uint8, optional
        Image of the static scene without markers (see
        :func:`estimate_background`).  Around each blob it is subtracted
        before the sub-pixel centre is computed, which removes the fixed
        background texture under the markers, the largest error left on a
        textured background with motion blur (see ``docs/markers.md``); where
        the image holds a bright blob itself (a marker that rested there), it
        is ignored for that blob.  Finding and measuring the blobs (``peak``,
        ``background``, shape) always use the frame itself.

    Returns
    -------
    MarkerDetections
        The accepted markers, brightest first within each searched region.

    Raises
    ------
    ValueError
        If ``image`` is not a 2-D uint8 array, or ``search_xy_px`` is not
        ``(K, 2)``, or ``search_radius_px`` is not positive, or ``background``
        is not a uint8 array of the image's shape.
    """
    if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8:
        desc = (
            f"shape {image.shape}, dtype {image.dtype}"
            if isinstance(image, np.ndarray)
            else type(image).__name__
        )
        raise ValueError(f"image must be a 2-D uint8 gray array (H, W), got {desc}")
    if image.shape[0] < 3 or image.shape[1] < 3:
        raise ValueError(f"image must be at least 3x3 pixels, got shape {image.shape}")
    if search_radius_px is not None and not search_radius_px > 0:
        raise ValueError(f"search_radius_px must be > 0, got {search_radius_px}")
    radius_px = float(params.search_radius_px if search_radius_px is None else search_radius_px)
    image = np.ascontiguousarray(image)  # OpenCV needs C order (a no-op for video frames)
    if background is not None:
        if (
            not isinstance(background, np.ndarray)
            or background.dtype != np.uint8
            or background.shape != image.shape
        ):
            desc = (
                f"shape {background.shape}, dtype {background.dtype}"
                if isinstance(background, np.ndarray)
                else type(background).__name__
            )
            raise ValueError(
                f"background must be a uint8 array of the image's shape {image.shape}, got {desc}"
            )
        background = np.ascontiguousarray(background)

    measured: list[_Measured] = []
    if search_xy_px is None:
        bg, sigma = _background_and_noise(image[::8, ::8])
        thr = bg + max(0.5 * params.min_contrast, 4.0 * sigma)
        for x0, y0, x1, y1 in _full_frame_regions(image, thr, params):
            measured.extend(
                _search_region(image, (x0, y0, x1, y1), thr, params, measured, background)
            )
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
            found = _search_region(image, (x0, y0, x1, y1), thr, params, measured, background)
            centres = group.tolist()
            for m in found:
                if m.blob is not None:
                    bx, by = m.blob.xy_px
                    if min((gx - bx) ** 2 + (gy - by) ** 2 for gx, gy in centres) > r2:
                        m.blob = None  # outside the search discs; keep the core as "seen"
            measured.extend(found)
    return _to_detections([m.blob for m in measured if m.blob is not None])


def estimate_background(
    frames: Sequence[NDArray[Any]], *, quantile: float = 0.5
) -> NDArray[np.uint8]:
    """Image of the static scene from frames in which the markers have moved.

    Parameters
    ----------
    frames : sequence of ndarray, each (H, W) uint8
        Frames spread over the recording (e.g. 9-15 frames, seconds apart), so
        that every pixel a marker covers in one frame is free in most others.
    quantile : float
        Per-pixel quantile over the frames: 0.5 (median) by default; lower
        (e.g. 0.2) if markers may rest at one place for up to half of the
        frames.  The result is biased low by about ``(0.5 - quantile)`` noise
        sigmas, which does not matter (detection measures the background
        around each blob again).

    Returns
    -------
    ndarray, shape (H, W), uint8
        To pass as ``detect_markers(..., background=...)``.  A marker that did
        not move in most of the frames is part of this image and would be
        subtracted away: choose frames from the whole recording.

    Raises
    ------
    ValueError
        If ``frames`` is empty, or the frames are not uint8 (H, W) of one
        size, or ``quantile`` is outside [0, 1].
    """
    if len(frames) == 0:
        raise ValueError("frames is empty; pass at least one (H, W) uint8 frame")
    if not 0 <= quantile <= 1:
        raise ValueError(f"quantile must be in [0, 1], got {quantile}")
    shape = np.shape(frames[0])
    for f in frames:
        if not isinstance(f, np.ndarray) or f.dtype != np.uint8 or f.ndim != 2 or f.shape != shape:
            desc = f"{f.shape} {f.dtype}" if isinstance(f, np.ndarray) else type(f).__name__
            raise ValueError(f"frames must all be uint8 (H, W) of shape {shape}, got {desc}")
    stack = np.stack(frames)
    k = round(quantile * (len(frames) - 1))  # a sample quantile (no interpolation)
    return np.ascontiguousarray(np.partition(stack, k, axis=0)[k])


# ------------------------------------------------------------------- candidates


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
    contours, _ = cv2.findContours(pooled, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    pad = _MARGIN_PX + 3
    regions = []
    for contour in contours:
        x, y, bw, bh = cv2.boundingRect(contour)
        x0, y0 = max(0, x * _POOL - pad), max(0, y * _POOL - pad)
        x1, y1 = min(w, (x + bw) * _POOL + pad), min(h, (y + bh) * _POOL + pad)
        regions.append((x0, y0, x1, y1))
    regions.sort(key=lambda r: (r[1], r[0]))  # raster order, independent of OpenCV's
    return regions


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
    background: NDArray[np.uint8] | None = None,
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
        m = _measure(image, sx, sy, params, cache, background)
        taken[sy - y0, sx - x0] = 1
        mark(m)
        if m.core is not None:
            out.append(m)
        if len(out) >= _MAX_SEEDS_PER_REGION:
            break
    return out


# ------------------------------------------------------------------- measurement


def _ring_radius(params: MarkerParams) -> int:
    """Half-size (px) of the first measurement window, whose border gives the background."""
    return math.ceil(0.5 * params.diameter_px_max) + 3


def _measure(
    image: NDArray[np.uint8],
    sx: int,
    sy: int,
    params: MarkerParams,
    cache: tuple[NDArray[np.float32], int, int] | None = None,
    background: NDArray[np.uint8] | None = None,
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
    sup: NDArray[np.bool_] | None = None
    if _SUPPORT_ON_SUBRECT and not has_neighbour:
        # The usual case, on the centre's rectangle only (the same pixels): ``near``
        # reaches ``margin`` beyond the core's box, the support 2 px further, both
        # inside the rectangle, which is ``margin + 3`` beyond the box.
        near_s = cast("NDArray[np.uint8]", cv2.dilate(core[sy0:sy1, sx0:sx1], _square_kernel(k)))
        low_near_s = low_mask[sy0:sy1, sx0:sx1] & near_s
        if cv2.countNonZero(low_mask) == cv2.countNonZero(low_near_s):
            sup = cast("NDArray[np.uint8]", cv2.dilate(low_near_s, _DISC5)).view(bool)
    if sup is None:
        sup = _support_full(core, mask, low_mask, k, has_neighbour)[sy0:sy1, sx0:sx1].view(bool)
    sub = np.subtract(win[sy0:sy1, sx0:sx1], bg, dtype=np.float64)
    if background is not None:
        # subtract the static scene where it is only background texture; where it
        # holds a bright blob (a marker that rested there) keep the flat level
        bgw = background[y0 + sy0 : y0 + sy1, x0 + sx0 : x0 + sx1].astype(np.float64)
        level = float(np.median(bgw))
        if float(bgw[sup].max()) - level < 0.25 * peak:
            diff = win[sy0:sy1, sx0:sx1] - bgw
            edge = np.concatenate((diff[0], diff[-1], diff[1:-1, 0], diff[1:-1, -1]))
            sub = diff - float(np.median(edge))
    mx, my = mom["m10"] / mom["m00"] + bx - sx0, mom["m01"] / mom["m00"] + by - sy0
    cx, cy = _centre(sub, sup, peak, mx, my, params.centre_method)
    if not (math.isfinite(cx) and math.isfinite(cy)) or math.hypot(cx - mx, cy - my) > 0.5 * (
        diameter + 4
    ):
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
_SUPPORT_ON_SUBRECT = True


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
            d_own = cv2.distanceTransform(1 - core, cv2.DIST_L2, 3)
            d_other = cv2.distanceTransform(1 - other_cores, cv2.DIST_L2, 3)
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


def _centre(
    sub: FloatArray, support: NDArray[np.bool_], peak: float, x0: float, y0: float, method: str
) -> tuple[float, float]:
    """Sub-pixel centre in the coordinates of ``sub`` (background already subtracted)."""
    if method == "radial":
        return _radial_centre(sub, support)
    if method == "centroid":
        return _centroid(sub, support, peak)
    return _disc_fit(sub, support, peak, x0, y0)


def _centroid(sub: FloatArray, support: NDArray[np.bool_], peak: float) -> tuple[float, float]:
    """Intensity-weighted centroid of ``max(I - bg - 0.1 peak, 0)`` on the support."""
    wgt = sub - 0.1 * peak
    np.maximum(wgt, 0.0, out=wgt)
    wgt *= support  # 0 outside the support (the same values as np.where, one temporary less)
    mom = cv2.moments(wgt)  # sums in float64, in one pass
    s = mom["m00"]
    if s <= 0:
        return math.nan, math.nan
    return float(mom["m10"] / s), float(mom["m01"] / s)


def _radial_centre(sub: FloatArray, support: NDArray[np.bool_]) -> tuple[float, float]:
    """Radial-symmetry centre (Parthasarathy 2012, Nat. Methods 9:724).

    Gradients at the pixel corners; the centre is the point closest, in the
    weighted least-squares sense, to all lines through the corners along their
    gradients, weighted by squared gradient over distance to the gradient
    centroid.
    """
    a = sub[:-1, :-1]
    b = sub[:-1, 1:]
    c = sub[1:, :-1]
    d = sub[1:, 1:]
    gx = 0.5 * ((b + d) - (a + c))
    gy = 0.5 * ((c + d) - (a + b))
    gx = np.asarray(cv2.blur(gx, (3, 3), borderType=cv2.BORDER_REPLICATE), dtype=np.float64)
    gy = np.asarray(cv2.blur(gy, (3, 3), borderType=cv2.BORDER_REPLICATE), dtype=np.float64)
    ok = support[:-1, :-1] & support[:-1, 1:] & support[1:, :-1] & support[1:, 1:]
    g2 = np.where(ok, gx * gx + gy * gy, 0.0)
    s = g2.sum()
    if s <= 0:
        return math.nan, math.nan
    ys = np.arange(g2.shape[0], dtype=np.float64)[:, None] + 0.5
    xs = np.arange(g2.shape[1], dtype=np.float64)[None, :] + 0.5
    xc = float((g2 * xs).sum() / s)
    yc = float((g2 * ys).sum() / s)
    dist = np.sqrt((xs - xc) ** 2 + (ys - yc) ** 2)
    wgt = np.where(ok, g2 / np.maximum(dist, 0.5), 0.0)
    gn2 = np.maximum(gx * gx + gy * gy, 1e-12)
    # normal n = (-gy, gx)/|g|; sum w n n^T c = sum w n n^T p
    nxx = wgt * gy * gy / gn2
    nyy = wgt * gx * gx / gn2
    nxy = -wgt * gx * gy / gn2
    sxx, syy, sxy = nxx.sum(), nyy.sum(), nxy.sum()
    bx = (nxx * xs + nxy * ys).sum()
    by = (nxy * xs + nyy * ys).sum()
    det = sxx * syy - sxy * sxy
    if det <= 1e-12 * max(sxx * syy, 1e-300):
        return math.nan, math.nan
    return float((syy * bx - sxy * by) / det), float((sxx * by - sxy * bx) / det)


def _disc_fit(
    sub: FloatArray, support: NDArray[np.bool_], peak: float, x0: float, y0: float
) -> tuple[float, float]:
    """Least-squares fit of a Gaussian-blurred disc ``B + A Phi((R - r) / s)``.

    Levenberg-Marquardt on ``(cx, cy, R, s, A, B)`` started from the
    centroid; a motion streak is not a disc, but the fit stays symmetric.
    """
    from scipy.special import ndtr  # here: a detection worker process need not import scipy

    ys, xs = np.nonzero(support)
    z = sub[ys, xs]
    xs_f, ys_f = xs.astype(np.float64), ys.astype(np.float64)
    c0 = _centroid(sub, support, peak)
    if not math.isfinite(c0[0]):
        c0 = (x0, y0)
    area = float(np.count_nonzero(sub > 0.5 * peak))
    p = np.array([c0[0], c0[1], max(math.sqrt(area / math.pi), 1.0), 0.7, peak, 0.0])
    lam = 1e-3

    def residual(q: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        dx, dy = xs_f - q[0], ys_f - q[1]
        r = np.sqrt(dx * dx + dy * dy) + 1e-9
        u = (q[2] - r) / q[3]
        return q[5] + q[4] * ndtr(u) - z, dx / r, dy / r, u

    res, ux, uy, u = residual(p)
    cost = float(res @ res)
    for _ in range(30):
        phi = np.exp(-0.5 * u * u) * (1.0 / math.sqrt(2 * math.pi))
        a_phi_s = p[4] * phi / p[3]
        jac = np.column_stack((a_phi_s * ux, a_phi_s * uy, a_phi_s, -a_phi_s * u, ndtr(u),
                               np.ones_like(u)))  # fmt: skip
        jtj = jac.T @ jac
        jtr = jac.T @ res
        step_ok = False
        for _ in range(8):
            try:
                delta = np.linalg.solve(jtj + lam * np.diag(np.diag(jtj) + 1e-9), -jtr)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            q = p + delta
            q[3] = max(q[3], 0.2)
            q[2] = max(q[2], 0.3)
            res_q, ux_q, uy_q, u_q = residual(q)
            cost_q = float(res_q @ res_q)
            if cost_q < cost:
                p, res, ux, uy, u, cost = q, res_q, ux_q, uy_q, u_q, cost_q
                lam = max(lam / 10, 1e-7)
                step_ok = True
                break
            lam *= 10
        if not step_ok or float(np.abs(delta[:2]).max()) < 1e-3:  # px, far below the noise
            break
    return float(p[0]), float(p[1])


# ------------------------------------------------------------ search along a video
# Used by core.pipeline (one instance per camera, in a thread or a worker process).

#: A full-frame marker search at least this often (frames), to pick up new markers.
FULL_SEARCH_EVERY = 10
#: The last few full-frame searches define how many markers to expect.
EXPECTED_COUNT_FULL_SEARCHES = 5
#: After this many fallback full searches in a row that found nothing the windowed search
#: had missed (a reflection that flickers off, a marker hidden for a while), fall back
#: only on every other frame until the count is reached again: a reappearing marker
#: is picked up at most one frame later, at half the cost.
UNPRODUCTIVE_FALLBACKS_BEFORE_BACKOFF = 2
#: At most this many detections per frame and camera go to matching (brightest/roundest).
MAX_DETECTIONS_PER_FRAME = 16


# A detector takes (gray image, predicted xy (K, 2) or None, search radius px or None)
# and returns (xy_px (N, 2), diameter_px (N,), quality (N,)).
Detector = Callable[
    [NDArray[np.uint8], FloatArray | None, float | None], tuple[FloatArray, FloatArray, FloatArray]
]


def _default_detector(params: Any | None) -> Detector:
    p = params if params is not None else MarkerParams()

    def detect(
        image: NDArray[np.uint8], search_xy_px: FloatArray | None, radius_px: float | None
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        d = detect_markers(image, params=p, search_xy_px=search_xy_px, search_radius_px=radius_px)
        q = d.quality if len(d.quality) == len(d) else d.peak
        return d.xy_px, d.diameter_px, q

    return detect


def _median(values: FloatArray) -> float:
    """``np.median`` of a short 1-D array, without its ~20 us of overhead per call."""
    v = sorted(np.asarray(values, dtype=np.float64).ravel().tolist())
    n = len(v)
    return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])


class _CameraDetections:
    """Per-frame detections of one camera, with predicted search windows.

    Prediction: each detection of the previous frame may move on by the
    displacement from its nearest neighbour in the frame before (a
    constant-velocity guess) or stay; the search window is centred between
    the two and its radius covers both, the marker size and what the
    velocity guess may miss.
    """

    def __init__(self, detect: Detector, *, full_every: int = FULL_SEARCH_EVERY) -> None:
        self.detect = detect
        self.full_every = full_every
        self.frames: list[FloatArray] = []
        self.n_full = 0
        self._recent_full: list[tuple[int, int]] = []  # (frame, count)
        self._prev: FloatArray | None = None
        self._prev2: FloatArray | None = None
        self._diam = 10.0
        self._unproductive = 0  # fallback full searches in a row that found nothing more

    def _expected(self) -> int:
        # Markers reliably seen: the median count of the last few full searches
        # (one search during a short occlusion does not lower it, so the marker
        # is picked up again as soon as it reappears).
        self._recent_full = self._recent_full[-EXPECTED_COUNT_FULL_SEARCHES:]
        if not self._recent_full:
            return 0
        counts = sorted(c for _, c in self._recent_full)
        n = len(counts)
        return (counts[(n - 1) // 2] + counts[n // 2]) // 2  # floor of the median

    def _predict(self) -> tuple[FloatArray | None, float]:
        prev = self._prev
        if prev is None or len(prev) == 0:
            return None, 0.0
        pred = prev.copy()
        step = np.zeros(len(prev))
        if self._prev2 is not None and len(self._prev2):
            d = np.linalg.norm(prev[:, None, :] - self._prev2[None, :, :], axis=2)
            j = np.argmin(d, axis=1)
            near = d[np.arange(len(prev)), j] < 4 * self._diam + 40.0
            vel = np.where(near[:, None], prev - self._prev2[j], 0.0)
            # Centre between "stays" and "moves on": right whether or not the
            # nearest-neighbour velocity belongs to this marker.
            pred = prev + 0.5 * vel
            step = np.linalg.norm(vel, axis=1)
        radius = 1.5 * self._diam + 12.0 + 0.5 * float(step.max(initial=0.0))
        return pred, radius

    def process(self, image: NDArray[np.uint8]) -> None:
        frame = len(self.frames)
        pred, radius = self._predict()
        expected = self._expected()
        scheduled = pred is None or frame % self.full_every == 0
        full = scheduled
        xy = np.zeros((0, 2))
        diam = q = np.zeros(0)
        n_windowed = -1
        if not full:
            xy, diam, q = self.detect(image, pred, radius)
            if len(xy) >= expected:
                self._unproductive = 0
            elif self._unproductive < UNPRODUCTIVE_FALLBACKS_BEFORE_BACKOFF or frame % 2 == 0:
                full, n_windowed = True, len(xy)
        if full:
            xy, diam, q = self.detect(image, None, None)
            self.n_full += 1
            if scheduled:  # searches made because something was missing would bias the count
                self._recent_full.append((frame, len(xy)))
            elif len(xy) <= n_windowed:  # the missing blob is not anywhere in the frame
                self._unproductive += 1
            else:
                self._unproductive = 0
        if len(xy) > MAX_DETECTIONS_PER_FRAME:
            keep = np.argsort(-q, kind="stable")[:MAX_DETECTIONS_PER_FRAME]
            xy, diam = xy[keep], diam[keep]
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if len(diam):
            self._diam = 0.9 * self._diam + 0.1 * _median(diam)
        self.frames.append(xy)
        self._prev2, self._prev = self._prev, xy


def _video_detection_worker(
    path: str, expected_count: int, params: MarkerParams | None, send: Callable[[Any], None]
) -> None:
    """Decode one video and search it frame by frame, as one camera's worker process.

    Sends ``("progress", frames_done)`` every 50 frames and finally ``("done",
    xy_px (M, 2), counts (T,), n_full)``: only the small per-frame detections
    leave the worker, never a frame.  Any exception is sent as ``("error",
    exception)`` (the original one when it pickles, else a ``RuntimeError``
    with its type and message).  Stops by itself when the parent is gone.
    """
    import os
    import pickle

    from core.video import iter_frames

    parent = os.getppid()
    try:
        state = _CameraDetections(_default_detector(params))
        for i, image in enumerate(iter_frames(path, gray=True, expected_count=expected_count)):
            state.process(image)
            if i % 50 == 49:
                if os.getppid() != parent:  # orphaned: nobody wants the result
                    return
                send(("progress", i + 1))
        counts = np.array([len(f) for f in state.frames], dtype=np.int64)
        flat = np.concatenate(state.frames) if state.frames else np.zeros((0, 2))
        send(("done", flat, counts, state.n_full))
    except BaseException as exc:
        payload: BaseException
        try:
            payload = pickle.loads(pickle.dumps(exc))
        except Exception:
            payload = RuntimeError(f"{type(exc).__name__}: {exc}")
        try:
            send(("error", payload))
        except OSError:  # the parent is gone
            pass


def _video_detection_main() -> None:
    """Body of a worker process started by ``core.pipeline`` (``python -c``).

    Reads ``(path, expected_count, params)`` pickled on stdin and writes the
    pickled messages of :func:`_video_detection_worker` to stdout; anything
    else that would be printed goes to stderr, so the message stream stays
    clean.  A plain interpreter, not ``multiprocessing``: the caller's main
    module is never re-imported, and only this module and ``core.video`` are
    (~0.2 s, no scipy).
    """
    import os
    import pickle
    import sys

    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    path, expected_count, params = pickle.load(sys.stdin.buffer)

    def send(msg: Any) -> None:
        pickle.dump(msg, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()

    try:
        _video_detection_worker(path, expected_count, params, send)
    finally:
        try:
            out.close()
        except OSError:
            pass

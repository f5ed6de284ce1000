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

Steps 1-3 run compiled (``core/_blobs.pyx``, one call per frame, without the
GIL), except the contours of step 1 (``cv2.findContours``) and the
``radial``/``disc_fit`` estimators and static-background subtraction, which
run here on the support the compiled search returns.

Pixel coordinates are OpenCV's: ``(x, y) = (column, row)``, origin at the
centre of the top-left pixel.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

try:
    from core import _blobs
except ImportError as exc:  # pragma: no cover - a source tree that was never installed
    raise ImportError(
        "core._blobs (the compiled marker search, core/_blobs.pyx) is not built: "
        "install the project with `pip install -e .` (needs a C compiler)"
    ) from exc

FloatArray = NDArray[np.float64]

CENTRE_METHODS = ("centroid", "radial", "disc_fit", "opaque_disc")

_POOL = 4  # max-pooling factor of the full-frame candidate mask
_MARGIN_PX = 3  # support of the centre beyond the half-maximum core (MARGIN_PX in _blobs.pyx)
_MAX_SEEDS_PER_REGION = 64


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
        Sub-pixel centre estimator: ``"opaque_disc"`` (default: the
        background-subtracted centroid on the dark room, where it is exact
        and the cheapest; a blurred opaque disc over a planar background,
        fitted, where the marker sits on lit skin or near a finger's edge,
        which pull a centroid by up to a pixel, with a straight skin edge
        under it or hiding part of it where that fits better; see
        ``docs/markers.md``),
        ``"centroid"`` everywhere, ``"radial"`` or ``"disc_fit"``.
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
    centre_method: str = "opaque_disc"
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
    fit_residual : ndarray, shape (N,)
        ``"opaque_disc"`` only: RMS residual of the disc fit (with a straight
        skin edge under or in front of it where that fits better) beyond the
        image noise, over the marker's contrast (below 0.04 for a whole marker
        on skin; more when two markers merge, see ``docs/markers.md``);
        ``inf`` for a blob too elongated to be one disc (a motion streak, or a
        cut or merged marker) or a marker more than ``MAX_HIDDEN_SHARE``
        behind skin; NaN where no disc was fitted (on the dark background,
        and with the other estimators).
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
    fit_residual: FloatArray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return int(self.xy_px.shape[0])

    @classmethod
    def empty(cls) -> MarkerDetections:
        """No marker."""
        z = np.zeros(0)
        return cls(xy_px=np.zeros((0, 2)), diameter_px=z, peak=z.copy(), roundness=z.copy(),
                   background=z.copy(), area_px=z.copy(), fill=z.copy(),
                   shape_cov_px2=np.zeros((0, 2, 2)), quality=z.copy(),
                   flatness=z.copy(), fit_residual=z.copy())  # fmt: skip


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

    return _to_detections(_detected_rows(image, params, search_xy_px, radius_px, background))


def _detected_rows(
    image: NDArray[np.uint8],
    params: MarkerParams,
    search_xy_px: NDArray[Any] | None,
    radius_px: float,
    background: NDArray[np.uint8] | None,
) -> FloatArray:
    """:func:`detect_markers` on checked arguments: the rows of the accepted blobs
    (columns in ``_blobs.COLUMNS``), without building a :class:`MarkerDetections`."""
    pts = np.zeros((0, 2))
    point_region = np.zeros(0, dtype=np.int32)
    if search_xy_px is None:
        bg, sigma = _blobs.background_and_noise(image, 8)
        thr = bg + max(0.5 * params.min_contrast, 4.0 * sigma)
        regions = np.asarray(_full_frame_regions(image, thr, params), dtype=np.int32).reshape(-1, 4)
    else:
        pts = np.asarray(search_xy_px, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"search_xy_px must have shape (K, 2), got {pts.shape}")
        finite = np.isfinite(pts)
        if not finite.all():
            pts = pts[finite.all(axis=1)]
        pts = np.ascontiguousarray(pts)
        # seeds are blob maxima: within the radius plus a streak's half length
        reach = radius_px + 0.5 * params.diameter_px_max
        regions, point_region = _blobs.merged_windows(pts, reach, image.shape[0], image.shape[1])
        if background is None and params.centre_method in ("centroid", "opaque_disc"):
            # the common case, tracking: one compiled call, the GIL released once
            return _measured_windows(image, params, pts, point_region, regions, radius_px)
        bg, sigma = _blobs.background_and_noise(image, 16) if len(regions) else (0.0, 0.0)
        thr = bg + max(0.5 * params.min_contrast, 4.0 * sigma)
    if len(regions) == 0:
        return np.zeros((0, len(_blobs.COLUMNS)))
    want_support = params.centre_method in ("radial", "disc_fit") or background is not None
    rows, supports = _blobs.search(
        image,
        regions,
        thr,
        params.diameter_px_min,
        params.diameter_px_max,
        params.min_contrast,
        params.max_elongation,
        params.min_fill,
        params.reject_border,
        _ring_radius(params),
        math.ceil(params.diameter_px_max * params.max_elongation) + _MARGIN_PX + 2,
        _MAX_SEEDS_PER_REGION,
        want_support,
    )
    if supports is not None:
        _recentre(rows, supports, image, params, background)
    kept = rows[_blobs.select(rows, pts, point_region, radius_px**2)]
    if params.centre_method == "opaque_disc" and len(kept):
        _fit_opaque_discs(image, kept, rows[:, _X : _Y + 1], thr, sigma)
    return kept


def _measured_windows(
    image: NDArray[np.uint8],
    params: MarkerParams,
    pts: FloatArray,
    point_region: NDArray[np.int32],
    regions: NDArray[np.int32],
    radius_px: float,
) -> FloatArray:
    """The windowed branch of :func:`_detected_rows` for a centre found without the
    blob's support (the centroid, or the opaque-disc fit): ``_blobs.measure_regions``
    does the noise, search, selection and fits that the general branch does one call
    at a time, with the same numbers."""
    rows, _, _ = _blobs.measure_regions(
        image,
        regions,
        pts,
        point_region,
        radius_px**2,
        16,
        params.min_contrast,
        params.diameter_px_min,
        params.diameter_px_max,
        params.max_elongation,
        params.min_fill,
        params.reject_border,
        _ring_radius(params),
        math.ceil(params.diameter_px_max * params.max_elongation) + _MARGIN_PX + 2,
        _MAX_SEEDS_PER_REGION,
        params.centre_method == "opaque_disc",
        _FIT_MAX_STEPS,
        _FIT_PAD_PX,
        _FIT_MIN_ROUNDNESS,
        MAX_HIDDEN_SHARE,
    )
    return rows


#: Opaque-disc fit: window half-size beyond the blob's half length (px), LM steps.
_FIT_PAD_PX = 3.0
_FIT_MAX_STEPS = 10
#: Blobs less round than this (motion streaks, merged or cut discs) are not discs:
#: they keep their centroid.
_FIT_MIN_ROUNDNESS = 0.75
#: A marker whose fitted skin edge in front hides more than this share of its disc is set
#: aside (infinite fit residual): the straight edge is not trusted for a larger part.
MAX_HIDDEN_SHARE = 0.15
#: A fitted disc whose RMS residual exceeds this share of its contrast is not one whole
#: marker (whole markers on skin: 0.027-0.043; a tenth hidden: 0.04-0.06; a quarter:
#: 0.09-0.13; bench/bench_hands.py): the pipeline sets it aside.
MAX_FIT_RESIDUAL = 0.05


def _fit_opaque_discs(
    image: NDArray[np.uint8],
    rows: FloatArray,
    all_xy: FloatArray,
    dark_level: float,
    noise_sigma: float,
) -> None:
    """Centres (in place) from an opaque blurred disc over a planar background
    (``_blobs.refine_rows``) for the round blobs whose surroundings are brighter than
    ``dark_level`` (the detection threshold: skin, not the dark room, where the
    centroid is exact and cheaper; a soft glint whose own halo lights the fit window's
    border but not a border 3 px wider, with no other blob inside, is on the dark room
    too); the fit residual beyond the image noise, over the
    marker's contrast, goes to the ``_FIT_RES`` column (NaN where no fit was made)."""
    _blobs.refine_rows(
        image,
        rows,
        np.ascontiguousarray(all_xy),
        _FIT_MAX_STEPS,
        float(dark_level),
        _FIT_PAD_PX,
        _FIT_MIN_ROUNDNESS,
        float(noise_sigma),
        1,
        MAX_HIDDEN_SHARE,
    )


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


def _full_frame_regions(
    image: NDArray[np.uint8], thr: float, params: MarkerParams
) -> list[tuple[int, int, int, int]]:
    """Regions ``(x0, y0, x1, y1)`` (half-open, px) around the bright components.

    The pixels above ``thr`` max-pooled in 4x4 cells; the bounding boxes of
    the pooled components' outer contours, ``_MARGIN_PX + 3`` px larger.
    """
    h, w = image.shape
    return _pooled_regions(_blobs.pool_mask(image, min(math.floor(thr), 254), _POOL), h, w)


def _pooled_regions(pooled: NDArray[np.uint8], h: int, w: int) -> list[tuple[int, int, int, int]]:
    """Regions of an ``(H, W)`` image around the outer contours of its pooled mask."""
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


# ------------------------------------------------------------------- measurement
# Seeds and blob measurement are compiled (core/_blobs.pyx, columns in _blobs.COLUMNS).

_X, _Y, _DIAM, _PEAK, _ROUND, _BG, _AREA, _FILL, _CXX, _CXY, _CYY, _QUAL, _FLAT = range(13)
_RX0, _RY0, _RX1, _RY1, _MX, _MY, _REGION, _FIT_RES = range(13, 21)


def _ring_radius(params: MarkerParams) -> int:
    """Half-size (px) of the first measurement window, whose border gives the background."""
    return math.ceil(0.5 * params.diameter_px_max) + 3


def _recentre(
    rows: FloatArray,
    supports: list[NDArray[np.uint8]],
    image: NDArray[np.uint8],
    params: MarkerParams,
    background: NDArray[np.uint8] | None,
) -> None:
    """Sub-pixel centres (in place) by ``params.centre_method`` on each blob's support,
    after subtracting the static scene ``background`` when given."""
    for row, support in zip(rows, supports, strict=True):
        rx0, ry0, rx1, ry1 = (int(v) for v in row[_RX0 : _RY1 + 1])
        bg, peak = float(row[_BG]), float(row[_PEAK])
        sup = support.view(bool)
        win = image[ry0:ry1, rx0:rx1]
        sub = np.subtract(win, bg, dtype=np.float64)
        if background is not None:
            # subtract the static scene where it is only background texture; where it
            # holds a bright blob (a marker that rested there) keep the flat level
            bgw = background[ry0:ry1, rx0:rx1].astype(np.float64)
            level = float(np.median(bgw))
            if float(bgw[sup].max()) - level < 0.25 * peak:
                diff = win - bgw
                edge = np.concatenate((diff[0], diff[-1], diff[1:-1, 0], diff[1:-1, -1]))
                sub = diff - float(np.median(edge))
        mx, my = float(row[_MX]), float(row[_MY])
        cx, cy = _centre(sub, sup, peak, mx, my, params.centre_method)
        if not (math.isfinite(cx) and math.isfinite(cy)) or math.hypot(cx - mx, cy - my) > 0.5 * (
            float(row[_DIAM]) + 4
        ):
            cx, cy = _centroid(sub, sup, peak)
        row[_X], row[_Y] = cx + rx0, cy + ry0


def _to_detections(rows: FloatArray) -> MarkerDetections:
    """Detections from rows of the compiled search (columns in ``_blobs.COLUMNS``)."""
    if len(rows) == 0:
        return MarkerDetections.empty()
    cols = np.ascontiguousarray(rows[:, : _FLAT + 1].T)
    cov = np.empty((len(rows), 2, 2))
    cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1] = cols[_CXX], cols[_CXY], cols[_CYY]
    cov[:, 1, 0] = cols[_CXY]
    return MarkerDetections(
        xy_px=np.ascontiguousarray(cols[[_X, _Y]].T),
        diameter_px=cols[_DIAM],
        peak=cols[_PEAK],
        roundness=cols[_ROUND],
        background=cols[_BG],
        area_px=cols[_AREA],
        fill=cols[_FILL],
        shape_cov_px2=cov,
        quality=cols[_QUAL],
        flatness=cols[_FLAT],
        fit_residual=np.ascontiguousarray(rows[:, _FIT_RES]),
    )


# ------------------------------------------------------------------ centre estimators


def _centre(
    sub: FloatArray, support: NDArray[np.bool_], peak: float, x0: float, y0: float, method: str
) -> tuple[float, float]:
    """Sub-pixel centre in the coordinates of ``sub`` (background already subtracted)."""
    if method == "radial":
        return _radial_centre(sub, support)
    if method == "disc_fit":
        return _disc_fit(sub, support, peak, x0, y0)
    return _centroid(sub, support, peak)  # "opaque_disc" fits its disc after the selection


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
    from scipy.special import ndtr  # here: only this optional estimator needs scipy

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
# Used by core.pipeline (one instance per camera, each in its own thread).

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
#: A blob that does not fit a whole disc is set aside only when it moved less than this
#: many diameters since the previous frame (faster: a motion streak, kept).
SET_ASIDE_MAX_STEP = 0.2
#: Two detections whose centres are closer than their mean diameter + this (px) touch:
#: their pixels are kept (with those of every set-aside blob) for core.merged.
TOUCHING_GAP_PX = 4.0
#: Margin of a kept patch around its blobs (px, beyond one typical diameter).
PATCH_MARGIN_PX = 4


# A detector takes (gray image, predicted xy (K, 2) or None, search radius px or None)
# and returns (xy_px (N, 2), diameter_px (N,), quality (N,)); a negative quality marks a
# blob that is not one whole marker (part of it hidden, or two markers merged): it is
# set aside (counted, never measured).
Detector = Callable[
    [NDArray[np.uint8], FloatArray | None, float | None], tuple[FloatArray, FloatArray, FloatArray]
]


def _default_detector(params: Any | None) -> Detector:
    p = params if params is not None else MarkerParams()

    def detect(
        image: NDArray[np.uint8], search_xy_px: FloatArray | None, radius_px: float | None
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        # frames from core.video are C-contiguous uint8 (H, W): detect_markers' checks
        # and its MarkerDetections are skipped (~40 us per frame)
        r = float(p.search_radius_px if radius_px is None else radius_px)
        rows = _detected_rows(image, p, search_xy_px, r, None)
        quality = rows[:, _QUAL].copy()
        quality[rows[:, _FIT_RES] > MAX_FIT_RESIDUAL] = -1.0  # not a whole disc: set aside
        return rows[:, _X : _Y + 1].copy(), rows[:, _DIAM].copy(), quality

    return detect


@dataclass(frozen=True)
class ImagePatch:
    """Pixels of one frame of one camera around blobs that are not one whole marker each.

    Attributes
    ----------
    x0, y0 : int
        Image column and row of ``pixels[0, 0]``.
    pixels : ndarray, shape (h, w), uint8
    points_px : ndarray, shape (K, 2)
        The blobs inside (px, OpenCV ``(x, y)``): set aside, or detected.
    detections : ndarray, shape (D,), int
        Which of the frame's detections lie in it (``core.merged`` replaces them by the
        markers it measures).
    diameter_px : float
        The camera's typical marker diameter at the time (px).
    """

    x0: int
    y0: int
    pixels: NDArray[np.uint8]
    points_px: FloatArray
    detections: NDArray[np.intp]
    diameter_px: float


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
        self.n_set_aside = 0  # frames with a blob set aside (partly hidden or merged)
        # frame -> pixels around set-aside or touching blobs (measured by core.merged)
        self.patches: dict[int, list[ImagePatch]] = {}

    @property
    def diameter_px(self) -> float:
        """Running typical diameter of the detections (px)."""
        return self._diam

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
        # Plain Python floats: 2-10 detections, where numpy's per-call cost dominates.
        # The same float64 operations as the vectorised form (distances as
        # sqrt(dx*dx + dy*dy), the first nearest neighbour on ties).
        prev = self._prev
        if prev is None or len(prev) == 0:
            return None, 0.0
        prev_l = prev.tolist()
        prev2_l = self._prev2.tolist() if self._prev2 is not None else []
        if not prev2_l:
            return prev.copy(), 1.5 * self._diam + 12.0
        gate = 4 * self._diam + 40.0
        pred = []
        step_max = 0.0
        for x, y in prev_l:
            best, bx, by = math.inf, 0.0, 0.0
            for x2, y2 in prev2_l:
                dx, dy = x - x2, y - y2
                d = math.sqrt(dx * dx + dy * dy)
                if d < best:
                    best, bx, by = d, dx, dy
            if not best < gate:
                bx = by = 0.0
            # Centre between "stays" and "moves on": right whether or not the
            # nearest-neighbour velocity belongs to this marker.
            pred.append((x + 0.5 * bx, y + 0.5 * by))
            step_max = max(step_max, math.sqrt(bx * bx + by * by))
        return np.array(pred), 1.5 * self._diam + 12.0 + 0.5 * step_max

    def _set_aside(
        self, xy: FloatArray, diam: FloatArray, q: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """Drop the blobs the detector marked as not whole markers (negative quality),
        unless they moved by more than ``SET_ASIDE_MAX_STEP`` diameters since the last
        frame: a motion streak is not a disc either, and its fit residual says nothing
        about a hidden part.  Partly hidden and merged markers are slow: the fingertips
        touch and turn at closures.  Returns the kept ``xy, diam, quality`` and the
        positions and diameters set aside."""
        xy, diam, q = np.asarray(xy), np.asarray(diam), np.asarray(q)
        prev = self._prev if self._prev is not None else np.zeros((0, 2))
        drop = q < 0
        for i in np.flatnonzero(drop).tolist():
            step = float(np.min(np.hypot(*(prev - xy[i]).T))) if len(prev) else math.inf
            drop[i] = step <= SET_ASIDE_MAX_STEP * float(diam[i])
        if np.any(drop):
            self.n_set_aside += 1
        return xy[~drop], diam[~drop], np.abs(q[~drop]), xy[drop], diam[drop]

    def _keep_patches(
        self,
        image: NDArray[np.uint8],
        frame: int,
        xy: FloatArray,
        diam: FloatArray,
        aside: FloatArray,
        aside_diam: FloatArray,
    ) -> None:
        """Keep the pixels around the set-aside blobs and the touching detections (closer
        than their mean diameter + ``TOUCHING_GAP_PX``): groups of them, each with a margin
        of a diameter + ``PATCH_MARGIN_PX``. A blob's diameter is the width of its
        half-maximum region, a marker's also where two merged along one direction."""
        if not len(aside) and not _blobs.any_touching(
            np.ascontiguousarray(xy, dtype=np.float64),
            np.ascontiguousarray(diam, dtype=np.float64),
            TOUCHING_GAP_PX,
        ):
            return  # the common case, checked without the interpreter's loop
        pts = xy.tolist()
        d = diam.tolist()
        n = len(pts)
        group = list(range(n + len(aside)))  # union-find over detections, then set-aside blobs
        pts_all = pts + aside.tolist()
        d_all = d + aside_diam.tolist()

        def root(i: int) -> int:
            while group[i] != i:
                i = group[i]
            return i

        touching = False
        for i in range(len(pts_all)):
            xi, yi = pts_all[i]
            for j in range(i + 1, len(pts_all)):
                dx, dy = pts_all[j][0] - xi, pts_all[j][1] - yi
                lim = 0.5 * (d_all[i] + d_all[j]) + TOUCHING_GAP_PX
                if dx < lim and -dx < lim and dx * dx + dy * dy < lim * lim:
                    group[root(j)] = root(i)
                    touching = True
        if not touching and not len(aside):
            return
        members: dict[int, list[int]] = {}
        for i in range(len(pts_all)):
            members.setdefault(root(i), []).append(i)
        h, w = image.shape
        kept = []
        for idx in members.values():
            if len(idx) < 2 and idx[0] < n:
                continue  # a whole marker alone
            p = np.array([pts_all[i] for i in idx])
            d_group = max(d_all[i] for i in idx)
            margin = math.ceil(d_group) + PATCH_MARGIN_PX
            x0 = max(0, math.floor(float(p[:, 0].min())) - margin)
            y0 = max(0, math.floor(float(p[:, 1].min())) - margin)
            x1 = min(w, math.ceil(float(p[:, 0].max())) + margin + 1)
            y1 = min(h, math.ceil(float(p[:, 1].max())) + margin + 1)
            if x1 - x0 < 5 or y1 - y0 < 5:
                continue
            kept.append(
                ImagePatch(
                    x0,
                    y0,
                    image[y0:y1, x0:x1].copy(),
                    p,
                    np.array([i for i in idx if i < n], dtype=np.intp),
                    float(d_group),
                )
            )
        if kept:
            self.patches[frame] = kept

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
        aside = np.zeros((0, 2))
        aside_diam = np.zeros(0)
        if len(q) and min(q) < 0:
            xy, diam, q, aside, aside_diam = self._set_aside(xy, diam, q)
        if len(xy) > MAX_DETECTIONS_PER_FRAME:
            keep = np.argsort(-q, kind="stable")[:MAX_DETECTIONS_PER_FRAME]
            xy, diam = xy[keep], diam[keep]
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if len(diam):
            self._diam = 0.9 * self._diam + 0.1 * _median(diam)
        if len(aside) or len(xy) > 1:
            self._keep_patches(
                image, frame, xy, np.asarray(diam, dtype=np.float64), aside, aside_diam
            )
        self.frames.append(xy)
        # set-aside blobs stay in the search windows and in the motion check
        seen = np.concatenate((xy, aside)) if len(aside) else xy
        self._prev2, self._prev = self._prev, seen

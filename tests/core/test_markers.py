"""Tests of core.markers on rendered ground truth.

The images are rendered here (not by the simulator): supersampled anti-aliased
discs at known sub-pixel centres, optionally streaked (linear motion,
symmetric about the centre) and Gaussian-blurred, with seeded noise and, for
compression, a real mp4v encode/decode through cv2.VideoWriter/VideoCapture.
``bench/bench_markers.py`` reuses :func:`render_discs` and :func:`mp4v_roundtrip`.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from core.markers import (
    CENTRE_METHODS,
    MarkerDetections,
    MarkerParams,
    detect_markers,
    estimate_background,
    params_for,
)

# ----------------------------------------------------------------- ground truth


def render_discs(
    size_wh: tuple[int, int],
    centres_xy_px: np.ndarray,
    diameters_px: np.ndarray | float,
    *,
    peak: np.ndarray | float = 200.0,
    background: float = 12.0,
    blur_sigma_px: float = 0.0,
    streak_xy_px: np.ndarray | tuple[float, float] = (0.0, 0.0),
    noise_sigma: float = 0.0,
    seed: int = 0,
    supersample: int = 8,
) -> np.ndarray:
    """A uint8 (H, W) image of bright discs on a dark background.

    Parameters
    ----------
    size_wh : (width, height) in px.
    centres_xy_px : (N, 2) true centres, OpenCV (x, y), origin at the centre of
        the top-left pixel.  For a streak, the centre of the motion segment.
    diameters_px : (N,) or scalar disc diameters (px).
    peak : (N,) or scalar brightness above the background (gray levels).
    blur_sigma_px : Gaussian blur (defocus) sigma (px), applied after pixel
        integration.
    streak_xy_px : (N, 2) or (2,) motion during the exposure (px), centred on
        the centre: the disc sweeps from ``c - s/2`` to ``c + s/2``.
    noise_sigma : sigma of additive Gaussian noise (gray levels), seeded.
    """
    width, height = size_wh
    centres = np.atleast_2d(np.asarray(centres_xy_px, dtype=np.float64))
    n = centres.shape[0]
    diam = np.broadcast_to(np.asarray(diameters_px, dtype=np.float64), (n,))
    peaks = np.broadcast_to(np.asarray(peak, dtype=np.float64), (n,))
    streaks = np.broadcast_to(np.asarray(streak_xy_px, dtype=np.float64), (n, 2))
    canvas = np.zeros((height, width), dtype=np.float64)
    ss = supersample
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    for (cx, cy), d, a, (sx, sy) in zip(centres, diam, peaks, streaks, strict=True):
        r = 0.5 * d
        reach = r + 0.5 * math.hypot(sx, sy) + 4 * blur_sigma_px + 3
        x0, x1 = max(0, math.floor(cx - reach)), min(width, math.ceil(cx + reach) + 1)
        y0, y1 = max(0, math.floor(cy - reach)), min(height, math.ceil(cy + reach) + 1)
        xs = (np.arange(x0, x1)[:, None] + offs[None, :]).ravel()  # sub-sample x
        ys = (np.arange(y0, y1)[:, None] + offs[None, :]).ravel()
        n_steps = 1 if sx == 0 and sy == 0 else max(2, math.ceil(2 * math.hypot(sx, sy)))
        cover = np.zeros((ys.size, xs.size))
        for t in (np.arange(n_steps) + 0.5) / n_steps - 0.5:
            px, py = cx + t * sx, cy + t * sy
            cover += ((xs[None, :] - px) ** 2 + (ys[:, None] - py) ** 2) <= r * r
        cover /= n_steps
        pix = cover.reshape(y1 - y0, ss, x1 - x0, ss).mean(axis=(1, 3))
        canvas[y0:y1, x0:x1] += a * pix
    if blur_sigma_px > 0:
        canvas = cv2.GaussianBlur(canvas, (0, 0), blur_sigma_px)
    canvas += background
    if noise_sigma > 0:
        canvas += np.random.default_rng(seed).normal(0.0, noise_sigma, canvas.shape)
    return np.clip(np.rint(canvas), 0, 255).astype(np.uint8)


def mp4v_roundtrip(frames: list[np.ndarray], *, fps: float = 100.0) -> list[np.ndarray]:
    """Encode gray frames with cv2.VideoWriter (mp4v) and decode them back to gray."""
    height, width = frames[0].shape
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "clip.mp4")
        writer = cv2.VideoWriter(path, cv2.VideoWriter.fourcc(*"mp4v"), fps, (width, height))
        if not writer.isOpened():
            raise RuntimeError("cv2.VideoWriter cannot write mp4v here")
        for f in frames:
            writer.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
        writer.release()
        cap = cv2.VideoCapture(path)
        out = []
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            out.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
        cap.release()
    if len(out) != len(frames):
        raise RuntimeError(f"mp4v round trip returned {len(out)} of {len(frames)} frames")
    return out


def random_centres(rng: np.random.Generator, n: int, size_wh: tuple[int, int]) -> np.ndarray:
    """``n`` sub-pixel centres on a jittered grid, well apart and inside the image."""
    w, h = size_wh
    cols = math.ceil(math.sqrt(n * w / h))
    rows = math.ceil(n / cols)
    gx, gy = np.meshgrid((np.arange(cols) + 0.5) * w / cols, (np.arange(rows) + 0.5) * h / rows)
    grid = np.column_stack((gx.ravel(), gy.ravel()))[:n]
    return grid + rng.uniform(-3, 3, grid.shape)


def match(found: MarkerDetections, truth_xy: np.ndarray, tol_px: float = 3.0) -> np.ndarray:
    """(N_truth, 2) error found - truth of the nearest detection (NaN if none within tol)."""
    err = np.full(truth_xy.shape, np.nan)
    if len(found) == 0:
        return err
    d = np.linalg.norm(found.xy_px[None, :, :] - truth_xy[:, None, :], axis=2)
    j = d.argmin(axis=1)
    ok = d[np.arange(len(truth_xy)), j] < tol_px
    err[ok] = found.xy_px[j[ok]] - truth_xy[ok]
    return err


SIZE = (320, 256)  # (width, height) px; small images keep the tests fast


# ------------------------------------------------------------------- API checks


def test_result_shapes_and_dtypes() -> None:
    truth = np.array([[60.3, 50.7], [200.25, 180.5]])
    img = render_discs(SIZE, truth, 12.0)
    det = detect_markers(img)
    assert len(det) == 2
    assert det.xy_px.shape == (2, 2) and det.xy_px.dtype == np.float64
    names = ("diameter_px", "peak", "roundness", "background", "area_px", "fill", "quality",
             "flatness")  # fmt: skip
    for name in names:
        arr = getattr(det, name)
        assert arr.shape == (2,) and arr.dtype == np.float64, name
    assert det.shape_cov_px2.shape == (2, 2, 2)
    np.testing.assert_allclose(np.sort(det.diameter_px), [12, 12], atol=1.0)  # px
    np.testing.assert_allclose(det.peak, 200, atol=5)  # gray levels
    np.testing.assert_allclose(det.background, 12, atol=1)  # gray levels
    assert np.all(det.roundness > 0.9) and np.all(det.quality > 0.8)


def test_empty_image_gives_empty_detections() -> None:
    det = detect_markers(np.full((64, 80), 10, np.uint8))
    assert len(det) == 0 and det.xy_px.shape == (0, 2) and det.shape_cov_px2.shape == (0, 2, 2)
    noisy = render_discs(SIZE, np.zeros((0, 2)), 10.0, noise_sigma=3.0, seed=4)
    assert len(detect_markers(noisy)) == 0


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((32, 32, 3), np.uint8),  # colour
        np.zeros((32, 32), np.float32),  # float
        np.zeros((32, 32), np.uint16),
        np.zeros(32, np.uint8),
        [[0, 1], [2, 3]],
    ],
)
def test_rejects_non_gray_uint8_images(bad: object) -> None:
    with pytest.raises(ValueError, match="uint8"):
        detect_markers(bad)  # type: ignore[arg-type]


@pytest.mark.parametrize("pts", [np.zeros((3,)), np.zeros((2, 3)), np.zeros((1, 2, 2))])
def test_rejects_wrong_search_shape(pts: np.ndarray) -> None:
    with pytest.raises(ValueError, match=r"\(K, 2\)"):
        detect_markers(np.zeros((32, 32), np.uint8), search_xy_px=pts)


def test_rejects_bad_radius_and_params() -> None:
    img = np.zeros((32, 32), np.uint8)
    with pytest.raises(ValueError, match="search_radius_px"):
        detect_markers(img, search_xy_px=np.zeros((1, 2)), search_radius_px=0.0)
    with pytest.raises(ValueError, match="diameter_px_min"):
        MarkerParams(diameter_px_min=10, diameter_px_max=5)
    with pytest.raises(ValueError, match="centre_method"):
        MarkerParams(centre_method="magic")
    with pytest.raises(ValueError):
        params_for(6.0, 1500.0, (700.0, 300.0))


def test_params_for_brackets_the_projected_size() -> None:
    p = params_for(6.0, 1500.0, (400.0, 700.0))  # 6 mm sphere: 12.9 .. 22.5 px
    assert p.diameter_px_min < 1500 * 6 / 700 < 1500 * 6 / 400 < p.diameter_px_max
    assert params_for(6.0, 1500.0, (400.0, 700.0), min_contrast=40).min_contrast == 40


# ------------------------------------------------------------------ conventions


def test_pixel_centre_convention_x_is_column() -> None:
    """A disc centred on pixel (row 20, column 10) is reported as x=10, y=20."""
    img = np.full((40, 60), 10, np.uint8)
    cv2.circle(img, (10, 20), 5, 220, -1)  # OpenCV draws at (x, y) = (col, row)
    assert img[20, 10] == 220 and img[10, 20] == 10
    det = detect_markers(img)
    assert len(det) == 1
    np.testing.assert_allclose(det.xy_px[0], [10.0, 20.0], atol=1e-6)  # px, symmetric disc


def test_transposed_image_swaps_x_and_y() -> None:
    truth = np.array([[70.37, 40.81], [150.62, 201.13]])
    img = render_discs(SIZE, truth, 11.0, blur_sigma_px=0.7)
    det = detect_markers(img)
    det_t = detect_markers(np.ascontiguousarray(img.T))
    a = det.xy_px[np.lexsort(det.xy_px.T[::-1])]
    b = det_t.xy_px[:, ::-1][np.lexsort(det_t.xy_px[:, ::-1].T[::-1])]
    np.testing.assert_allclose(a, b, atol=1e-3)  # px (window placement follows raster order)
    np.testing.assert_allclose(a, truth[np.lexsort(truth.T[::-1])], atol=0.05)  # px


# ------------------------------------------------------------------ accuracy


@pytest.fixture(scope="module")
def clean_field() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    truth = random_centres(rng, 20, SIZE)
    diam = rng.uniform(8, 20, len(truth))
    return render_discs(SIZE, truth, diam, blur_sigma_px=0.6), truth


@pytest.mark.parametrize("method", CENTRE_METHODS)
def test_noise_free_centres_are_exact(method: str, clean_field: tuple) -> None:
    img, truth = clean_field
    det = detect_markers(img, params=MarkerParams(centre_method=method))
    err = match(det, truth)
    assert len(det) == len(truth) and np.isfinite(err).all()
    assert np.abs(err).max() <= 0.02, method  # px, noise-free 8-20 px discs


@pytest.mark.parametrize("method", CENTRE_METHODS)
def test_noisy_centres_within_tolerance(method: str) -> None:
    rng = np.random.default_rng(2)
    truth = random_centres(rng, 20, SIZE)
    img = render_discs(SIZE, truth, rng.uniform(8, 20, 20), peak=150, blur_sigma_px=0.8,
                       noise_sigma=4.0, seed=3)  # fmt: skip
    err = match(detect_markers(img, params=MarkerParams(centre_method=method)), truth)
    assert np.isfinite(err).all()
    rms = math.sqrt(np.mean(np.sum(err**2, axis=1)))
    assert rms <= 0.08, (method, rms)  # px, noise sigma 4 gray levels on a 150 peak


@pytest.mark.parametrize(
    ("diameter_px", "peak"), [(3.0, 200), (5.0, 200), (34.0, 200), (12.0, 500)]
)
def test_small_large_and_saturated_markers(diameter_px: float, peak: float) -> None:
    """From the 3 px lower limit to 34 px, and a disc saturated to a plateau (peak 500
    before clipping to 255)."""
    rng = np.random.default_rng(int(diameter_px))
    truth = random_centres(rng, 6 if diameter_px > 20 else 12, SIZE)
    img = render_discs(SIZE, truth, diameter_px, peak=peak, blur_sigma_px=0.6,
                       noise_sigma=1.0, seed=2)  # fmt: skip
    det = detect_markers(img)
    err = match(det, truth)
    assert len(det) == len(truth) and np.isfinite(err).all()
    assert np.abs(err).max() <= 0.05  # px, noise sigma 1 (3 px discs have few edge pixels)
    np.testing.assert_allclose(det.diameter_px, diameter_px, atol=0.15 * diameter_px + 1.0)  # px


def test_motion_blur_centre_is_the_mid_exposure_position() -> None:
    rng = np.random.default_rng(5)
    truth = random_centres(rng, 12, SIZE)
    streaks = rng.uniform(-14, 14, (12, 2))  # up to ~20 px of motion in one exposure
    img = render_discs(SIZE, truth, 12.0, streak_xy_px=streaks, blur_sigma_px=0.6,
                       noise_sigma=2.0, seed=6)  # fmt: skip
    det = detect_markers(img)
    err = match(det, truth)
    assert np.isfinite(err).all()
    assert np.abs(err).max() <= 0.1  # px, streaks up to 20 px, noise sigma 2
    # px: the width (a streak's half-maximum width is 0.87 d: its cross profile is the
    # semicircular chord of the disc), never the length
    assert np.all((det.diameter_px > 9.5) & (det.diameter_px < 13.5))


@pytest.fixture(scope="module")
def compressed_frames() -> tuple[list[np.ndarray], np.ndarray]:
    rng = np.random.default_rng(7)
    truth = [random_centres(rng, 16, (640, 512)) for _ in range(3)]
    frames = [
        render_discs((640, 512), t, 13.0, peak=190, blur_sigma_px=0.8, noise_sigma=2.0, seed=i)
        for i, t in enumerate(truth)
    ]
    return mp4v_roundtrip(frames), np.array(truth)


def test_mp4v_compressed_centres_within_tolerance(compressed_frames: tuple) -> None:
    frames, truth = compressed_frames
    errs = np.concatenate([match(detect_markers(f), t) for f, t in zip(frames, truth, strict=True)])
    assert np.isfinite(errs).all()  # every marker found after compression
    rms = math.sqrt(np.mean(np.sum(errs**2, axis=1)))
    assert rms <= 0.15, rms  # px, mp4v at OpenCV's default quality, noise sigma 2


def test_static_background_subtraction_removes_texture_bias() -> None:
    """A fixed textured background biases streaked markers along their motion;
    subtracting a marker-free background image removes that bias."""
    rng = np.random.default_rng(13)
    fine = cv2.GaussianBlur(rng.standard_normal((SIZE[1], SIZE[0])), (0, 0), 1.2)
    texture = 14.0 + 8.0 * fine / fine.std()  # gray levels, std 8, 1.2 px grain
    truth = random_centres(rng, 16, SIZE)
    streaks = rng.uniform(-8, 8, (16, 2))  # px of motion during the exposure
    markers = render_discs(SIZE, truth, 11.0, peak=200, streak_xy_px=streaks,
                           blur_sigma_px=0.6, background=0.0).astype(np.float64)  # fmt: skip
    img = np.clip(np.rint(markers + texture), 0, 255).astype(np.uint8)
    bg_img = np.clip(np.rint(texture), 0, 255).astype(np.uint8)
    err_raw = match(detect_markers(img), truth)
    err_sub = match(detect_markers(img, background=bg_img), truth)
    assert np.isfinite(err_raw).all() and np.isfinite(err_sub).all()
    rms_raw = math.sqrt(np.mean(np.sum(err_raw**2, axis=1)))
    rms_sub = math.sqrt(np.mean(np.sum(err_sub**2, axis=1)))
    assert rms_sub <= 0.02  # px, only the rounding of the two images is left
    assert rms_sub < 0.5 * rms_raw, (rms_raw, rms_sub)
    # a background image that holds the markers themselves (they rested there) is
    # ignored around them instead of erasing them
    same = detect_markers(img, background=img)
    np.testing.assert_allclose(same.xy_px, detect_markers(img).xy_px, atol=1e-12)  # px
    with pytest.raises(ValueError, match="background"):
        detect_markers(img, background=bg_img[:-1])
    with pytest.raises(ValueError, match="background"):
        detect_markers(img, background=bg_img.astype(np.float32))


def test_estimate_background_from_moving_markers() -> None:
    rng = np.random.default_rng(14)
    fine = cv2.GaussianBlur(rng.standard_normal((SIZE[1], SIZE[0])), (0, 0), 1.2)
    texture = 14.0 + 8.0 * fine / fine.std()
    frames = []
    for i in range(9):  # markers at new places in every frame, fresh noise
        centres = rng.uniform((10, 10), (SIZE[0] - 10, SIZE[1] - 10), (10, 2))
        markers = render_discs(SIZE, centres, 12.0, background=0.0, noise_sigma=2.0,
                               seed=i).astype(np.float64)  # fmt: skip
        frames.append(np.clip(np.rint(markers + texture), 0, 255).astype(np.uint8))
    bg = estimate_background(frames)
    assert bg.shape == frames[0].shape and bg.dtype == np.uint8
    diff = bg.astype(np.float64) - np.clip(texture, 0, 255)
    assert np.abs(diff).max() < 12  # gray levels: no marker left in it
    assert abs(diff.mean()) < 0.5 and diff.std() < 1.5  # gray levels: median of 9 noisy frames
    low = estimate_background(frames, quantile=0.0)
    assert np.all(low <= bg)
    with pytest.raises(ValueError, match="empty"):
        estimate_background([])
    with pytest.raises(ValueError, match="uint8"):
        estimate_background([frames[0], frames[1][:-1]])
    with pytest.raises(ValueError, match="quantile"):
        estimate_background(frames, quantile=1.5)


# ------------------------------------------------------------------ distractors


def test_elongated_streak_and_huge_glare_are_rejected() -> None:
    img = render_discs(SIZE, np.array([[80.4, 60.6]]), 12.0, blur_sigma_px=0.6)
    cv2.line(img, (150, 40), (280, 70), 230, 3)  # thin line-like glint, 130 px long
    cv2.circle(img, (220, 190), 40, 255, -1)  # saturated glare blob, 80 px wide
    cv2.circle(img, (60, 200), 1, 200, -1)  # 3 px speck, below a 5 px lower size limit
    det = detect_markers(img, params=MarkerParams(diameter_px_min=5.0))
    assert len(det) == 1
    np.testing.assert_allclose(det.xy_px[0], [80.4, 60.6], atol=0.02)  # px
    # the same speck is a (small) marker for the default 3 px limit
    assert len(detect_markers(img)) == 2


def test_dim_and_ragged_blobs_are_rejected() -> None:
    img = render_discs(SIZE, np.array([[80.4, 60.6], [200.0, 60.0]]), 12.0, peak=[200, 12])
    pts = np.array([[150, 150], [170, 150], [150, 170], [190, 190], [150, 190]], np.int32)
    cv2.polylines(img, [pts], False, 200, 3)  # ragged hook-shaped glint
    det = detect_markers(img)
    assert len(det) == 1
    np.testing.assert_allclose(det.xy_px[0], [80.4, 60.6], atol=0.02)  # px


def test_gaussian_glint_scores_lower_than_a_disc() -> None:
    """Sphere images are flat-topped; a Gaussian glint of the same width is kept
    (the tracker decides) but with a lower flatness and quality."""
    img = render_discs(SIZE, np.array([[80.4, 60.6]]), 10.0, blur_sigma_px=0.6, noise_sigma=1)
    yy, xx = np.mgrid[0 : SIZE[1], 0 : SIZE[0]]
    sigma = 10.0 / 2.355  # px: same half-maximum width as the disc
    glint = 200 * np.exp(-((xx - 200.3) ** 2 + (yy - 150.8) ** 2) / (2 * sigma**2))
    img = np.clip(img + glint, 0, 255).astype(np.uint8)
    det = detect_markers(img)
    assert len(det) == 2
    disc, gauss = np.argmin(det.xy_px[:, 0]), np.argmax(det.xy_px[:, 0])
    assert det.flatness[disc] > 0.75 and det.flatness[gauss] < 0.5  # ln(4/3)/ln(2) = 0.42
    assert det.quality[gauss] < 0.8 * det.quality[disc]
    np.testing.assert_allclose(det.xy_px[gauss], [200.3, 150.8], atol=0.02)  # px


def test_non_contiguous_image_is_accepted() -> None:
    truth = np.array([[40.3, 30.6]])
    img = render_discs((80, 60), truth, 10.0)
    wide = np.zeros((60, 160), np.uint8)
    wide[:, ::2] = img
    det = detect_markers(wide[:, ::2])  # a strided view
    np.testing.assert_allclose(det.xy_px, truth, atol=0.02)  # px


def test_two_markers_close_together_are_both_found() -> None:
    truth = np.array([[100.3, 100.6], [114.9, 103.2]])  # 12 px discs, ~2.8 px gap
    img = render_discs(SIZE, truth, 12.0, blur_sigma_px=0.6, noise_sigma=1.0, seed=8)
    det = detect_markers(img)
    err = match(det, truth)
    assert len(det) == 2 and np.isfinite(err).all()
    assert np.abs(err).max() <= 0.1  # px, the neighbour's halo is masked out
    # overlapping search windows (one per predicted marker) give each marker once
    win = detect_markers(img, search_xy_px=truth + 1.0, search_radius_px=10.0)
    assert len(win) == 2
    np.testing.assert_allclose(np.sort(win.xy_px, axis=0), np.sort(det.xy_px, axis=0), atol=1e-9)


def test_markers_touching_the_border() -> None:
    # fully inside but 1 px from the border: found and exact; cut by the border: rejected
    truth_in = np.array([[6.7, 128.2], [160.4, 249.1]])
    truth_cut = np.array([[316.0, 40.0], [100.0, 1.5]])
    img = render_discs(SIZE, np.vstack((truth_in, truth_cut)), 10.0)
    det = detect_markers(img)
    err = match(det, truth_in)
    assert len(det) == 2 and np.abs(err).max() <= 0.02  # px
    det_all = detect_markers(img, params=MarkerParams(reject_border=False))
    assert len(det_all) == 4  # the cut ones are reported when asked for (biased centres)


# ------------------------------------------------------------------ windowed search


def test_windowed_search_matches_full_frame() -> None:
    rng = np.random.default_rng(9)
    truth = random_centres(rng, 12, SIZE)
    img = render_discs(SIZE, truth, rng.uniform(8, 18, 12), blur_sigma_px=0.7,
                       noise_sigma=2.0, seed=10)  # fmt: skip
    full = detect_markers(img)
    predicted = truth[:5] + rng.uniform(-6, 6, (5, 2))
    win = detect_markers(img, search_xy_px=predicted, search_radius_px=12.0)
    assert len(win) == 5
    for xy in win.xy_px:
        d = np.linalg.norm(full.xy_px - xy, axis=1)
        assert d.min() <= 1e-9  # px, same measurement code on the same pixels
    # a prediction far from any marker finds nothing; NaN rows are skipped
    empty = detect_markers(img, search_xy_px=np.array([[5.0, 5.0], [np.nan, np.nan]]),
                           search_radius_px=4.0)  # fmt: skip
    assert len(empty) == 0


def test_windowed_search_respects_the_radius() -> None:
    truth = np.array([[100.0, 100.0], [130.0, 100.0]])
    img = render_discs(SIZE, truth, 10.0)
    det = detect_markers(img, search_xy_px=np.array([[104.0, 100.0]]), search_radius_px=10.0)
    assert len(det) == 1 and abs(det.xy_px[0, 0] - 100.0) < 0.02  # px


# ------------------------------------------------------------------ simulator output


def test_simulator_rendered_markers() -> None:
    """Markers drawn by core.simulation.render (textured, vignetted background,
    limb darkening, shot and read noise, motion over the exposure) are found at
    the projections of the sphere centres."""
    render = pytest.importorskip("core.simulation.render")
    rig_mod = pytest.importorskip("core.simulation.rig")
    from core.camera import ImageSize

    size = ImageSize(640, 512)
    cam = rig_mod.default_rig(image_size=size).left
    rng = np.random.default_rng(12)
    centres_mm = np.array([[-30.0, -20.0, 480.0], [25.0, 15.0, 520.0], [0.0, 40.0, 450.0]])
    motion_mm = np.linspace(-0.5, 0.5, 9)[:, None, None] * np.array([[[3.0, -2.0, 0.0]]])
    layer = render.SphereLayer(centres_mm=centres_mm[None] + motion_mm, radius_mm=2.5, peak=230.0)
    canvas = render.make_background(size, rng=rng)
    render.draw_spheres(canvas, cam, layer, psf_sigma_px=0.5, shot_noise=(rng, 0.025))
    render.SensorNoise(size, sigma=2.0, rng=rng).add_to(canvas)
    img = render.to_uint8(canvas)
    truth = cam.project(centres_mm)  # mid-exposure position (the motion is symmetric)
    focal_px = float(cam.K[0, 0])
    det = detect_markers(img, params=params_for(5.0, focal_px, (400.0, 600.0)))
    err = match(det, truth)
    assert len(det) == 3 and np.isfinite(err).all()
    assert (
        np.abs(err).max() <= 0.08
    )  # px, read noise sigma 2 + shot noise (gain 0.025), 3 mm motion


# ------------------------------------------------- lean measurement == reference


def _centroid_reference(sub: np.ndarray, support: np.ndarray, peak: float) -> tuple[float, float]:
    """The centroid as first written: numpy sums of ``max(sub - 0.1 peak, 0)`` on the support."""
    wgt = np.where(support, np.maximum(sub - 0.1 * peak, 0.0), 0.0)
    s = wgt.sum()
    ys, xs = np.mgrid[0 : sub.shape[0], 0 : sub.shape[1]]
    return float((wgt * xs).sum() / s), float((wgt * ys).sum() / s)


def test_centroid_by_moments_equals_the_numpy_sums() -> None:
    from core.markers import _centroid

    rng = np.random.default_rng(21)
    for i in range(20):
        centre = rng.uniform(8.0, 24.0, 2)
        img = render_discs((33, 29), centre[None], rng.uniform(4.0, 14.0), blur_sigma_px=0.7,
                           noise_sigma=2.0, seed=i).astype(np.float64) - 12.0  # fmt: skip
        support = rng.random(img.shape) < 0.9
        got = _centroid(img, support, float(img.max()))
        np.testing.assert_allclose(got, _centroid_reference(img, support, float(img.max())),
                                   rtol=0, atol=1e-9)  # px, float64 summation order only  # fmt: skip


def test_compiled_search_equals_the_opencv_formulation(compressed_frames: tuple) -> None:
    """The compiled search (core/_blobs.pyx) gives, field by field, the detections of
    the original OpenCV/numpy formulation (tests/core/markers_reference.py): on
    compressed frames, touching and overlapping neighbours (the split by distance),
    streaks, glare, markers at the border, full-frame and windowed searches."""
    from markers_reference import detect_reference

    rng = np.random.default_rng(31)
    cases: list[tuple[np.ndarray, dict]] = [(img, {}) for img in compressed_frames[0]]
    for i in range(12):
        c = random_centres(rng, 8, SIZE)
        diam = rng.uniform(4.0, 20.0, len(c))
        # close pairs, blurred: neighbours whose skirts meet are split by distance
        # (centre distance: the mean radius times 1.2-2, plus up to 6 px)
        offset = rng.normal(size=(4, 2))
        d2 = rng.uniform(4.0, 12.0, 4)
        dist = 0.5 * (diam[:4] + d2) * rng.uniform(0.6, 1.0, 4) + rng.uniform(0.0, 6.0, 4)
        offset *= (dist / np.hypot(*offset.T))[:, None]
        c = np.concatenate([c, c[:4] + offset])
        diam = np.concatenate([diam, d2])
        img = render_discs(SIZE, c, diam, peak=rng.uniform(40, 255, len(c)),
                           blur_sigma_px=rng.uniform(0.6, 2.2), noise_sigma=1.5, seed=i,
                           streak_xy_px=rng.uniform(-6.0, 6.0, (len(c), 2)) * (i % 3 == 0))  # fmt: skip
        cases.append((img, {}))
        cases.append((img, {"search_xy_px": c[::2] + rng.normal(0.0, 3.0, (len(c[::2]), 2))}))
    edge = render_discs(SIZE, np.array([[1.0, 100.0], [318.6, 30.0], [150.0, 0.5], [80.0, 80.0]]),
                        np.array([10.0, 9.0, 12.0, 60.0]), seed=3)  # fmt: skip
    cases.append((edge, {}))
    n_found = 0
    centroid = MarkerParams(centre_method="centroid")  # what the reference computes
    for img, kw in cases:
        got = detect_markers(img, params=centroid, **kw)
        want = detect_reference(img, params=centroid, **kw)
        assert len(got) == len(want)
        n_found += len(got)
        np.testing.assert_allclose(got.xy_px, want.xy_px, rtol=0, atol=1e-9)  # px
        for name in ("diameter_px", "peak", "roundness", "background", "area_px", "fill",
                     "shape_cov_px2", "quality", "flatness"):  # fmt: skip
            np.testing.assert_allclose(
                getattr(got, name), getattr(want, name), rtol=1e-9, atol=1e-9
            )
    assert n_found >= 3 * 14 + 12 * 10  # the markers are found at all

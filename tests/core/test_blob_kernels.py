"""The compiled detector's image-wide helpers against plain numpy formulations.

``core/_blobs.pyx`` computes them with loops written for speed (32-bit words for the
pooled cells, four interleaved histograms, restrict-qualified C for the 3x3 mean);
these tests hold them to the obvious formulation on images that hit the edge cases:
partial cells at the right and bottom edges, thresholds at the ends of the range,
runs of equal gray levels, widths that are not multiples of the word size.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from markers_reference import _background_and_noise

from core import _blobs
from core.markers import TOUCHING_GAP_PX


def _pooled_reference(image: np.ndarray, t: int, pool: int) -> np.ndarray:
    h, w = image.shape
    hp, wp = -(-h // pool), -(-w // pool)
    padded = np.zeros((hp * pool, wp * pool), dtype=np.int32) - 1
    padded[:h, :w] = image
    cells = padded.reshape(hp, pool, wp, pool).max(axis=(1, 3))
    return (cells > t).astype(np.uint8)


@pytest.mark.parametrize("shape", [(1024, 1280), (37, 53), (5, 3), (64, 4), (33, 1001)])
@pytest.mark.parametrize("pool", [1, 3, 4, 5])
def test_pool_mask_matches_max_pooling(shape: tuple[int, int], pool: int) -> None:
    rng = np.random.default_rng(shape[0] * 7 + pool)
    image = rng.integers(0, 60, size=shape, dtype=np.uint8)
    # a few bright pixels, some in the partial last row and column of cells
    for y, x in [(shape[0] - 1, shape[1] - 1), (0, 0), (shape[0] // 2, shape[1] - 1)]:
        image[y, x] = 200
    for t in (-5, 0, 30, 59, 60, 199, 200, 254, 255, 300):
        got = _blobs.pool_mask(image, t, pool)
        np.testing.assert_array_equal(got, _pooled_reference(image, t, pool), err_msg=f"t={t}")


@pytest.mark.parametrize("step", [1, 3, 8, 16])
def test_background_and_noise_matches_the_histogram_quantiles(step: int) -> None:
    rng = np.random.default_rng(step)
    for shape in [(1024, 1280), (17, 29), (3, 3), (100, 7)]:
        # dark, flat images (long runs of one level) and noisy ones
        for image in (
            np.full(shape, 12, dtype=np.uint8),
            rng.integers(0, 256, size=shape, dtype=np.uint8),
            np.clip(rng.normal(30, 4, size=shape), 0, 255).astype(np.uint8),
        ):
            assert _blobs.background_and_noise(image, step) == _background_and_noise(
                image[::step, ::step]
            )


def _touching_reference(xy: np.ndarray, diam: np.ndarray, gap: float) -> bool:
    """core.markers._CameraDetections._keep_patches' loop, as it was written in Python."""
    pts, d = xy.tolist(), diam.tolist()
    for i in range(len(pts)):
        xi, yi = pts[i]
        for j in range(i + 1, len(pts)):
            dx, dy = pts[j][0] - xi, pts[j][1] - yi
            lim = 0.5 * (d[i] + d[j]) + gap
            if dx < lim and -dx < lim and dx * dx + dy * dy < lim * lim:
                return True
    return False


def test_any_touching_is_the_python_test() -> None:
    rng = np.random.default_rng(5)
    seen = {True: 0, False: 0}
    for n in range(0, 9):
        for _ in range(300):
            xy = rng.uniform(0, 120, size=(n, 2))
            diam = rng.uniform(4, 20, size=n)
            want = _touching_reference(xy, diam, TOUCHING_GAP_PX)
            assert _blobs.any_touching(xy, diam, TOUCHING_GAP_PX) is want
            seen[want] += 1
    # exactly at the limit: not touching (strict inequalities)
    xy = np.array([[0.0, 0.0], [14.0, 0.0]])
    assert not _blobs.any_touching(xy, np.array([10.0, 10.0]), 4.0)
    assert _blobs.any_touching(xy, np.array([10.0, 10.0 + 2 * math.ulp(10.0)]), 4.0)
    assert seen[True] > 100 and seen[False] > 100  # both answers were exercised
    with pytest.raises(ValueError):
        _blobs.any_touching(xy, np.array([1.0]), 4.0)

"""Type stub of the compiled marker search (core/_blobs.pyx)."""

import numpy as np
from numpy.typing import NDArray

COLUMNS: tuple[str, ...]

def search(
    image: NDArray[np.uint8],
    regions: NDArray[np.int32],
    thr: float,
    diameter_px_min: float,
    diameter_px_max: float,
    min_contrast: float,
    max_elongation: float,
    min_fill: float,
    reject_border: bool,
    ring_radius_px: int,
    half_limit_px: int,
    max_seeds_per_region: int,
    want_support: bool,
) -> tuple[NDArray[np.float64], list[NDArray[np.uint8]] | None]: ...
def background_and_noise(image: NDArray[np.uint8], step: int) -> tuple[float, float]: ...
def pool_mask(image: NDArray[np.uint8], t: int, pool: int) -> NDArray[np.uint8]: ...
def merged_windows(
    pts: NDArray[np.float64], reach: float, H: int, W: int
) -> tuple[NDArray[np.int32], NDArray[np.int32]]: ...
def measure_regions(
    image: NDArray[np.uint8],
    regions: NDArray[np.int32],
    pts: NDArray[np.float64],
    point_region: NDArray[np.int32],
    r2: float,
    noise_step: int,
    min_contrast: float,
    diameter_px_min: float,
    diameter_px_max: float,
    max_elongation: float,
    min_fill: float,
    reject_border: bool,
    ring_radius_px: int,
    half_limit_px: int,
    max_seeds_per_region: int,
    refine: bool,
    max_iter: int,
    pad_px: float,
    min_roundness: float,
    max_hidden: float,
) -> tuple[NDArray[np.float64], float, float]: ...
def any_touching(xy: NDArray[np.float64], diam: NDArray[np.float64], gap: float) -> bool: ...
def select(
    rows: NDArray[np.float64],
    pts: NDArray[np.float64],
    point_region: NDArray[np.int32],
    r2: float,
) -> NDArray[np.intp]: ...

FIT_COLUMNS: tuple[str, ...]

def fit_discs(
    image: NDArray[np.uint8],
    seeds: NDArray[np.float64],
    others: NDArray[np.float64],
    max_iter: int,
    dark_level: float,
    edges: int = 0,
) -> NDArray[np.float64]: ...
def refine_rows(
    image: NDArray[np.uint8],
    rows: NDArray[np.float64],
    others: NDArray[np.float64],
    max_iter: int,
    dark_level: float,
    pad_px: float,
    min_roundness: float,
    noise_sigma: float,
    edges: int = 1,
    max_hidden: float = 1.0,
) -> None: ...

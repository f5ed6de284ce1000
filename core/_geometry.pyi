"""Type stub of the compiled loops of the serial part (core/_geometry.pyx)."""

import numpy as np
from numpy.typing import NDArray

def nearest_epipolar(
    line_r: NDArray[np.float64],
    norm_r: NDArray[np.float64],
    r_pts: NDArray[np.float64],
    norm_l: NDArray[np.float64],
    starts: NDArray[np.intp],
    counts: NDArray[np.intp],
    rows: NDArray[np.intp],
    f_right: float,
    f_left: float,
) -> NDArray[np.float64]: ...
def undistort(
    xy: NDArray[np.float64], dist: NDArray[np.float64], max_iter: int, tol: float
) -> NDArray[np.float64]: ...
def points_at_times(
    pts: NDArray[np.float64],
    starts: NDArray[np.intp],
    nxt: NDArray[np.intp],
    prv: NDArray[np.intp],
    frame_t: NDArray[np.float64],
    point_t: NDArray[np.float64],
    gap_after: NDArray[np.uint8],
    t: NDArray[np.float64],
    j_before: NDArray[np.intp],
    exact_tol_s: float,
) -> tuple[NDArray[np.float64], NDArray[np.intp]]: ...

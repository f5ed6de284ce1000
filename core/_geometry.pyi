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

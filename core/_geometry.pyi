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
def truncated_epipolar_costs(
    la: NDArray[np.float64],
    lb: NDArray[np.float64],
    lc: NDArray[np.float64],
    norm_r: NDArray[np.float64],
    r_pts: NDArray[np.float64],
    norm_l: NDArray[np.float64],
    starts: NDArray[np.intp],
    counts: NDArray[np.intp],
    rows: NDArray[np.intp],
    f_right: float,
    f_left: float,
    gate_px: float,
    gate_sq: float,
) -> NDArray[np.float64]: ...
def refine_system(
    cam_left: NDArray[np.float64],
    cam_right: NDArray[np.float64],
    lens_left: tuple[float, ...],
    lens_right: tuple[float, ...],
    obs: NDArray[np.float64],
    step_mm: NDArray[np.float64],
    lam: NDArray[np.float64],
    damped: NDArray[np.float64],
    jtr: NDArray[np.float64],
    cost: NDArray[np.float64],
) -> bool: ...
def refine_accept(
    cam_left: NDArray[np.float64],
    cam_right: NDArray[np.float64],
    lens_left: tuple[float, ...],
    lens_right: tuple[float, ...],
    obs: NDArray[np.float64],
    cost: NDArray[np.float64],
    x_new: NDArray[np.float64],
    delta: NDArray[np.float64],
    x: NDArray[np.float64],
    lam: NDArray[np.float64],
    tol_mm: float,
) -> bool | None: ...
def link_frames(
    pts: NDArray[np.float64],
    counts: NDArray[np.intp],
    nxt: NDArray[np.intp],
    max_step_px: float,
) -> None: ...

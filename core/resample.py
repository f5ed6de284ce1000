"""Trajectories at their real frame times, brought to an even time grid for the metrics.

The metrics (:mod:`core.aperture`, :mod:`core.taps`) filter and differentiate a
signal sampled at a constant rate. A free-running camera does not deliver one:
variable-frame-rate timestamps jitter, and a lost frame leaves two frames one
interval further apart than their numbers say (``core.timing``, ``core.clock``).
Read as ``frame / fps``, a lost frame in fast motion doubles the velocity
across it and every later time is one interval early; jitter adds velocity
noise.

:func:`uniform_trajectories` therefore samples the trajectories at ``t0 + k /
fps`` from their real frame times (a cubic spline through each stretch of
finite positions, per marker), so the metrics' frequencies, velocities and
times are those of the capture times. A sample between two frames that a lost
frame separates is filled in (``measured`` False), as the tracker's own
interpolations are; across more than ``max_gap_s`` nothing is invented (NaN).
Frames that are already evenly spaced (a lab rig, constant timestamps without
losses) are returned as they are, so their results do not change.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline

from core.timing import lost_after

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Frame times within this share of an interval of ``t0 + i / fps`` are evenly spaced.
EVEN_TOLERANCE = 1e-3


@dataclass(frozen=True)
class UniformTrajectories:
    """Trajectories at ``t0_s + k / fps``.

    Attributes
    ----------
    positions_mm : (K, M, 3) float64
        Positions at the grid's instants; NaN where nothing is known.
    measured : (K, M) bool
        True where both frames around the instant were measured and no frame
        was lost between them.
    t0_s : float
        Time of the first sample (the first frame's).
    fps : float
        The grid's rate (the nominal frame rate).
    resampled : bool
        False when the frames were evenly spaced and are returned as they are.
    """

    positions_mm: FloatArray
    measured: BoolArray
    t0_s: float
    fps: float
    resampled: bool


def uniform_trajectories(
    positions_mm: NDArray[np.floating],
    measured: NDArray[np.bool_],
    time_s: NDArray[np.floating] | None,
    fps: float,
    *,
    max_gap_s: float = 0.1,
) -> UniformTrajectories:
    """The trajectories at an even rate ``fps`` from their frames' real times.

    Parameters
    ----------
    positions_mm : (T, M, 3) float
        Per frame and marker; NaN where missing.
    measured : (T, M) bool
        False where a position was filled in or is missing.
    time_s : (T,) float or None
        Capture time of each frame (s), increasing; None means ``i / fps``.
    fps : float
        Nominal frame rate (Hz), the grid's rate.
    max_gap_s : float
        Frames further apart than this (lost frames) are not interpolated across.

    Raises
    ------
    ValueError
        On shapes that do not agree, or times that do not increase.
    """
    pos = np.asarray(positions_mm, dtype=np.float64)
    meas = np.asarray(measured, dtype=bool)
    if pos.ndim != 3 or pos.shape[2] != 3 or meas.shape != pos.shape[:2]:
        raise ValueError(
            f"positions (T, M, 3) and measured (T, M) expected, got {pos.shape}, {meas.shape}"
        )
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    n = pos.shape[0]
    if time_s is None:
        return UniformTrajectories(pos, meas, 0.0, float(fps), False)
    t = np.asarray(time_s, dtype=np.float64).reshape(-1)
    if t.shape != (n,):
        raise ValueError(f"time_s must have one time per frame ({n}), got {t.shape}")
    if n < 2:
        return UniformTrajectories(pos, meas, float(t[0]) if n else 0.0, float(fps), False)
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise ValueError("frame times must be finite and increase")
    t0 = float(t[0])
    rel = t - t0
    if np.max(np.abs(rel * fps - np.arange(n))) <= EVEN_TOLERANCE:
        return UniformTrajectories(pos, meas, t0, float(fps), False)

    grid = np.arange(int(np.floor(rel[-1] * fps + EVEN_TOLERANCE)) + 1) / fps
    k = len(grid)
    out = np.full((k, pos.shape[1], 3), np.nan)
    # The frame at or before each instant, and whether a frame was lost after it.
    left = np.clip(np.searchsorted(rel, grid, side="right") - 1, 0, n - 2)
    lost = lost_after(t, fps)[:-1] > 0  # room in the time line, not a long interval
    on_frame = np.abs(rel[left] - grid) * fps <= EVEN_TOLERANCE
    out_meas = np.zeros((k, pos.shape[1]), dtype=bool)
    for m in range(pos.shape[1]):
        finite = np.all(np.isfinite(pos[:, m]), axis=1)
        # Stretches of finite positions without a gap longer than max_gap_s inside.
        breaks = ~finite[:-1] | ~finite[1:] | (np.diff(rel) > max_gap_s)
        start = 0
        for stop in [*(np.flatnonzero(breaks) + 1).tolist(), n]:
            a, b = start, stop
            start = stop
            while a < b and not finite[a]:
                a += 1
            if b - a < 1:
                continue
            inside = (grid >= rel[a] - EVEN_TOLERANCE / fps) & (
                grid <= rel[b - 1] + EVEN_TOLERANCE / fps
            )
            if not np.any(inside):
                continue
            g = np.clip(grid[inside], rel[a], rel[b - 1])
            if b - a == 1:
                out[inside, m] = pos[a, m]
            elif b - a < 4:
                out[inside, m] = np.stack(
                    [np.interp(g, rel[a:b], pos[a:b, m, c]) for c in range(3)], axis=1
                )
            else:
                out[inside, m] = CubicSpline(rel[a:b], pos[a:b, m], axis=0)(g)
        i = left
        both = meas[i, m] & meas[i + 1, m] & ~lost[i]
        out_meas[:, m] = np.where(on_frame, meas[i, m], both) & np.all(
            np.isfinite(out[:, m]), axis=1
        )
    return UniformTrajectories(out, out_meas, t0, float(fps), True)


__all__ = ["EVEN_TOLERANCE", "UniformTrajectories", "uniform_trajectories"]

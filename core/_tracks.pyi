"""Type stub of the tracker's compiled loop (core/_tracks.pyx)."""

from typing import Any

import numpy as np
from numpy.typing import NDArray

from core.camera import Camera

def link(
    cams_py: tuple[Camera, Camera],
    gate_mm: float,
    max_coast_frames: int,
    max_single_view_frames: int,
    merge_px: tuple[float, float] | None,
    *arrays: NDArray[Any],  # the eleven of core.tracks._concatenated, in its order
    overlap_frames: list[int] | None,
) -> tuple[
    NDArray[np.int64],
    NDArray[np.int64],
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.intp],
    list[int],
]: ...
def project(cam: Camera, points_mm: NDArray[np.float64]) -> NDArray[np.float64]: ...
def assign(
    preds: NDArray[np.float64], gates: NDArray[np.float64], cands: NDArray[np.float64]
) -> list[tuple[int, int]]: ...
def distances(p: NDArray[np.float64], q: NDArray[np.float64]) -> NDArray[np.float64]: ...

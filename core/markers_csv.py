"""The ``markers.csv`` file (docs/interfaces.md): its header, writer and reader.

Long format, one row per frame and marker, header first::

    frame,time_s,marker,x_mm,y_mm,z_mm,status,reprojection_px
    0,0.0,thumb,12.3100,-40.0200,598.7700,measured,0.080

- ``frame``: the left video's frame number; ``time_s``: that frame's time (s).
- ``marker``: ``thumb``, ``index``, ... (the labels of the task's marker protocol).
- ``x_mm, y_mm, z_mm``: position in the rig's world frame (the left camera's
  frame), 4 decimals (0.1 µm); empty when ``status`` is ``missing``.
- ``status``: ``measured``, ``interpolated`` (gap filled) or ``missing``.
- ``reprojection_px``: reprojection error of a measured point, 3 decimals;
  empty for interpolated and missing points.

:class:`MarkerTable` is the file in memory. The pipeline writes it
(``core.pipeline.write_markers_csv``), the service reads it back for reports
and exports; this module is the only place that knows the columns.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np
from numpy.typing import NDArray

MARKERS_CSV_HEADER: tuple[str, ...] = (
    "frame",
    "time_s",
    "marker",
    "x_mm",
    "y_mm",
    "z_mm",
    "status",
    "reprojection_px",
)
MEASURED = "measured"
INTERPOLATED = "interpolated"
MISSING = "missing"
STATUSES: tuple[str, ...] = (MEASURED, INTERPOLATED, MISSING)

# Columns a reader needs; ``reprojection_px`` may be absent from older files.
_REQUIRED_COLUMNS = MARKERS_CSV_HEADER[:7]


@dataclass(frozen=True)
class MarkerTable:
    """Marker trajectories of one trial: the contents of ``markers.csv``.

    Attributes
    ----------
    fps : float
        Frame rate of the left video (Hz).
    frames : (T,) int64
        Left-video frame numbers, consecutive.
    labels : tuple of M str
        Marker names in column order (``thumb``, ``index``, ...).
    positions_mm : (T, M, 3) float64
        Positions in mm in the rig's world frame; NaN where missing.
    status : (T, M) str
        ``measured``, ``interpolated`` or ``missing``.
    reprojection_px : (T, M) float64
        Reprojection error of each measured sample (px); NaN when unknown.
    frame_time_s : (T,) float64 or None
        Time of each frame (s), e.g. its capture time; None means
        ``frames / fps`` (see :attr:`time_s`).
    """

    fps: float
    frames: NDArray[np.int64]
    labels: tuple[str, ...]
    positions_mm: NDArray[np.float64]
    status: NDArray[np.str_]
    reprojection_px: NDArray[np.float64]
    frame_time_s: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        t = self.frames.shape[0]
        m = len(self.labels)
        if self.positions_mm.shape != (t, m, 3):
            raise ValueError(f"positions_mm must be ({t}, {m}, 3), got {self.positions_mm.shape}")
        if self.status.shape != (t, m) or self.reprojection_px.shape != (t, m):
            raise ValueError(
                f"status and reprojection_px must be ({t}, {m}), got "
                f"{self.status.shape}, {self.reprojection_px.shape}"
            )
        if self.frame_time_s is not None and self.frame_time_s.shape != (t,):
            raise ValueError(f"frame_time_s must be ({t},), got {self.frame_time_s.shape}")
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {self.fps}")

    @property
    def time_s(self) -> NDArray[np.float64]:
        """(T,) time of each frame in s: ``frame_time_s``, or ``frame / fps`` without it."""
        if self.frame_time_s is not None:
            return self.frame_time_s
        return self.frames.astype(np.float64) / self.fps


def _fmt(value: float, decimals: int) -> str:
    return "" if not math.isfinite(value) else f"{value:.{decimals}f}"


def write_markers_csv(table: MarkerTable, path_or_file: str | Path | TextIO) -> None:
    """Write ``table`` as ``markers.csv`` (see the module docstring for the columns).

    Parameters
    ----------
    table : MarkerTable
    path_or_file : path or open text file
        A path is written as UTF-8 with ``\\n`` line ends.
    """
    if isinstance(path_or_file, str | Path):
        with open(path_or_file, "w", newline="", encoding="utf-8") as fh:
            write_markers_csv(table, fh)
        return
    writer = csv.writer(path_or_file, lineterminator="\n")
    writer.writerow(MARKERS_CSV_HEADER)
    time_s = table.time_s
    for t, frame in enumerate(table.frames):
        time_text = repr(round(float(time_s[t]), 6))
        for m, name in enumerate(table.labels):
            status = str(table.status[t, m])
            if status == MISSING:
                coords = ["", "", ""]
            else:
                coords = [_fmt(float(v), 4) for v in table.positions_mm[t, m]]
            rep = _fmt(float(table.reprojection_px[t, m]), 3) if status == MEASURED else ""
            writer.writerow([int(frame), time_text, name, *coords, status, rep])


def markers_csv_text(table: MarkerTable) -> str:
    """The ``markers.csv`` text of ``table``."""
    out = io.StringIO()
    write_markers_csv(table, out)
    return out.getvalue()


def read_markers_csv(source: str | Path | TextIO, *, fps: float | None = None) -> MarkerTable:
    """Read a ``markers.csv`` into a :class:`MarkerTable`.

    Parameters
    ----------
    source : path or open text file
    fps : float, optional
        Frame rate (Hz); estimated from ``frame`` and ``time_s`` when not given.

    Returns
    -------
    MarkerTable
        Frames from the smallest to the largest frame number in the file; a
        frame or marker absent from the file is ``missing``. ``frame_time_s``
        holds the file's times when every frame has one.

    Raises
    ------
    ValueError
        A required column is absent, or ``fps`` cannot be estimated.
    """
    if isinstance(source, str | Path):
        with open(source, newline="", encoding="utf-8") as fh:
            return read_markers_csv(fh, fps=fps)
    reader = csv.DictReader(source)
    missing = [c for c in _REQUIRED_COLUMNS if c not in (reader.fieldnames or ())]
    if missing:
        raise ValueError(f"markers.csv lacks the columns {missing}")
    rows = list(reader)
    labels: list[str] = []
    for row in rows:
        if row["marker"] not in labels:
            labels.append(row["marker"])
    frame_numbers = [int(row["frame"]) for row in rows]
    frame_min = min(frame_numbers, default=0)
    frame_max = max(frame_numbers, default=-1)
    frames = np.arange(frame_min, frame_max + 1, dtype=np.int64)
    t, m = frames.size, len(labels)
    pos = np.full((t, m, 3), np.nan)
    status = np.full((t, m), MISSING, dtype="<U12")
    reproj = np.full((t, m), np.nan)
    times = np.full(t, np.nan)
    for row, frame in zip(rows, frame_numbers, strict=True):
        i = frame - frame_min
        j = labels.index(row["marker"])
        times[i] = float(row["time_s"])
        status[i, j] = row["status"]
        if row["status"] != MISSING and row["x_mm"] != "":
            pos[i, j] = (float(row["x_mm"]), float(row["y_mm"]), float(row["z_mm"]))
        rp = row.get("reprojection_px") or ""
        if rp != "":
            reproj[i, j] = float(rp)
    if fps is None:
        ok = np.isfinite(times) & (frames != 0)
        if not ok.any():
            raise ValueError("cannot infer fps from markers.csv; pass fps=")
        fps = float(np.median(frames[ok] / times[ok]))
    return MarkerTable(
        fps=float(fps),
        frames=frames,
        labels=tuple(labels),
        positions_mm=pos,
        status=status,
        reprojection_px=reproj,
        frame_time_s=times if np.isfinite(times).all() else None,
    )

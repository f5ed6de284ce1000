"""Marker trajectories for motion-capture tools: C3D and OpenSim TRC files of a trial.

Both carry the trial's ``markers.csv`` (:class:`core.markers_csv.MarkerTable`) for
Vicon Nexus, Mokka, OpenSim...: coordinates in mm in the rig's world frame (the left
camera's frame: x right, y down, z away from the camera); missing samples are marked
invalid (C3D residual -1, empty TRC cells), interpolated ones residual 0 in C3D (its
"not a measured point").

Both formats have one frame rate and no time per frame: frame k is at k / rate. A
recording with lost frames or a variable frame rate is therefore written on a uniform
grid (:func:`on_uniform_grid`): each decoded frame in the slot its capture time falls
in, each lost frame an invalid sample. docs/reports.md, "Exports".
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import ezc3d
import numpy as np
from numpy.typing import NDArray

from core.markers_csv import MISSING, MarkerTable
from core.timing import FROM_CONTAINER, FrameTimes

#: The nominal rate is kept while it places the last frame within this share of a frame
#: interval of its capture time; otherwise the rate is the one the capture times give.
RATE_TOLERANCE = 0.1


def _num(value: float, digits: int) -> str:
    return "" if not math.isfinite(value) else f"{value:.{digits}f}"


def on_uniform_grid(table: MarkerTable) -> MarkerTable:
    """The trajectories on a uniform time grid: frame k at ``k / fps``, lost frames missing.

    The lost frames are found in the capture times (``table.frame_time_s``) by the rule
    of the analysis (:class:`core.timing.FrameTimes`: an interval of 1.5 nominal ones or
    more), so they are the ``sync.dropped_frames_left`` of result.json; each lost frame
    becomes a ``missing`` sample (NaN position). The rate is ``table.fps`` (result.json's
    ``fps``) unless it places the last frame more than :data:`RATE_TOLERANCE` of an
    interval away from its capture time (a rate taken from the median of jittered
    intervals); then it is the least-squares rate of the capture times over the grid.

    Parameters
    ----------
    table : MarkerTable
        As read from ``markers.csv``: one row per decoded frame.

    Returns
    -------
    MarkerTable
        ``frames`` consecutive from the first frame's slot, ``frame_time_s`` None (so
        ``time_s`` is ``frames / fps``); ``table`` itself when it has no capture times
        (already ``frame / fps``) or fewer than two frames.
    """
    t = table.frame_time_s
    if t is None or t.size < 2:
        return table
    try:
        times = FrameTimes(t, table.fps, FROM_CONTAINER)
    except ValueError:  # times that do not increase: nothing to place them by
        return table
    lost = np.zeros(t.size, dtype=np.int64)
    np.add.at(lost, np.asarray(times.dropped_after, dtype=np.int64), 1)
    offsets = np.arange(t.size) + np.concatenate([[0], np.cumsum(lost)[:-1]])  # from slot 0
    rate = float(table.fps)
    span = float(offsets[-1])
    if abs(span / rate - float(times.t_s[-1])) > RATE_TOLERANCE / rate:
        rate = 1.0 / float(np.polyfit(offsets, times.t_s, 1)[0])
    first = round(float(t[0]) * rate)
    n, m = int(offsets[-1]) + 1, len(table.labels)
    positions = np.full((n, m, 3), np.nan)
    status = np.full((n, m), MISSING, dtype="<U12")
    reprojection = np.full((n, m), np.nan)
    positions[offsets], status[offsets] = table.positions_mm, table.status
    reprojection[offsets] = table.reprojection_px
    return MarkerTable(
        fps=rate,
        frames=np.arange(first, first + n, dtype=np.int64),
        labels=table.labels,
        positions_mm=positions,
        status=status,
        reprojection_px=reprojection,
    )


def write_c3d(path: str | Path, table: MarkerTable, *, focal_px: float | None = None) -> Path:
    """Write the trajectories as a C3D file (ezc3d), in mm, on a uniform time grid.

    ``POINT:RATE`` is the grid's rate and frame k is at k / rate
    (:func:`on_uniform_grid`): a lost frame is an invalid sample, so that the frames
    after it keep their time.

    Each sample's fourth word says what it is, as the C3D format defines it (its
    camera mask in the high byte, its residual in ``POINT:SCALE`` steps in the low
    byte):

    - measured (stereo): the cameras 1 and 2 (left, right) and a positive residual,
      the reprojection error brought to mm at the marker's depth
      (``reprojection_px * z / focal_px``, ``focal_px`` the left camera's focal length;
      one step where either is unknown), 1 to 255 steps;
    - interpolated: 0, C3D's "filtered, interpolated or otherwise modified, not a
      measured point";
    - missing: -1 (C3D's "invalid") and zero coordinates.

    ``POINT:SCALE`` is -(largest coordinate / 32000) as the format asks (negative:
    float storage). The header's first frame number is left as ezc3d writes it (the
    grid's first frame is the recording's first, as the analysis measures from it).
    """
    path = Path(path)
    table = on_uniform_grid(table)
    c3d = ezc3d.c3d()
    t, m = table.frames.size, len(table.labels)
    pts = np.zeros((4, m, t))
    pts[:3] = np.transpose(table.positions_mm, (2, 1, 0))
    pts[3] = 1.0
    invalid = ~np.isfinite(table.positions_mm).all(axis=2)  # (T, M)
    pts[:3, invalid.T] = 0.0
    step = max(float(np.abs(pts[:3]).max()) if pts.size else 0.0, 1.0) / 32000.0  # mm
    measured = (table.status == "measured") & ~invalid
    steps = np.ones((t, m))
    if focal_px is not None and focal_px > 0:
        with np.errstate(invalid="ignore"):
            res_mm = np.abs(table.reprojection_px) * table.positions_mm[:, :, 2] / focal_px
        steps = np.where(np.isfinite(res_mm), np.rint(res_mm / step), 1.0)
    words = np.where(measured, (3 << 8) + np.clip(steps, 1, 255), 0.0)
    words[invalid] = -1.0
    c3d["parameters"]["POINT"]["RATE"]["value"] = [float(table.fps)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = list(table.labels)
    c3d["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c3d["parameters"]["POINT"]["SCALE"]["value"] = [-step]
    c3d["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = [
        f"{name} marker, bradyscope rig frame (left camera)" for name in table.labels
    ]
    c3d["data"]["points"] = pts
    c3d.add_parameter("MANUFACTURER", "COMPANY", "bradyscope")
    c3d.write(str(path))
    _finish_c3d(path, -step, words.astype(np.float32))
    return path


def _finish_c3d(path: Path, scale: float, words: NDArray[np.float32]) -> None:
    """Write what ezc3d does not into the file it wrote: the header's scale factor
    (words 7-8, which it leaves at -1 whatever ``POINT:SCALE`` says, and readers check
    that the two agree) and each sample's fourth word ``words`` (T, M) (ezc3d puts the
    camera mask and the residual in each other's byte in float files: its issue 386).

    ezc3d writes Intel (little-endian) float files of points only: both are checked.
    """
    t, m = words.shape
    with open(path, "r+b") as fh:
        header = fh.read(512)
        param_block, n_points, n_analog = header[0], *struct.unpack("<HH", header[2:6])
        data_block = struct.unpack("<H", header[16:18])[0]
        fh.seek(512 * (param_block - 1))
        processor = fh.read(4)[3]
        if processor != 84 or n_points != m or n_analog != 0:  # 84: Intel
            raise ValueError(
                f"unexpected C3D layout in {path.name}: processor {processor}, "
                f"{n_points} points, {n_analog} analog values"
            )
        fh.seek(12)
        fh.write(struct.pack("<f", scale))
        fh.seek(512 * (data_block - 1))
        data = np.frombuffer(fh.read(t * m * 16), dtype="<f4").reshape(t, m, 4).copy()
        data[:, :, 3] = words
        fh.seek(512 * (data_block - 1))
        fh.write(data.tobytes())


def write_trc(path: str | Path, table: MarkerTable) -> Path:
    """Write the trajectories as an OpenSim TRC file (tab separated, mm), on a uniform
    time grid (:func:`on_uniform_grid`).

    Frame numbers start at 1 as the format expects; ``Time`` is k / ``DataRate`` (s, the
    left video's clock, frame k of the grid), as readers that take the rate assume.
    Missing samples, and the lost frames' samples, are empty cells.
    """
    path = Path(path)
    table = on_uniform_grid(table)
    t, m = table.frames.size, len(table.labels)
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
        "OrigDataStartFrame\tOrigNumFrames",
        f"{table.fps:.10g}\t{table.fps:.10g}\t{t}\t{m}\tmm\t{table.fps:.10g}\t"
        f"{int(table.frames[0]) + 1 if t else 1}\t{t}",
        "Frame#\tTime\t" + "\t".join(f"{name}\t\t" for name in table.labels).rstrip("\t"),
        "\t\t" + "\t".join(f"X{k}\tY{k}\tZ{k}" for k in range(1, m + 1)),
        "",
    ]
    time_s = table.frames / table.fps
    for i in range(t):
        cells = [str(i + 1), f"{time_s[i]:.6f}"]
        for j in range(m):
            cells.extend(_num(float(v), 4) for v in table.positions_mm[i, j])
        lines.append("\t".join(cells))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def read_trc(path: str | Path) -> tuple[float, tuple[str, ...], NDArray[np.float64]]:
    """Read a TRC file written by :func:`write_trc`: ``(fps, labels, positions_mm (T, M, 3))``."""
    lines = Path(path).read_text(encoding="utf-8").splitlines()
    fps = float(lines[2].split("\t")[0])
    labels = tuple(c for c in lines[3].split("\t")[2:] if c)
    rows = [ln.split("\t") for ln in lines[6:] if ln.strip()]
    m = len(labels)
    pos = np.full((len(rows), m, 3), np.nan)
    for i, cells in enumerate(rows):
        values = [float(c) if c != "" else np.nan for c in cells[2 : 2 + 3 * m]]
        values += [np.nan] * (3 * m - len(values))
        pos[i] = np.asarray(values).reshape(m, 3)
    return fps, labels, pos

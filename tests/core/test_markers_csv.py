"""markers.csv: the header of docs/interfaces.md, writer and reader round trip."""

from __future__ import annotations

import io

import numpy as np
import pytest

from core.markers_csv import (
    MARKERS_CSV_HEADER,
    MarkerTable,
    markers_csv_text,
    read_markers_csv,
    write_markers_csv,
)


def _table(*, frame_time_s: np.ndarray | None = None) -> MarkerTable:
    rng = np.random.default_rng(3)
    t = 5
    pos = rng.normal(scale=50.0, size=(t, 2, 3)) + np.array([0.0, 0.0, 600.0])
    status = np.full((t, 2), "measured", dtype="<U12")
    status[2, 1] = "interpolated"
    status[4, 0] = "missing"
    pos[4, 0] = np.nan
    reproj = np.where(status == "measured", 0.125, np.nan)
    return MarkerTable(
        fps=100.0,
        frames=np.arange(10, 10 + t, dtype=np.int64),
        labels=("thumb", "index"),
        positions_mm=pos,
        status=status,
        reprojection_px=reproj,
        frame_time_s=frame_time_s,
    )


def test_header_and_rows_follow_the_interface() -> None:
    lines = markers_csv_text(_table()).splitlines()
    assert lines[0] == "frame,time_s,marker,x_mm,y_mm,z_mm,status,reprojection_px"
    assert tuple(lines[0].split(",")) == MARKERS_CSV_HEADER
    assert len(lines) == 1 + 5 * 2  # one row per frame and marker
    assert lines[1].startswith("10,0.1,thumb,")
    interpolated = lines[1 + 2 * 2 + 1].split(",")
    assert interpolated[6] == "interpolated" and interpolated[7] == ""  # no reprojection
    missing = lines[1 + 4 * 2].split(",")
    assert missing[3:] == ["", "", "", "missing", ""]


def test_round_trip_keeps_positions_status_and_times(tmp_path) -> None:
    times = np.array([0.1, 0.1101, 0.1199, 0.1302, 0.14])  # s, capture times off the grid
    table = _table(frame_time_s=times)
    write_markers_csv(table, tmp_path / "markers.csv")
    back = read_markers_csv(tmp_path / "markers.csv", fps=100.0)
    assert back.labels == table.labels
    np.testing.assert_array_equal(back.frames, table.frames)
    np.testing.assert_array_equal(back.status, table.status)
    np.testing.assert_allclose(back.positions_mm, table.positions_mm, atol=5e-5)  # mm, 4 decimals
    np.testing.assert_allclose(back.time_s, times, atol=1e-9)  # s, the file's times, not i/fps
    assert np.isnan(back.reprojection_px[2, 1]) and back.reprojection_px[0, 0] == 0.125


def test_fps_is_estimated_from_frames_and_times() -> None:
    back = read_markers_csv(io.StringIO(markers_csv_text(_table())))
    assert back.fps == pytest.approx(100.0)


def test_reader_names_the_missing_columns() -> None:
    with pytest.raises(ValueError, match=r"lacks the columns \['time_s'"):
        read_markers_csv(io.StringIO("frame,marker\n0,thumb\n"))


def test_table_checks_its_shapes() -> None:
    table = _table()
    with pytest.raises(ValueError, match="frame_time_s"):
        MarkerTable(
            fps=100.0,
            frames=table.frames,
            labels=table.labels,
            positions_mm=table.positions_mm,
            status=table.status,
            reprojection_px=table.reprojection_px,
            frame_time_s=np.zeros(3),
        )

"""The quality panel's camera-timing lines (issue 11): what result.json's ``sync`` says about
free-running cameras, read and shown in the report; the trial page is checked in test_pages."""

from __future__ import annotations

import dataclasses
import html as html_lib

from sample_trial import sample_report_data

from app.reports.data import ReportData, quality_rows
from app.reports.rendering import render_report_html
from app.reports.result import read_result
from core.clock import LARGE_DRIFT_PPM, LARGE_DROPS

#: The ``sync`` of a free-running pair as core writes it (docs/sync.md): a 60-fps right camera
#: 14.2 frames late, 300 ppm fast, three frames lost; both rolling shutters compensated.
FREE_RUNNING = {
    "offset_frames": 14.2,
    "method": "auto",
    "confidence": 0.83,
    "offset_s": 0.236667,
    "drift_ppm": 301.5,
    "dropped_frames_left": [],
    "dropped_frames_right": [150, 310, 455],
    "readout_ms": [15.0, 12.5],
    "epipolar_px_before": 1.9,
    "epipolar_px_after": 0.04,
    "time_source": ["container", "fps"],
    "fps_right": 59.94,
}


def _data(sync: dict[str, object], warnings: list[str] | None = None) -> ReportData:
    data = sample_report_data()
    result = dict(data.result)
    result["sync"] = sync
    result["fps"] = 60.0
    if warnings is not None:
        result["quality"] = {**result["quality"], "warnings": warnings}
    return dataclasses.replace(data, result=result)


def _rows(data: ReportData) -> dict[str, tuple[str, bool]]:
    return {r.label: (r.value, r.warn) for r in quality_rows(data)}


def test_free_running_sync_is_read_and_shown_line_by_line():
    sync = read_result({"fps": 60.0, "sync": FREE_RUNNING}).sync
    assert sync.offset_s == 0.236667 and sync.drift_ppm == 301.5
    assert sync.dropped_frames_right == (150, 310, 455) and sync.dropped_frames_left == ()
    assert sync.time_source == ("container", "fps") and sync.readout_ms == (15.0, 12.5)
    rows = _rows(_data(FREE_RUNNING))
    # Offset in frames and in ms (the clock offset itself, not frames / fps), how it was found.
    assert rows["Camera synchronisation offset"] == (
        "+14.20 frames (+236.7 ms), estimated (confidence 0.83)",
        False,
    )
    assert rows["Camera clock drift (right against left)"] == ("+302 ppm", False)
    assert rows["Frame rate"] == ("left 60.00 Hz, right 59.94 Hz", False)
    assert rows["Frame times from"] == (
        "left: container timestamps; right: frame rate (frame number / fps)",
        False,
    )
    assert rows["Lost frames found"] == (
        "left 0, right 3 (1 frame lost after frame 150, 1 after frame 310 and 1 after frame 455)",
        False,
    )
    assert rows["Rolling-shutter readout compensated"] == ("left 15 ms, right 12.5 ms", False)


def test_large_drift_many_lost_frames_and_a_guessed_offset_are_marked():
    many = list(range(100, 100 + 10 * (LARGE_DROPS + 5), 10))  # more than the panel lists
    sync = {
        **FREE_RUNNING,
        "drift_ppm": -(LARGE_DRIFT_PPM + 500),
        "dropped_frames_left": many,
        "confidence": 0.1,
        "time_source": ["file", "file"],
    }
    rows = _rows(_data(sync))
    assert rows["Camera clock drift (right against left)"] == ("-1500 ppm", True)
    value, warn = rows["Lost frames found"]
    assert warn and value == (
        f"left {len(many)} ({len(many)} frames lost in {len(many)} gaps; the longest, 1 frame"
        " (33 ms), after frame 100), right 3 (1 frame lost after frame 150, 1 after frame 310"
        " and 1 after frame 455)"
    )
    assert rows["Camera synchronisation offset"][1] is True  # confidence under 0.2: a guess
    assert rows["Frame times from"] == ("timestamps file", False)
    # At the limits, nothing is marked.
    sync = {**FREE_RUNNING, "drift_ppm": LARGE_DRIFT_PPM, "dropped_frames_left": many[:2]}
    assert 2 + 3 <= LARGE_DROPS
    rows = _rows(_data(sync))
    assert not rows["Camera clock drift (right against left)"][1]
    assert not rows["Lost frames found"][1]


def test_frames_lost_in_one_gap_are_counted_once_with_their_number():
    """One entry per lost frame: a frame number repeated is one gap of several frames (a
    browser take listed "after frame 0, 2, 2, 2, 2, 2, 2, 2 and 70 more")."""
    sync = {**FREE_RUNNING, "dropped_frames_left": [0, 2, 2, 2, 2, 2, 2, 2, 17]}
    value, warn = _rows(_data(sync))["Lost frames found"]
    assert value.startswith("left 9 (1 frame lost after frame 0, 7 after frame 2 and 1 after")
    assert warn  # 9 + 3 lost: more than LARGE_DROPS
    many = [0, *[2] * 7, 17, 28, 28, *[155] * 13, 157, 157]
    sync = {**FREE_RUNNING, "dropped_frames_left": many}
    value, _ = _rows(_data(sync))["Lost frames found"]
    # 60 Hz: 13 lost frames are 14 intervals, 233 ms between the frames either side.
    assert value.startswith(
        "left 26 (26 frames lost in 6 gaps; the longest, 13 frames (233 ms), after frame 155)"
    ), value


def test_a_lab_rig_result_and_an_older_one_show_what_they_carry():
    lab = {
        **FREE_RUNNING,
        "offset_frames": 3.0,
        "offset_s": 0.05,
        "drift_ppm": 0.0,
        "dropped_frames_right": [],
        "time_source": ["fps", "fps"],
        "fps_right": 60.0,
    }
    del lab["readout_ms"]
    rows = _rows(_data(lab))
    assert rows["Lost frames found"] == ("left 0, right 0", False)
    assert rows["Frame rate"] == ("60.0 Hz", False)
    assert "Rolling-shutter readout compensated" not in rows
    # A result from before the time model: the offset from frames / fps, nothing invented.
    rows = _rows(_data({"offset_frames": 1.25, "method": "given"}))
    assert rows["Camera synchronisation offset"] == ("+1.25 frames (+20.8 ms), given", False)
    for label in ("Camera clock drift (right against left)", "Lost frames found"):
        assert label not in rows
    # A malformed list is not shown rather than shown wrong.
    odd = read_result({"sync": {"dropped_frames_right": [1, "x"], "readout_ms": [1.0, None]}})
    assert odd.sync.dropped_frames_right == () and odd.sync.readout_ms == ()


def test_the_report_shows_the_sync_lines_and_core_warnings():
    warning = (
        "the cameras' clocks differ by 1500 ppm; check that both record at the frame rate"
        " they state"
    )
    html = html_lib.unescape(
        render_report_html(_data({**FREE_RUNNING, "drift_ppm": 1500.0}, [warning]))
    )
    for text in (
        "+14.20 frames (+236.7 ms), estimated (confidence 0.83)",
        "+1500 ppm",
        "left: container timestamps; right: frame rate (frame number / fps)",
        "right 3 (1 frame lost after frame 150, 1 after frame 310 and 1 after frame 455)",
        "left 15 ms, right 12.5 ms",
        warning,
    ):
        assert text in html, text
    assert 'class="quality-row warn"><dt>Camera clock drift' in html.replace("\n", "").replace(
        "  ", ""
    )

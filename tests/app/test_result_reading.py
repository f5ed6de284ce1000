"""app.reports.result: result.json read once, typed, from the places core writes."""

from __future__ import annotations

from sample_trial import synthetic_trial

from app.reports.result import TrialResult, read_result


def test_a_full_document_reads_typed() -> None:
    _, doc = synthetic_trial()
    result = read_result(doc)
    assert result.fps == 100.0
    assert result.sync.offset_frames == 1.25 and result.sync.method == "auto"
    assert result.metric("amplitude_decrement_mm_per_tap") == -0.8  # mm/tap, as written
    assert result.metrics["tap_count"] == 20 and isinstance(result.metrics["tap_count"], int)
    assert result.metrics_first_10["frequency_hz"] == 2.5
    assert len(result.taps) == 20 and result.cycle_amplitudes[0] == 52.0
    assert [e.kind for e in result.events] == ["hesitation"]
    assert result.quality.reprojection_px_median == 0.1
    assert result.quality.warnings == ("The thumb marker was lost in the last frame.",)


def test_only_numbers_are_metrics_and_nothing_is_read_twice() -> None:
    doc = {
        "metrics": {
            "tap_count": 3,
            "frequency_hz": None,  # undefined: kept, as None
            "flag": True,  # a bool is no metric
            "note": "text",
            # core writes these at the top level; under metrics they are not read
            "events": [{"kind": "halt", "t_start_s": 1.0, "duration_s": 0.5}],
            "metrics_first_10": {"tap_count": 2},
        },
        "quality": {"warnings": "one string, not a list"},
    }
    result = read_result(doc)
    assert result.metrics == {"tap_count": 3, "frequency_hz": None}
    assert result.events == () and result.metrics_first_10 == {}
    assert result.quality.warnings == ()
    assert result.metric("frequency_hz") is None


def test_an_empty_document_reads_as_an_empty_result() -> None:
    assert read_result(None) == TrialResult()
    assert read_result({"fps": 0, "sync": {"offset_frames": None}}).fps is None


def test_marker_images_set_aside_and_overlaps_reach_the_quality_panel() -> None:
    from app.reports.data import quality_rows
    from app.reports.result import read_result

    doc = {
        "fps": 100.0,
        "quality": {
            "frames_left": 1000,
            "set_aside_frames_left": 3,
            "set_aside_frames_right": 140,
            "overlap_frames": 12,
            "merged_measured_frames_left": 0,
            "merged_measured_frames_right": 97,
        },
    }
    q = read_result(doc).quality
    assert (q.set_aside_frames, q.overlap_frames, q.frames) == (143, 12, 1000)
    assert q.merged_measured_frames == 97

    class _Data:  # the two fields quality_rows reads
        calibration = None
        analysis = read_result(doc)

    rows = {r.label: r for r in quality_rows(_Data())}  # type: ignore[arg-type]
    aside = rows["Marker images set aside (partly hidden or merged; camera frames)"]
    assert aside.value == "143" and aside.warn  # more than 5 % of the 2000 camera frames
    overlap = rows["Frames with the two markers overlapping in a camera (not measured there)"]
    assert overlap.value == "12" and not overlap.warn
    merged = rows["Touching marker images measured as two discs (camera frames)"]
    assert merged.value == "97" and not merged.warn  # measured, not a loss
    # older results without the fields show no such rows
    old = {
        r.label
        for r in quality_rows(type("D", (), {"calibration": None, "analysis": read_result({})})())
    }  # type: ignore[arg-type]
    assert not any(
        "set aside" in label or "overlapping" in label or "two discs" in label for label in old
    )


def test_frames_measured_counts_measured_only() -> None:
    """The quality panel's "Frames measured" is the measured share, not measured plus
    interpolated; interpolated and missing frames have their own rows."""
    from app.reports.data import quality_rows
    from app.reports.result import read_result

    doc = {
        "fps": 100.0,
        "quality": {
            "tracked_fraction": 0.97,  # measured or interpolated
            "measured_fraction": 0.88,
            "interpolated_fraction": 0.09,
            "frames_left": 1000,
        },
    }

    class _Data:  # the two fields quality_rows reads
        calibration = None
        analysis = read_result(doc)

    rows = {r.label: r for r in quality_rows(_Data())}  # type: ignore[arg-type]
    assert (rows["Frames measured"].value, rows["Frames measured"].warn) == ("88.0 %", True)
    assert (rows["Frames interpolated"].value, rows["Frames interpolated"].warn) == ("9.0 %", True)
    assert (rows["Frames missing"].value, rows["Frames missing"].warn) == ("3.0 %", False)

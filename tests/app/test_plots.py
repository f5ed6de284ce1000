"""Plots: valid inline SVG, the marks clinicians rely on, unique ids, shape errors."""

from __future__ import annotations

import itertools
import re
from dataclasses import replace
from datetime import UTC, datetime

import numpy as np
import pytest
from sample_trial import CLOSED_MM, synthetic_trial

from app import plots, trends
from app.reports.figures import signal_series
from app.reports.result import result_events


@pytest.fixture(scope="module")
def trial():
    return synthetic_trial()


def _n_drawn_paths(svg: str) -> int:
    return len(re.findall(r"<path [^>]*d=\"M", svg))


def _aperture(markers):
    """The thumb–index distance per frame, as the report draws it (mm)."""
    return signal_series(markers, "finger_tapping")[1]


def test_the_finger_tapping_signal_is_the_thumb_index_distance(trial):
    markers, result = trial
    a = _aperture(markers)
    assert a.shape == (markers.frames.size,)
    # Before the first tap the fingers are closed: distance = CLOSED_MM (+ jitter).
    np.testing.assert_allclose(a[:20], CLOSED_MM, atol=0.1)  # mm, 0.02 mm jitter per axis
    peak = result["taps"][0]
    i = round(peak["t_max_aperture_s"] * markers.fps)
    np.testing.assert_allclose(a[i], CLOSED_MM + peak["amplitude_mm"], atol=0.1)  # mm
    assert np.isnan(a[-1])  # the thumb is missing in the last frame
    # Convention: the marker order must not matter.
    swapped = replace(
        markers,
        labels=("index", "thumb"),
        positions_mm=markers.positions_mm[:, ::-1],
        status=markers.status[:, ::-1],
    )
    np.testing.assert_array_equal(_aperture(swapped), a)


def test_a_trial_without_the_task_markers_has_no_signal(trial):
    markers, _ = trial
    assert signal_series(replace(markers, labels=("a", "b")), "finger_tapping") is None
    assert signal_series(markers, "toe_tapping") is None
    assert signal_series(None, "finger_tapping") is None


def test_aperture_plot_marks_every_tap_and_the_hesitation(trial):
    markers, result = trial
    a = _aperture(markers)
    svg = plots.aperture_plot(markers.time_s, a, taps=result["taps"], events=result_events(result))
    assert svg.startswith("<svg") and svg.rstrip().endswith("</svg>")
    assert "<title>Aperture over time: 20 taps, 1 hesitation(s), 0 halt(s) marked</title>" in svg
    # Every tap is numbered on the plot (text stays text: svg.fonttype = none).
    labels = set(re.findall(r">(\d+)</text>", svg))
    assert {str(k) for k in range(1, 21)} <= labels
    assert "hesitation" in svg
    # Without events nothing is shaded and the legend has no hesitation entry.
    plain = plots.aperture_plot(markers.time_s, a, taps=result["taps"])
    assert "hesitation" not in plain.split("</title>", 1)[1]
    assert _n_drawn_paths(svg) > _n_drawn_paths(plain)


def test_aperture_plot_halts_are_marked_apart():
    t = np.arange(300) / 100.0
    a = 20 + 10 * np.sin(2 * np.pi * 2 * t)
    svg = plots.aperture_plot(t, a, events=[plots.PlotEvent("halt", 1.0, 1.8)])
    assert "halt" in svg.split("</title>", 1)[1]
    assert plots.COLOURS["halt"] in svg


def test_empty_inputs_give_a_message_not_an_error():
    svg = plots.aperture_plot(np.zeros(0), np.zeros(0))
    assert "No aperture could be measured" in svg
    assert "No taps were found." in plots.tap_amplitude_plot([])
    assert "No taps were found." in plots.velocity_plot([])
    assert "No fingertip positions" in plots.fingertip_paths_plot(
        np.full((3, 2, 3), np.nan), labels=["thumb", "index"]
    )
    assert "No mean amplitude measured yet." in trends.trend_plot(
        [], label="Mean amplitude", unit="mm"
    )


def test_shape_errors_are_value_errors():
    with pytest.raises(ValueError):
        plots.aperture_plot(np.zeros(5), np.zeros(4))
    with pytest.raises(ValueError):
        plots.aperture_plot(np.zeros(5), np.zeros(5), interpolated=np.zeros(4, bool))
    with pytest.raises(ValueError):
        plots.fingertip_paths_plot(np.zeros((5, 2, 3)), labels=["thumb"])


def test_amplitude_plot_draws_the_given_decrement(trial):
    _, result = trial
    svg = plots.tap_amplitude_plot(result["taps"], decrement_per_tap=-0.8)
    assert "decrement -0.80 mm/tap" in svg
    # Without a slope (the metrics did not assess it) none is drawn or fitted: a result
    # page said "decrement -0.77 mm/tap" beside a metrics table saying not assessable.
    unassessed = plots.tap_amplitude_plot(result["taps"])
    assert "decrement not assessable" in unassessed and "mm/tap" not in unassessed
    assert "<title>Amplitude of" in unassessed and "decrement line" not in unassessed
    # More than 10 taps: the legend says the line is over all of them, as the summary
    # beside it gives the first 10 taps' slope (the two were read as one number).
    n = len(result["taps"])
    assert n > 10 and f"decrement -0.80 mm/tap, all {n} taps" in svg
    ten = plots.tap_amplitude_plot(result["taps"][:10], decrement_per_tap=-0.8)
    assert "decrement -0.80 mm/tap" in ten and "mm/tap, all" not in ten


def test_ids_are_unique_when_plots_share_a_page(trial):
    markers, result = trial
    page = "".join(
        [
            plots.tap_amplitude_plot(result["taps"]),
            plots.tap_amplitude_plot(result["taps"]),
            plots.velocity_plot(result["taps"]),
            plots.fingertip_paths_plot(markers.positions_mm, labels=markers.labels),
        ]
    )
    ids = re.findall(r'id="([^"]+)"', page)
    assert ids and len(ids) == len(set(ids))
    # Every local reference points at an id on the page.
    refs = set(re.findall(r"url\(#([^)]+)\)", page)) | set(re.findall(r'href="#([^"]+)"', page))
    assert refs <= set(ids)


def test_trend_plot_separates_hands_and_medication():
    pts = [
        trends.TrendPoint(
            datetime(2024, m, 1, tzinfo=UTC), hand, med, 50.0 - m + (5 if med == "on" else 0)
        )
        for m in (1, 4, 7, 10)
        for hand in ("left", "right")
        for med in ("on", "off")
    ]
    svg = trends.trend_plot(pts, label="Mean amplitude", unit="mm")
    for name in ("left, on", "left, off", "right, on", "right, off"):
        assert name in svg
    assert "Mean amplitude (mm)" in svg
    # One series with a single medication state has a single legend entry.
    only_on = trends.trend_plot(
        [p for p in pts if p.medication_state == "on"], label="A", unit="mm"
    )
    assert "left, off" not in only_on


def test_a_trend_of_few_visits_is_labelled_at_the_visits():
    """Three visits over two years were labelled '2025' and '2026' only: the first visit sat
    on the '2025' tick (found in a clinician-style review)."""
    days = (datetime(2024, 11, 27, 9, tzinfo=UTC), datetime(2025, 11, 27, 9, tzinfo=UTC))
    days += (datetime(2026, 10, 28, 9, tzinfo=UTC),)
    pts = [trends.TrendPoint(d, "right", "off", 40.0) for d in days]
    svg = trends.trend_plot(pts, label="Mean amplitude", unit="mm")
    ticks = re.findall(r">(\d{1,2} [A-Z][a-z]{2})<", svg)
    assert ticks == ["27 Nov", "27 Nov", "28 Oct"], ticks
    # many visits: the concise automatic dates again
    many = [
        trends.TrendPoint(datetime(2024, m, 1, tzinfo=UTC), "right", "off", 40.0)
        for m in range(1, 13)
    ]
    assert not re.findall(
        r">(\d{1,2} [A-Z][a-z]{2})<", trends.trend_plot(many, label="A", unit="mm")
    )


def test_missing_and_unreliable_tap_values_do_not_break_the_plots(trial):
    markers, result = trial
    taps = [dict(tp) for tp in result["taps"]]
    taps[3]["opening_velocity_mm_s_max"] = None
    taps[4]["amplitude_mm"] = None
    taps[5]["reliable"] = False
    svg = plots.tap_amplitude_plot(taps, decrement_per_tap=-0.8)
    assert "unreliable tap" in svg
    assert "decrement -0.80 mm/tap" in svg
    assert plots.velocity_plot(taps).startswith("<svg")
    a = _aperture(markers)
    taps[6]["t_max_aperture_s"] = None
    assert plots.aperture_plot(markers.time_s, a, taps=taps).startswith("<svg")


def _same_day_points(values=(1.0, 2.0, 0.0, 3.0)):
    """Four trials of one visit (both hands, off and on, an hour apart) and one a year before."""
    day = datetime(2025, 3, 1, 9, tzinfo=UTC)
    pts = [
        trends.TrendPoint(day.replace(hour=9 + 2 * (med == "on")), hand, med, v)
        for (hand, med), v in zip(
            (("left", "off"), ("right", "off"), ("left", "on"), ("right", "on")),
            values,
            strict=True,
        )
    ]
    return [*pts, trends.TrendPoint(datetime(2024, 3, 1, tzinfo=UTC), "right", "off", 2.0)]


def test_trend_points_show_their_values_on_hover():
    pts = _same_day_points()
    svg = trends.trend_plot(pts, label="Hesitations and halts", unit="count", integer=True)
    titles = re.findall(r"<title>([^<]*)</title>", svg)[1:]  # the first is the plot's own
    assert len(titles) == len(pts)
    assert "2025-03-01 11:00, right hand, medication on: 3" in titles


def _y_ticks(svg: str) -> list[str]:
    return re.findall(r'id="trend\d+-ytick_\d+">.*?<text [^>]*>([^<]+)</text>', svg, re.S)


def test_count_trends_have_whole_number_ticks():
    svg = trends.trend_plot(_same_day_points(), label="Hesitations", unit="count", integer=True)
    ticks = _y_ticks(svg)
    assert ticks and all(float(t).is_integer() for t in ticks), ticks
    # The check can fail: matplotlib's default ticks for 0-3 include halves.
    plain = trends.trend_plot(_same_day_points(), label="Hesitations", unit="count")
    assert any(not float(t).is_integer() for t in _y_ticks(plain)), _y_ticks(plain)


def test_points_of_one_visit_do_not_hide_each_other():
    # Same value everywhere: without the sideways spread the two on/off pairs would coincide.
    svg = trends.trend_plot(_same_day_points((2.0, 2.0, 2.0, 2.0)), label="A", unit="mm")
    xs = [
        float(x)
        for x in re.findall(r'<g id="trend\d+-pt\d+">.*?<use [^>]*?x="([\d.]+)"', svg, re.S)
    ]
    assert len(xs) == 5
    visit = sorted(xs)[1:]  # the year-before point is leftmost
    assert min(b - a for a, b in itertools.pairwise(visit)) > 2.0  # pt apart

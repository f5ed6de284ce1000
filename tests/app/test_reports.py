"""The report: one template as HTML and PDF; the PDF's words and plots are checked."""

from __future__ import annotations

import dataclasses
import json
import logging
import re
import shutil
import subprocess
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from sample_trial import sample_report_data

from app.reports.catalogue import format_metric, metric_rows
from app.reports.figures import plots_document, read_plots_document
from app.reports.rendering import render_report_html, render_report_pdf

needs_poppler = pytest.mark.skipif(
    shutil.which("pdftotext") is None or shutil.which("pdftoppm") is None,
    reason="poppler-utils (pdftotext, pdftoppm) is not installed",
)


@pytest.fixture(scope="module")
def data():
    return sample_report_data(patient_code="PD-0042")


@pytest.fixture(scope="module")
def pdf_path(data, tmp_path_factory):
    path = tmp_path_factory.mktemp("report") / "report.pdf"
    path.write_bytes(render_report_pdf(data))
    return path


def _expected_values(data) -> list[str]:
    metrics = data.result["metrics"]
    return [format_metric(k, v) for k, v in metrics.items() if isinstance(v, int | float)]


def test_format_metric_uses_the_catalogue_decimals():
    assert format_metric("amplitude_mm_mean", 44.44) == "44.4"
    assert format_metric("frequency_hz", 2.3214) == "2.32"
    assert format_metric("tap_count", 20) == "20"
    assert format_metric("amplitude_decrement_mm_per_tap", 0.5) == "+0.50"
    assert format_metric("frequency_hz", float("nan")) == "–"
    assert format_metric("frequency_hz", None) == "–"


def test_hesitation_definition_matches_docs_metrics():
    # Both criteria of docs/metrics.md, with its thresholds, are what users read.
    from app.reports.catalogue import METRICS

    docs = (Path(__file__).resolve().parents[2] / "docs" / "metrics.md").read_text()
    assert "longer than **1.5 ×** the" in docs and "of at least **0.2 s**" in docs
    definition = METRICS["hesitation_count"].definition
    assert "over 1.5 times the median of the neighbouring taps" in definition
    assert "or that follow a closed pause of at least 0.2 s" in definition


def test_metric_rows_follow_the_catalogue_and_show_first_10(data):
    rows = metric_rows(data.result)
    assert [r.key for r in rows][:3] == ["tap_count", "frequency_hz", "amplitude_mm_mean"]
    amp = next(r for r in rows if r.key == "amplitude_mm_mean")
    assert amp.unit == "mm" and amp.definition
    assert amp.value_first_10 == format_metric("amplitude_mm_mean", 48.4)
    assert all(r.key not in ("events", "metrics_first_10") for r in rows)


def test_html_report_is_standalone_and_complete(data):
    html = render_report_html(data)
    assert "PD-0042" in html
    for value in _expected_values(data):
        assert f">{value}<" in html, value
    for name in ("aperture", "amplitude", "velocity", "paths"):
        assert f'data-plot="{name}"' in html, name
    # No external resource: no src/href to anything but in-page fragments.
    assert not re.search(r'(?:src|href)="(?!#)', html)
    assert "@import" not in html and "url(http" not in html
    assert "The thumb marker was lost in the last frame." in html  # warnings in the quality panel
    assert "clinic-A, calibration v3" in html and "0.21 px" in html
    assert "+1.25 frames (+12.5 ms), estimated" in html


def test_user_text_is_escaped(data):
    evil = dataclasses.replace(data, notes="<script>alert(1)</script>")
    html = render_report_html(evil)
    assert "<script>alert(1)</script>" not in html
    assert "&lt;script&gt;" in html


def test_pdf_renderer_fetches_no_url(data, monkeypatch):
    import app.reports.rendering as reports

    fetched: list[str] = []
    original = reports._refusing_fetcher

    def spying():
        fetcher = original()
        fetch = fetcher.fetch

        def spy(url, headers=None):
            fetched.append(url)
            return fetch(url, headers)

        fetcher.fetch = spy
        return fetcher

    monkeypatch.setattr(reports, "_refusing_fetcher", spying)
    html_with_remote = render_report_html(data).replace(
        "</body>", '<img src="http://127.0.0.1:9/tracker.png" alt=""></body>'
    )
    monkeypatch.setattr(reports, "render_report_html", lambda d: html_with_remote)
    pdf = reports.render_report_pdf(data)
    assert pdf.startswith(b"%PDF")
    # The plots are inline data (each SVG plot as a data: image); the one remote URL
    # was asked for, and refused (no exception).
    remote = [url for url in fetched if not url.startswith("data:")]
    assert remote == ["http://127.0.0.1:9/tracker.png"]
    assert sum(url.startswith("data:image/svg+xml;base64,") for url in fetched) == 4
    with pytest.raises(ValueError, match="does not fetch"):
        original().fetch("http://example.org/x.css")


def test_weasyprint_reads_every_rule_of_the_report(data, caplog):
    """WeasyPrint logs a warning for each CSS declaration it cannot read and drops it: one
    per report made, in the server's and the worker's logs, and a rule lost from the PDF."""
    with caplog.at_level(logging.WARNING, logger="weasyprint"):
        assert render_report_pdf(data).startswith(b"%PDF")
    assert [r.getMessage() for r in caplog.records if r.name.startswith("weasyprint")] == []


def test_pdf_warm_up_makes_a_pdf_with_the_reports_font(tmp_path):
    """``bradyscope serve`` warms WeasyPrint up once it answers: a real one-line PDF, in the
    font the reports use, so that the first report does not pay for loading either."""
    import app.reports.rendering as reports

    pdf = tmp_path / "warm.pdf"
    pdf.write_bytes(reports.warm_up_pdf())
    fonts = subprocess.run(["pdffonts", str(pdf)], capture_output=True, text=True, check=True)
    assert "DejaVu-Sans" in fonts.stdout


def test_report_key_names_what_the_report_shows(data):
    """The PDF report cache's key: the same report at another "generated on" time has the
    same key; a change of anything the report shows, another."""
    from app.reports.rendering import report_key

    first = report_key(data)
    later = dataclasses.replace(data, generated_at=data.generated_at + timedelta(hours=3))
    assert report_key(later) == first and re.fullmatch(r"[0-9a-f]{64}", first)
    changes = {
        "rating": dataclasses.replace(data, clinician_rating=3, rating_comment="Slower"),
        "revision": dataclasses.replace(data, revision=2),
        "notes": dataclasses.replace(data, notes="Tremor at rest."),
        "result": dataclasses.replace(
            data, result={**data.result, "metrics": {**data.result["metrics"], "tap_count": 9}}
        ),
        "time zone": dataclasses.replace(data, timezone="America/New_York"),
        "patient": dataclasses.replace(data, patient_code="PD-0043"),
    }
    keys = {what: report_key(changed) for what, changed in changes.items()}
    assert first not in keys.values()
    assert len(set(keys.values())) == len(changes)


def _pdf_words(pdf: Path, page: int) -> list[tuple[str, float, float, float, float]]:
    out = subprocess.run(
        ["pdftotext", "-bbox", "-f", str(page), "-l", str(page), str(pdf), "-"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    pattern = (
        r'<word xMin="([\d.]+)" yMin="([\d.]+)" xMax="([\d.]+)" yMax="([\d.]+)">([^<]*)</word>'
    )
    return [
        (w, float(a), float(b), float(c), float(d)) for a, b, c, d, w in re.findall(pattern, out)
    ]


def _plot_regions(pdf: Path) -> dict[str, tuple[int, tuple[float, float, float, float]]]:
    """Page and box (pt) of each plot: the band just above its caption's first word."""
    n_pages = int(
        re.search(
            r"Pages:\s+(\d+)",
            subprocess.run(
                ["pdfinfo", str(pdf)], check=True, capture_output=True, text=True
            ).stdout,
        ).group(1)
    )
    captions = {
        "Thumb–index": "aperture",
        "Amplitude": "amplitude",
        "Peak": "velocity",
        "Fingertip": "paths",
    }
    regions = {}
    # Captions follow the "Aperture over time" heading (page 1, after the summary block,
    # whose rows name the same measures); earlier words are tables.
    in_movement = False
    for page in range(1, n_pages + 1):
        for word, x0, y0, _x1, _y1 in _pdf_words(pdf, page):
            in_movement = in_movement or word == "Aperture"
            name = captions.get(word)
            if in_movement and name and name not in regions:
                width = 240.0 if name in ("amplitude", "velocity") else 490.0
                regions[name] = (page, (x0, y0 - 130.0, x0 + width, y0 - 8.0))
    return regions


def _coloured_fraction(
    pdf: Path, page: int, box: tuple[float, float, float, float], tmp: Path
) -> float:
    """Fraction of clearly coloured (data-drawing) pixels of ``box`` on ``page`` at 72 dpi."""
    stem = tmp / f"p{page}"
    subprocess.run(
        [
            "pdftoppm",
            "-r",
            "72",
            "-png",
            "-f",
            str(page),
            "-l",
            str(page),
            "-singlefile",
            str(pdf),
            str(stem),
        ],
        check=True,
    )
    img = np.asarray(Image.open(f"{stem}.png").convert("RGB")).astype(int)
    x0, y0, x1, y1 = (round(v) for v in box)
    crop = img[max(y0, 0) : y1, x0:x1]
    saturation = crop.max(axis=2) - crop.min(axis=2)
    return float(np.mean(saturation > 60))


@needs_poppler
def test_pdf_text_holds_the_patient_code_and_every_metric_value(pdf_path, data):
    text = subprocess.run(
        ["pdftotext", "-layout", str(pdf_path), "-"], check=True, capture_output=True, text=True
    ).stdout
    assert "PD-0042" in text
    for value in _expected_values(data):
        assert re.search(rf"(?<![\d.]){re.escape(value)}(?![\d])", text), value
    assert "Measurement quality" in text and "Definitions" in text


@needs_poppler
def test_pdf_plot_words_stay_text(pdf_path):
    """The plots reach the PDF as vector drawings: their axis labels are searchable text."""
    text = subprocess.run(
        ["pdftotext", str(pdf_path), "-"], check=True, capture_output=True, text=True
    ).stdout
    for words in ("time (s)", "tap peak", "thumb–index distance (mm)"):
        assert words in text, words


@needs_poppler
def test_pdf_plots_are_drawn_not_blank(pdf_path, tmp_path):
    regions = _plot_regions(pdf_path)
    assert set(regions) == {"aperture", "amplitude", "velocity", "paths"}
    for name, (page, box) in regions.items():
        fraction = _coloured_fraction(pdf_path, page, box, tmp_path)
        assert fraction > 0.002, f"{name} plot looks blank ({fraction:.4f} coloured)"


@needs_poppler
def test_blank_plot_check_catches_a_report_without_data(data, tmp_path):
    """The blank-plot check must fail on a report whose plots have no data."""
    empty = dataclasses.replace(data, markers=None, result={**data.result, "taps": []})
    pdf = tmp_path / "empty.pdf"
    pdf.write_bytes(render_report_pdf(empty))
    regions = _plot_regions(pdf)
    assert set(regions) == {"aperture", "amplitude", "velocity", "paths"}
    for name, (page, box) in regions.items():
        assert _coloured_fraction(pdf, page, box, tmp_path) < 0.0005, name


def test_null_values_render_as_a_dash(data):
    taps = [dict(tp) for tp in data.result["taps"]]
    taps[0]["amplitude_mm"] = None
    taps[1]["reliable"] = False
    metrics = {**data.result["metrics"], "amplitude_decrement_mm_per_tap": None}
    odd = dataclasses.replace(data, result={**data.result, "taps": taps, "metrics": metrics})
    html = render_report_html(odd)
    row = re.search(r'<tr data-metric="amplitude_decrement_mm_per_tap">.*?</tr>', html, re.S).group(
        0
    )
    assert '<td class="num">–</td>' in row
    assert "Unreliable tap" in html


def test_comparison_plots_share_their_scales(data):
    from sample_trial import synthetic_trial

    from app.reports.figures import comparison_plots

    markers, result = synthetic_trial(amplitude0_mm=30.0, seed=3)
    smaller = dataclasses.replace(data, markers=markers, result=result, trial_id=8)
    first, second = comparison_plots(data, smaller)

    def ticks(svg: str) -> set[str]:
        return set(re.findall(r">(\d+)</text>", svg))

    assert ticks(first["amplitude"]) == ticks(second["amplitude"])
    assert ticks(first["aperture"]) == ticks(second["aperture"])
    # Drawn alone, the smaller trial gets its own, shorter axis: the check above can fail.
    from app.reports.figures import report_plots

    assert ticks(report_plots(smaller)["amplitude"]) != ticks(first["amplitude"])
    ids = re.findall(r'id="([^"]+)"', first["aperture"] + second["aperture"])
    assert len(ids) == len(set(ids))


def test_stored_plots_round_trip_and_other_plotting_code_is_drawn_again(data):
    stored = plots_document(data.result, data.markers)
    read = read_plots_document(stored)
    assert read is not None and set(read) == {"aperture", "amplitude", "velocity", "paths"}
    assert render_report_html(dataclasses.replace(data, plots=read)).count("<svg") >= 4
    # The report shows the stored drawing, not a new one (ids are unique per drawing).
    html = render_report_html(dataclasses.replace(data, markers=None, plots=read))
    assert all(svg in html for svg in read.values())
    # Plots drawn by other plotting code, or not a plots document: None (drawn again).
    doc = json.loads(stored)
    assert read_plots_document(json.dumps({**doc, "style": "other"})) is None
    assert read_plots_document(json.dumps({**doc, "format": "other/1"})) is None
    assert read_plots_document(json.dumps({**doc, "plots": {"aperture": "<svg/>"}})) is None
    assert read_plots_document("not json") is None


@needs_poppler
def test_the_trial_report_names_the_trial_by_its_own_time_not_the_sessions(data, tmp_path):
    """The visit report named each trial by its upload ("uploaded 21:48 UTC"), while the
    report of the same trial said the session's start as "Recorded" on its header and on
    every page's running head: two takes of a visit read alike. Both now say the trial's
    own time, as the visit report does; the session's time stays, named as such."""
    take = dataclasses.replace(data, uploaded_at=data.recorded_at + timedelta(minutes=18))
    pdf = tmp_path / "trial.pdf"
    pdf.write_bytes(render_report_pdf(take))
    raw = subprocess.run(
        ["pdftotext", str(pdf), "-"], check=True, capture_output=True, text=True
    ).stdout
    text = " ".join(raw.split())
    assert "#7, uploaded 2025-03-14 09:48 UTC" in text  # the header's Trial
    assert "2025-03-14 09:30 UTC" in text and "SESSION" in text  # the session's, named so
    assert "RECORDED" not in text  # the header's keys are upper case (CSS)
    pages = raw.count("\f")
    head = "· medication off · uploaded 2025-03-14 09:48 UTC · trial #7"
    assert pages > 1 and text.count(head) == pages  # every page's running head
    assert "09:30 UTC · trial #7" not in text
    # a trial whose upload time is not known keeps the session's time, with no "uploaded"
    unknown = render_report_html(dataclasses.replace(data, uploaded_at=None))
    assert "#7, 2025-03-14 09:30 UTC" in unknown and "uploaded" not in unknown

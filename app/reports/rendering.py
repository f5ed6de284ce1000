"""The report of one trial: one Jinja2 template rendered as HTML and as PDF.

- :func:`render_report_html` renders ``templates/report.html`` (a standalone
  page: inline CSS and inline SVG plots, no external resource).
- :func:`render_report_pdf` renders the same HTML with WeasyPrint; its URL
  fetcher refuses every URL, so a report can never reach the network.

For the PDF each inline ``<svg>`` plot becomes an ``<img>`` of the same SVG
(a ``data:`` URL, :func:`svg_plots_as_images`): WeasyPrint then draws it as an
image, outside the page's CSS cascade, which made the report's PDF about 30 %
cheaper (docs/performance.md); the plots stay vector and their words searchable.
:func:`report_key` names what a report shows, for the PDF report cache
(:mod:`app.reports.pdf_cache`).
"""

from __future__ import annotations

import base64
import hashlib
import html as html_lib
import re
from collections.abc import Sequence
from dataclasses import replace
from datetime import UTC, datetime
from typing import Any

from app.reports.catalogue import metric_rows
from app.reports.data import ReportData, quality_rows, summary_column
from app.reports.figures import report_plots
from app.reports.summary import short_taps_note, summary_rows
from app.reports.task_metrics import primary_specs
from app.reports.visit import VisitData, task_groups, trial_time
from app.templating import jinja_env
from core.tasks import TASKS, Task, parse_task
from core.version import software_version


def _word(task: str) -> str:
    return "tap" if parse_task(task) is Task.FINGER_TAPPING else "cycle"


def summary_context(data: ReportData) -> dict[str, Any]:
    """The summary block of one trial, with the other hand and medication state beside it."""
    columns = [summary_column(data), *data.beside]
    return {
        "summary_columns": columns,
        "summary_rows": summary_rows(columns),
        "summary_first": True,
        "summary_caption": f"First 10 {_word(data.task)}s against the MDS-UPDRS"
        f" {parse_task(data.task).updrs_item} wording"
        + (", beside the same visit's other trials" if data.beside else ""),
        "summary_note": short_taps_note(columns[0]),
    }


def report_context(data: ReportData) -> dict[str, Any]:
    """The template context shared by the report and the trial page."""
    return {
        **summary_context(data),
        "data": data,
        # the trial's own time (its upload), as the visit report names its trials
        "when": trial_time(data.uploaded_at, data.recorded_at, data.timezone, with_day=True),
        "metric_rows": metric_rows(data.analysis),
        "more_metric_rows": metric_rows(data.analysis, primary=False),
        "quality_rows": quality_rows(data),
        "warnings": list(data.analysis.quality.warnings),
        "taps": list(data.analysis.task_cycles),  # the cycles of a task other than tapping
        "events": list(data.analysis.events),
        "plots": report_plots(data),
        "metric_specs": primary_specs(data.task),
        "software_version": software_version(),
    }


def render_report_html(data: ReportData) -> str:
    """The standalone HTML report of one trial (inline CSS and SVG; no external resource)."""

    template = jinja_env.get_template("report.html")
    return template.render(**report_context(data))


def _refusing_fetcher() -> Any:
    """A WeasyPrint URL fetcher that refuses every URL except inline ``data:`` URLs."""
    from weasyprint.urls import URLFetcher

    class RefusingURLFetcher(URLFetcher):  # type: ignore[misc]  # weasyprint has no type hints
        def fetch(self, url: str, headers: Any = None) -> Any:
            if url.startswith("data:"):
                return super().fetch(url, headers)
            raise ValueError(f"the PDF renderer does not fetch URLs (refused {url[:80]!r})")

    return RefusingURLFetcher(allowed_protocols=("data",), fail_on_errors=False)


_INLINE_SVG = re.compile(r"<svg\b([^>]*)>.*?</svg>", re.S)
_ATTRIBUTE = re.compile(r'\s([\w:-]+)="([^"]*)"')


def _svg_image(match: re.Match[str]) -> str:
    attributes = dict(_ATTRIBUTE.findall(match.group(1)))
    body = base64.b64encode(match.group(0).encode("utf-8")).decode("ascii")
    alt = attributes.get("aria-label", "")  # already escaped in the attribute
    css_class = html_lib.escape(attributes.get("class", ""), quote=True)
    return f'<img class="{css_class}" alt="{alt}" src="data:image/svg+xml;base64,{body}">'


def svg_plots_as_images(html: str) -> str:
    """``html`` with every inline ``<svg>`` element replaced by an ``<img>`` of it.

    The image keeps the plot's class and its accessible label (as ``alt``). Inline
    SVG in HTML is laid out by WeasyPrint as part of the page: every one of its
    elements goes through the page's CSS cascade; as an image it is drawn alone.
    """
    return _INLINE_SVG.sub(_svg_image, html)


def html_to_pdf(html: str) -> bytes:
    """A standalone HTML page as PDF bytes (WeasyPrint; no URL is ever fetched).

    Inline SVG plots are drawn as images of themselves (:func:`svg_plots_as_images`).
    """
    import weasyprint

    document = weasyprint.HTML(
        string=svg_plots_as_images(html), base_url=None, url_fetcher=_refusing_fetcher()
    )
    return bytes(document.write_pdf())


def warm_up_pdf() -> bytes:
    """Load WeasyPrint and the fonts a report uses by making a one-line PDF (~0.4 s of CPU
    the first report would otherwise pay); ``bradyscope serve`` calls it once it answers."""
    return html_to_pdf(
        "<!doctype html><html><head><style>body { font-family: 'DejaVu Sans', sans-serif; }"
        "</style></head><body><p>bradyscope <b>0.0</b> <i>mm</i></p></body></html>"
    )


_KEY_TIME = datetime(2000, 1, 1, tzinfo=UTC)


def report_key(data: ReportData) -> str:
    """What the report of ``data`` shows, as a SHA-256 (lower-case hex).

    The report's HTML rendered at a fixed "generated on" time: two reports with
    the same key are the same but for that time, and any change of what the
    report shows (its result revision, a rating, the session, the visit's other
    trials, the time zone, the template or the software) changes the key. The
    key of the PDF report cache (:mod:`app.reports.pdf_cache`).
    """
    html = render_report_html(replace(data, generated_at=_KEY_TIME))
    return hashlib.sha256(html.encode("utf-8")).hexdigest()


def render_report_pdf(data: ReportData) -> bytes:
    """The report of one trial as PDF bytes (WeasyPrint; no URL is ever fetched).

    Made anew at each call (about a second of CPU); the service keeps reports
    made ahead of time in the PDF report cache (:mod:`app.reports.pdf_cache`).
    """
    return html_to_pdf(render_report_html(data))


def visit_context(visit: VisitData) -> dict[str, Any]:
    """The template context of the visit report."""
    details = [
        {
            "data": data,
            "column": summary_column(data),
            "plots": report_plots(data),
            "metric_rows": metric_rows(data.analysis),
            "quality_rows": quality_rows(data),
            "warnings": list(data.analysis.quality.warnings),
            "when": trial_time(data.uploaded_at, data.recorded_at, visit.timezone, with_day=True),
        }
        for group in task_groups(visit.trials)
        for column in group.columns
        for data in visit.trials
        if data.trial_id == column.trial_id
    ]
    return {
        "visit": visit,
        "provenance": provenance_lines(visit.trials),
        "groups": task_groups(visit.trials),
        "details": details,
        # the definitions of each task measured at the visit, in the order of the items
        "metric_definitions": [
            {"task": task, "specs": primary_specs(task)}
            for task in TASKS
            if any(d.task == task for d in visit.trials)
        ],
    }


def provenance_lines(trials: Sequence[ReportData]) -> list[str]:
    """What measured the trials, one line per software, algorithm and calibration.

    ``"trials #10, #11: bradyscope 0.1.0, algorithm 2026.1, calibration id 3 (clinic-A v3)"``.
    """
    groups: dict[str, list[int]] = {}
    for data in trials:
        result, cal = data.analysis, data.calibration
        cal_id = result.calibration_id or (cal.id if cal is not None else None)
        text = (
            f"bradyscope {result.software_version or '(version not recorded)'},"
            f" algorithm {result.algorithm_version or '(not recorded)'},"
            f" calibration id {cal_id if cal_id is not None else '–'}"
        )
        if cal is not None and cal.version:
            text += f" ({cal.rig_name} v{cal.version})"
        groups.setdefault(text, []).append(data.trial_id)
    return [
        f"trial{'s' if len(ids) > 1 else ''} {', '.join(f'#{i}' for i in sorted(ids))}: {text}"
        for text, ids in groups.items()
    ]


def render_visit_html(visit: VisitData) -> str:
    """The visit report as a standalone HTML page: page 1 the visit summary, then each trial.

    A pure function of ``visit``: the same data give the same page (except the
    plots' element ids), so that a signed copy can be stored and reproduced.
    """
    return jinja_env.get_template("visit_report.html").render(**visit_context(visit))


def visit_key(visit: VisitData) -> str:
    """What the visit report of ``visit`` shows, as a SHA-256 (lower-case hex), as
    :func:`report_key` for a trial's: its HTML at a fixed "generated on" time. The key of
    the visit reports in the PDF report cache."""
    html = render_visit_html(replace(visit, generated_at=_KEY_TIME))
    return hashlib.sha256(html.encode("utf-8")).hexdigest()


def render_visit_pdf(visit: VisitData) -> bytes:
    """The visit report as PDF bytes (A4; page 1 is the one-page visit summary)."""
    return html_to_pdf(render_visit_html(visit))

"""The report of one trial: one Jinja2 template rendered as HTML and as PDF.

- :func:`render_report_html` renders ``templates/report.html`` (a standalone
  page: inline CSS and inline SVG plots, no external resource).
- :func:`render_report_pdf` renders the same HTML with WeasyPrint; its URL
  fetcher refuses every URL, so a report can never reach the network.
"""

from __future__ import annotations

from typing import Any

from app.reports.catalogue import METRICS, metric_rows
from app.reports.data import ReportData, quality_rows
from app.reports.figures import report_plots
from app.templating import jinja_env


def report_context(data: ReportData) -> dict[str, Any]:
    """The template context shared by the report and the trial page."""
    return {
        "data": data,
        "metric_rows": metric_rows(data.analysis),
        "more_metric_rows": metric_rows(data.analysis, primary=False),
        "quality_rows": quality_rows(data),
        "warnings": list(data.analysis.quality.warnings),
        "taps": list(data.analysis.taps),
        "events": list(data.analysis.events),
        "plots": report_plots(data),
        "metric_specs": {k: v for k, v in METRICS.items() if v.primary},
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


def render_report_pdf(data: ReportData) -> bytes:
    """The report of one trial as PDF bytes (WeasyPrint; no URL is ever fetched)."""
    import weasyprint

    html = render_report_html(data)
    document = weasyprint.HTML(string=html, base_url=None, url_fetcher=_refusing_fetcher())
    return bytes(document.write_pdf())

"""Time the report path: plots, HTML and PDF of one trial (synthetic 20-tap trial, 9 s at 100 fps).

Prints CPU seconds per step, the ratio of a cached (second) rendering to
the first, and of the PDF with its plots as SVG images (as served) to the same
with inline SVG (as before), measured in the same run. "PDF from the report
cache" is what a request pays when the worker made the report already: the
report's key (its HTML) and the file read (``app.reports.pdf_cache``, in a
temporary folder). Usage::

    python bench/bench_reports.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "app"))

from sample_trial import sample_report_data

from app import exports
from app.reports import figures, rendering
from app.reports.pdf_cache import ReportPdfCache


def _cpu(fn) -> float:
    t0 = time.process_time()
    fn()
    return time.process_time() - t0


@contextlib.contextmanager
def _inline_svg() -> Iterator[None]:
    """The PDF drawn as before: the plots inline SVG in the page, not images of it."""
    convert = rendering.svg_plots_as_images
    rendering.svg_plots_as_images = lambda html: html
    try:
        yield
    finally:
        rendering.svg_plots_as_images = convert


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    data = sample_report_data()
    rendering.render_report_html(data)  # warm imports and the Jinja cache
    folder = tempfile.TemporaryDirectory(prefix="bench-reports-")
    cache = ReportPdfCache(folder.name, max_bytes=2**30)
    rows = []
    for _ in range(args.repeat):
        figures._PLOT_CACHE.clear()
        plots_s = _cpu(lambda: figures.report_plots(data))
        figures._PLOT_CACHE.clear()
        # html_to_pdf(render_report_html(...)): a PDF made anew, past the report cache.
        pdf_cold = _cpu(lambda: rendering.html_to_pdf(rendering.render_report_html(data)))
        html = rendering.render_report_html(data)
        pdf_warm = _cpu(lambda html=html: rendering.html_to_pdf(html))
        with _inline_svg():
            pdf_inline = _cpu(lambda html=html: rendering.html_to_pdf(html))
        html_warm = _cpu(lambda: rendering.render_report_html(data))
        cache.clear()
        pdf = rendering.render_report_pdf(data)
        cache.put(1, data.trial_id, rendering.report_key(data), pdf)
        pdf_again = _cpu(lambda: cache.get(1, data.trial_id, rendering.report_key(data)))
        fhir = _cpu(lambda pdf=pdf: exports.fhir_bundle(data, pdf))
        rows.append((plots_s, pdf_cold, pdf_warm, pdf_inline, pdf_again, html_warm, fhir))
    best = [min(col) for col in zip(*rows, strict=True)]
    names = [
        "4 plots (SVG)",
        "PDF, plots not cached",
        "PDF, plots cached",
        "same, plots as inline SVG",
        "PDF from the report cache",
        "HTML, plots cached",
        "FHIR bundle (validated)",
    ]
    frames = data.markers.frames.size if data.markers is not None else 0
    print(f"trial: {len(data.result['taps'])} taps, {frames} frames; best of {args.repeat} (CPU s)")
    for name, value in zip(names, best, strict=True):
        print(f"  {name:28s} {value:6.3f} s")
    print(f"  cached / uncached PDF ratio  {best[2] / best[1]:6.2f}")
    print(f"  SVG images / inline SVG      {best[2] / best[3]:6.2f}")
    folder.cleanup()


if __name__ == "__main__":
    main()

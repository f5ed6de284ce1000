"""Time the report path: plots, HTML and PDF of one trial (synthetic 20-tap trial, 9 s at 100 fps).

Prints CPU seconds per step and the ratio of a cached (second) rendering to
the first, measured in the same run. Usage::

    python bench/bench_reports.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "app"))

from sample_trial import sample_report_data

from app import exports, reports


def _cpu(fn) -> float:
    t0 = time.process_time()
    fn()
    return time.process_time() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    data = sample_report_data()
    reports.render_report_html(data)  # warm imports and the Jinja cache
    rows = []
    for _ in range(args.repeat):
        reports._PLOT_CACHE.clear()
        plots_s = _cpu(lambda: reports.report_plots(data))
        reports._PLOT_CACHE.clear()
        pdf_cold = _cpu(lambda: reports.render_report_pdf(data))
        pdf_warm = _cpu(lambda: reports.render_report_pdf(data))
        html_warm = _cpu(lambda: reports.render_report_html(data))
        pdf = reports.render_report_pdf(data)
        fhir = _cpu(lambda pdf=pdf: exports.fhir_bundle(data, pdf))
        rows.append((plots_s, pdf_cold, pdf_warm, html_warm, fhir))
    best = [min(col) for col in zip(*rows, strict=True)]
    names = [
        "4 plots (SVG)",
        "PDF, plots not cached",
        "PDF, plots cached",
        "HTML, plots cached",
        "FHIR bundle (validated)",
    ]
    frames = data.markers.frames.size if data.markers is not None else 0
    print(f"trial: {len(data.result['taps'])} taps, {frames} frames; best of {args.repeat} (CPU s)")
    for name, value in zip(names, best, strict=True):
        print(f"  {name:28s} {value:6.3f} s")
    print(f"  cached / uncached PDF ratio  {best[2] / best[1]:6.2f}")


if __name__ == "__main__":
    main()

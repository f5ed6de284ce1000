"""The trial report, in parts that depend on each other in this order only.

- :mod:`app.reports.result`: ``result.json`` read once, typed (:class:`~app.reports.result.TrialResult`).
- :mod:`app.reports.catalogue`: the metrics (label, unit, UCUM code, decimals, definition).
- :mod:`app.reports.data`: :class:`~app.reports.data.ReportData`, what one report shows,
  and the lines derived from it (quality panel, events).
- :mod:`app.reports.figures`: its plots as inline SVG (cached per result).
- :mod:`app.reports.rendering`: the HTML and PDF report from one template.
- :mod:`app.reports.pdf_cache`: PDF reports made ahead of time, kept on disk (by content).

Loading a report from the database is a use case: ``app.services.results``.
"""

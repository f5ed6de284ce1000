"""Patients' trend plots drawn once, kept on disk in ``<data dir>/cache/trends/``.

A trend plot (:func:`app.trends.trend_plot`) takes about 0.1 s of matplotlib,
and a patient page shows one per trend metric of each task measured, so its
first view took 0.6 s on the demo patient (``bench/bench_pages.py``). The
worker draws a patient's plots when a trial's result changes (the
``report_pdf`` job, :mod:`app.handlers`) and the page reads them from here;
a plot missing here (a session's date or medication state changed, a trial
deleted) is drawn by the page and kept. A file is named after what it shows::

    <patient id>-<key>.svg

``key`` is :func:`app.trends.trend_key`: the SHA-256 of the plot's points,
words and units and of the plotting code, so a stale plot is never found.
Bounds, erasure, restore and several processes as in :mod:`app.reports.file_cache`
(:data:`KEEP_PER_PATIENT` files a patient; the whole cache at most
``BRADYSCOPE_REPORT_CACHE_MB``, apart from the PDF reports').
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from app.reports.file_cache import PatientFileCache
from app.storage import Storage
from app.trends import TrendPoint, trend_key, trend_plot

log = logging.getLogger(__name__)

KEEP_PER_PATIENT = 64
"""Files a patient keeps: the plots of their page (up to 5 tasks x 4 trend metrics) and
those of a few earlier states of it."""


class TrendSvgCache(PatientFileCache):
    """The trend plots kept in ``directory`` (created on the first write)."""

    suffix = ".svg"

    @classmethod
    def of(cls, storage: Storage) -> TrendSvgCache:
        """The cache of ``storage``'s data directory, with its bound."""
        return cls(storage.trend_cache_dir, max_bytes=storage.report_cache_bytes)

    def path(self, patient_id: int, key: str) -> Path:
        """Where the plot of ``patient_id`` with content ``key`` is kept."""
        self.check_id("patient_id", patient_id)
        self.check_key(key)
        return self.directory / f"{patient_id}-{key}.svg"

    def get(self, patient_id: int, key: str) -> str | None:
        """The kept plot (SVG text), or None; a file found counts as just used."""
        body = self.read(self.path(patient_id, key))
        return None if body is None else body.decode("utf-8")

    def put(self, patient_id: int, key: str, svg: str) -> Path:
        """Keep ``svg`` as the patient's plot with content ``key``; returns its path.

        Then the patient's files beyond :data:`KEEP_PER_PATIENT` and, past
        ``max_bytes``, the least recently used files of the cache are removed.
        """
        if not svg.lstrip().startswith("<svg"):
            raise ValueError("only an SVG plot is kept in the trend cache")
        final = self.path(patient_id, key)
        self.write(final, svg.encode("utf-8"))
        self.keep_newest(f"{patient_id}-*.svg", KEEP_PER_PATIENT)
        self.trim()
        return final


def cached_trend_plot(
    cache: TrendSvgCache,
    patient_id: int,
    points: Sequence[TrendPoint],
    *,
    label: str,
    unit: str,
    limb: str,
) -> tuple[str, bool]:
    """The patient's trend plot of ``points`` (:func:`app.trends.trend_plot`, counts on whole
    numbers): from ``cache``, or drawn now and kept there. Returns the SVG and whether it
    was drawn now.

    A plot that cannot be kept (a full disk) is still returned, with a warning in the log:
    the page shows it, the next view draws it again.
    """
    integer = unit == "count"
    key = trend_key(points, label=label, unit=unit, integer=integer, limb=limb)
    kept = cache.get(patient_id, key)
    if kept is not None:
        return kept, False
    svg = trend_plot(points, label=label, unit=unit, integer=integer, limb=limb)
    try:
        cache.put(patient_id, key, svg)
    except OSError as exc:
        log.warning(
            "a trend plot of patient %d was not kept in %s: %s",
            patient_id,
            cache.directory,
            exc.strerror or exc,
        )
    return svg, True


__all__ = ["KEEP_PER_PATIENT", "TrendSvgCache", "cached_trend_plot"]

"""The plots of a report as inline SVG, drawn once per result revision.

The worker draws a new revision's plots when it stores the revision (and a
correction when it is made) and keeps them in storage as a small JSON
document (:func:`plots_document`, ``Result.plots_path``); pages, reports and
FHIR exports read them from there (``ReportData.plots``). Results stored
before that, or whose document was drawn by other plotting code, are drawn
on demand and kept in a small in-process cache.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import math
import sys
import threading
from collections import OrderedDict
from collections.abc import Mapping
from typing import Any

import numpy as np

from app import plots
from app.reports.data import ReportData
from app.reports.result import TrialResult, read_result
from core.markers_csv import MarkerTable

PLOTS_FORMAT = "bradyscope.plots/1"
PLOT_NAMES = ("aperture", "amplitude", "velocity", "paths")

_PLOT_CACHE: OrderedDict[str, dict[str, str]] = OrderedDict()
_PLOT_CACHE_SIZE = 16
_plot_cache_lock = threading.Lock()


def _plot_key(data: ReportData) -> str:
    digest = hashlib.sha256()
    digest.update(json.dumps(data.result, sort_keys=True, default=str).encode())
    if data.markers is not None:
        digest.update(np.ascontiguousarray(data.markers.positions_mm).tobytes())
        digest.update("".join(data.markers.status.ravel().tolist()).encode())
    return digest.hexdigest()


def report_plots(data: ReportData) -> dict[str, str]:
    """The trial's plots as inline SVG: ``aperture``, ``amplitude``, ``velocity``, ``paths``.

    ``data.plots`` when the revision's stored plots were read; otherwise drawn
    and kept in a small in-process cache (a page, its PDF and its FHIR export
    then share one drawing).
    """
    if data.plots is not None:
        return dict(data.plots)
    key = _plot_key(data)
    with _plot_cache_lock:
        cached = _PLOT_CACHE.get(key)
        if cached is not None:
            _PLOT_CACHE.move_to_end(key)
            return dict(cached)
    out = draw_plots(data.analysis, data.markers)
    with _plot_cache_lock:
        _PLOT_CACHE[key] = out
        while len(_PLOT_CACHE) > _PLOT_CACHE_SIZE:
            _PLOT_CACHE.popitem(last=False)
    return dict(out)


def _plots_style() -> str:
    """What the drawing depends on besides the data: the plotting code and matplotlib.

    A stored plots document drawn by other code (an upgrade) is drawn again.
    """
    from importlib.metadata import version

    digest = hashlib.sha256(version("matplotlib").encode())
    for module in (plots, sys.modules[__name__]):
        digest.update(inspect.getsource(module).encode())
    return digest.hexdigest()[:16]


_STYLE: list[str] = []  # computed once, on first use


def plots_style() -> str:
    """A short key of the plotting code (see :func:`_plots_style`)."""
    if not _STYLE:
        _STYLE.append(_plots_style())
    return _STYLE[0]


def plots_document(result: Mapping[str, Any], markers: MarkerTable | None) -> str:
    """The plots of one result revision as a JSON document, to be stored with it.

    ``result`` is the revision's ``result.json`` and ``markers`` its
    ``markers.csv`` as read back from storage (what a page would draw from).
    """
    drawn = draw_plots(read_result(result), markers)
    return json.dumps({"format": PLOTS_FORMAT, "style": plots_style(), "plots": drawn})


def read_plots_document(text: str) -> dict[str, str] | None:
    """The plots of a stored :func:`plots_document`; None when drawn by other plotting
    code, or not such a document (then they are drawn again)."""
    try:
        doc = json.loads(text)
    except ValueError:
        return None
    if not isinstance(doc, dict) or doc.get("format") != PLOTS_FORMAT:
        return None
    if doc.get("style") != plots_style():
        return None
    drawn = doc.get("plots")
    if not isinstance(drawn, dict) or set(drawn) != set(PLOT_NAMES):
        return None
    if not all(isinstance(v, str) for v in drawn.values()):
        return None
    return {str(k): str(v) for k, v in drawn.items()}


def _aperture_series(
    markers: MarkerTable | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(time_s, aperture_mm, interpolated) of the trial, or None without thumb and index."""
    m = markers
    if m is None or not {"thumb", "index"} <= set(m.labels):
        return None
    aperture = plots.aperture_from_positions(m.positions_mm, labels=m.labels)
    i_t, i_i = m.labels.index("thumb"), m.labels.index("index")
    interp = (m.status[:, i_t] == "interpolated") | (m.status[:, i_i] == "interpolated")
    return m.time_s, aperture, interp


def _aperture(data: ReportData) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    return _aperture_series(data.markers)


def _aperture_svg(
    analysis: TrialResult, markers: MarkerTable | None, *, top_mm: float | None = None
) -> str:
    series = _aperture_series(markers)
    if series is None:
        return plots.aperture_plot(np.zeros(0), np.zeros(0))
    time_s, aperture, interp = series
    return plots.aperture_plot(
        time_s,
        aperture,
        taps=analysis.taps,
        events=analysis.events,
        interpolated=interp,
        top_mm=top_mm,
    )


def _amplitude_svg(analysis: TrialResult, *, top_mm: float | None = None) -> str:
    return plots.tap_amplitude_plot(
        analysis.taps,
        decrement_mm_per_tap=analysis.metric("amplitude_decrement_mm_per_tap"),
        top_mm=top_mm,
    )


def draw_plots(analysis: TrialResult, markers: MarkerTable | None) -> dict[str, str]:
    """Draw the four plots of one result (``aperture``, ``amplitude``, ``velocity``, ``paths``).

    ``markers`` None (the file is gone) draws the trajectory plots empty.
    """
    out: dict[str, str] = {
        "aperture": _aperture_svg(analysis, markers),
        "amplitude": _amplitude_svg(analysis),
    }
    m = markers
    if m is not None and {"thumb", "index"} <= set(m.labels):
        keep = [i for i, name in enumerate(m.labels) if name in ("thumb", "index")]
        out["paths"] = plots.fingertip_paths_plot(
            m.positions_mm[:, keep], labels=[m.labels[i] for i in keep]
        )
    else:
        out["paths"] = plots.fingertip_paths_plot(
            np.full((0, 2, 3), np.nan), labels=["thumb", "index"]
        )
    out["velocity"] = plots.velocity_plot(analysis.taps)
    return out


def comparison_plots(
    first: ReportData, second: ReportData
) -> tuple[dict[str, str], dict[str, str]]:
    """Aperture and amplitude plots of two trials drawn on the same scales (mm).

    Returns
    -------
    (plots of ``first``, plots of ``second``), each with ``aperture`` and ``amplitude``.
    """

    def peak(values: list[float]) -> float | None:
        finite = [v for v in values if math.isfinite(v)]
        return max(finite) if finite else None

    apertures = [_aperture(d) for d in (first, second)]
    top_aperture = peak(
        [float(np.nanmax(a[1])) for a in apertures if a is not None and np.isfinite(a[1]).any()]
    )
    top_amplitude = peak(first.analysis.tap_amplitudes_mm + second.analysis.tap_amplitudes_mm)
    out = []
    for d in (first, second):
        out.append(
            {
                "aperture": _aperture_svg(
                    d.analysis,
                    d.markers,
                    top_mm=None if top_aperture is None else 1.12 * top_aperture,
                ),
                "amplitude": _amplitude_svg(
                    d.analysis, top_mm=None if top_amplitude is None else 1.2 * top_amplitude
                ),
            }
        )
    return out[0], out[1]

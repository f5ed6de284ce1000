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
import json
import math
import sys
import threading
from collections import OrderedDict
from collections.abc import Mapping
from typing import Any

import numpy as np

from app import plots, quantities
from app.quantities import quantity_of
from app.reports.data import ReportData
from app.reports.result import TrialResult, read_result
from core.markers_csv import MarkerTable
from core.protocols import cycle_signal, marker_columns, protocol_for
from core.tasks import Task, parse_task, task_key

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
    return plots.code_key((plots, quantities, sys.modules[__name__]))[:16]


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


def signal_series(
    markers: MarkerTable | None, task: Task | str, *, side: str | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(time_s, signal, interpolated) of a trial: the task's cycle signal per frame, raw
    (:func:`core.protocols.cycle_signal`, in its unit), and the frames where one of its
    markers was filled in; None without the protocol's markers.

    ``side`` gives pronation–supination's direction of supination (None: right).
    """
    if markers is None:
        return None
    try:
        cols = marker_columns(markers.labels, task)
    except ValueError:
        return None
    values = cycle_signal(task, markers.positions_mm[:, cols], side=side or "right").values
    interp = np.any(markers.status[:, cols] == "interpolated", axis=1)
    return markers.time_s, values, interp


def _signal(data: ReportData) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    return signal_series(data.markers, data.analysis.task, side=data.analysis.side)


def _aperture_svg(
    analysis: TrialResult, markers: MarkerTable | None, *, top: float | None = None
) -> str:
    quantity = quantity_of(analysis.task)
    series = signal_series(markers, analysis.task, side=analysis.side)
    if series is None:
        return plots.aperture_plot(np.zeros(0), np.zeros(0), quantity=quantity)
    time_s, values, interp = series
    return plots.aperture_plot(
        time_s,
        values,
        taps=analysis.task_cycles,
        events=analysis.events,
        interpolated=interp,
        top=top,
        quantity=quantity,
    )


def _amplitude_svg(analysis: TrialResult, *, top: float | None = None) -> str:
    task = parse_task(analysis.task)
    return plots.tap_amplitude_plot(
        analysis.task_cycles,
        decrement_per_tap=analysis.metric(task_key("amplitude_decrement_mm_per_tap", task)),
        top=top,
        quantity=quantity_of(task),
    )


def draw_plots(analysis: TrialResult, markers: MarkerTable | None) -> dict[str, str]:
    """Draw the four plots of one result (``aperture``, ``amplitude``, ``velocity``, ``paths``)
    in its task's quantity (the aperture plot shows the task's cycle signal).

    ``markers`` None (the file is gone) draws the trajectory plots empty.
    """
    quantity = quantity_of(analysis.task)
    labels = protocol_for(analysis.task).labels
    out: dict[str, str] = {
        "aperture": _aperture_svg(analysis, markers),
        "amplitude": _amplitude_svg(analysis),
    }
    m = markers
    if m is not None and set(labels) <= set(m.labels):
        cols = marker_columns(m.labels, analysis.task)
        out["paths"] = plots.fingertip_paths_plot(
            m.positions_mm[:, cols], labels=labels, quantity=quantity
        )
    else:
        out["paths"] = plots.fingertip_paths_plot(
            np.full((0, len(labels), 3), np.nan), labels=labels, quantity=quantity
        )
    out["velocity"] = plots.velocity_plot(analysis.task_cycles, quantity=quantity)
    return out


def comparison_plots(
    first: ReportData, second: ReportData
) -> tuple[dict[str, str], dict[str, str]]:
    """Signal and amplitude plots of two trials drawn on the same scales (mm, or degrees);
    trials of two different tasks (two quantities) each keep their own.

    Returns
    -------
    (plots of ``first``, plots of ``second``), each with ``aperture`` and ``amplitude``.
    """

    def peak(values: list[float]) -> float | None:
        finite = [v for v in values if math.isfinite(v)]
        return max(finite) if finite else None

    out = []
    if parse_task(first.analysis.task) is not parse_task(second.analysis.task):
        for d in (first, second):
            out.append({"aperture": _aperture_svg(d.analysis, d.markers)})
            out[-1]["amplitude"] = _amplitude_svg(d.analysis)
        return out[0], out[1]
    signals = [_signal(d) for d in (first, second)]
    top_signal = peak(
        [float(np.nanmax(a[1])) for a in signals if a is not None and np.isfinite(a[1]).any()]
    )
    top_amplitude = peak(first.analysis.cycle_amplitudes + second.analysis.cycle_amplitudes)
    for d in (first, second):
        out.append(
            {
                "aperture": _aperture_svg(
                    d.analysis,
                    d.markers,
                    top=None if top_signal is None else 1.12 * top_signal,
                ),
                "amplitude": _amplitude_svg(
                    d.analysis,
                    top=None if top_amplitude is None else plots.HEADROOM * top_amplitude,
                ),
            }
        )
    return out[0], out[1]

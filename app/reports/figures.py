"""The plots of a report as inline SVG, drawn once per result (a small in-process cache)."""

from __future__ import annotations

import hashlib
import json
import math
import threading
from collections import OrderedDict

import numpy as np

from app import plots
from app.reports.data import ReportData

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

    Drawn once per result and kept in a small in-process cache (a page, its
    PDF and its FHIR export then share one drawing).
    """
    key = _plot_key(data)
    with _plot_cache_lock:
        cached = _PLOT_CACHE.get(key)
        if cached is not None:
            _PLOT_CACHE.move_to_end(key)
            return dict(cached)
    out = _draw_plots(data)
    with _plot_cache_lock:
        _PLOT_CACHE[key] = out
        while len(_PLOT_CACHE) > _PLOT_CACHE_SIZE:
            _PLOT_CACHE.popitem(last=False)
    return dict(out)


def _aperture(data: ReportData) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(time_s, aperture_mm, interpolated) of the trial, or None without thumb and index."""
    m = data.markers
    if m is None or not {"thumb", "index"} <= set(m.labels):
        return None
    aperture = plots.aperture_from_positions(m.positions_mm, labels=m.labels)
    i_t, i_i = m.labels.index("thumb"), m.labels.index("index")
    interp = (m.status[:, i_t] == "interpolated") | (m.status[:, i_i] == "interpolated")
    return m.time_s, aperture, interp


def _aperture_svg(data: ReportData, *, top_mm: float | None = None) -> str:
    series = _aperture(data)
    if series is None:
        return plots.aperture_plot(np.zeros(0), np.zeros(0))
    time_s, aperture, interp = series
    return plots.aperture_plot(
        time_s,
        aperture,
        taps=data.analysis.taps,
        events=data.analysis.events,
        interpolated=interp,
        top_mm=top_mm,
    )


def _amplitude_svg(data: ReportData, *, top_mm: float | None = None) -> str:
    return plots.tap_amplitude_plot(
        data.analysis.taps,
        decrement_mm_per_tap=data.analysis.metric("amplitude_decrement_mm_per_tap"),
        top_mm=top_mm,
    )


def _draw_plots(data: ReportData) -> dict[str, str]:
    out: dict[str, str] = {"aperture": _aperture_svg(data), "amplitude": _amplitude_svg(data)}
    m = data.markers
    if m is not None and {"thumb", "index"} <= set(m.labels):
        keep = [i for i, name in enumerate(m.labels) if name in ("thumb", "index")]
        out["paths"] = plots.fingertip_paths_plot(
            m.positions_mm[:, keep], labels=[m.labels[i] for i in keep]
        )
    else:
        out["paths"] = plots.fingertip_paths_plot(
            np.full((0, 2, 3), np.nan), labels=["thumb", "index"]
        )
    out["velocity"] = plots.velocity_plot(data.analysis.taps)
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
                    d, top_mm=None if top_aperture is None else 1.12 * top_aperture
                ),
                "amplitude": _amplitude_svg(
                    d, top_mm=None if top_amplitude is None else 1.2 * top_amplitude
                ),
            }
        )
    return out[0], out[1]

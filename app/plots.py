"""Plots of one trial, drawn with matplotlib as inline SVG.

Every function returns an ``<svg>`` element as a string, ready to be placed in
an HTML page or in the report (WeasyPrint renders inline SVG in the PDF).
Text stays text (``svg.fonttype = "none"``) so the PDF's words are searchable,
and element ids are prefixed per plot so that several plots can share a page.

Lengths are in mm, angles in degrees, times in s, as everywhere in bradyscope.
What a plot of cycles shows (the task's signal, its unit, its words and the
result.json keys of its cycles) is a :class:`app.quantities.CycleQuantity`,
built from the task's definition; the default is finger tapping's. The set-up shared with a patient's trends (:mod:`app.trends`) is public here:
:data:`COLOURS`, :data:`RC`, :func:`new_figure`, :func:`draw_empty`, :func:`to_svg`.
"""

from __future__ import annotations

import hashlib
import inspect
import io
import itertools
import math
import re
import secrets
from collections.abc import Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from app.quantities import TAPPING, CycleQuantity

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

# matplotlib (~0.5 s to import) is imported on the first drawing, not with the web
# application: the worker draws a result's plots once and the pages read them.

# A calm, colour-blind-safe palette (Okabe–Ito) used by the pages too.
COLOURS = {
    "aperture": "#0b5d8c",
    "interpolated": "#9aa5b1",
    "tap": "#0b5d8c",
    "hesitation": "#e69f00",
    "halt": "#c0392b",
    "gap": "#7b8794",
    "opening": "#009e73",
    "closing": "#cc79a7",
    "thumb": "#d55e00",
    "index": "#0072b2",
    "left": "#0072b2",
    "right": "#d55e00",
    "trend": "#555555",
}

RC: Any = {  # matplotlib rc parameters (typed as Any: its stubs want Literal keys)
    "svg.fonttype": "none",
    "svg.hashsalt": "bradyscope",
    "font.family": "DejaVu Sans",
    "font.size": 9.0,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "axes.grid": True,
    "grid.color": "#e3e7eb",
    "grid.linewidth": 0.6,
    "axes.edgecolor": "#6b7785",
    "axes.labelcolor": "#1f2933",
    "xtick.color": "#3e4c59",
    "ytick.color": "#3e4c59",
    "legend.frameon": False,
    "legend.fontsize": 8.0,
}

# Element ids: the plot's name and a number unique to this drawing. Plots drawn by other
# processes (the worker stores a revision's plots) share pages and reports, so the
# numbers start at a random point per process instead of 0.
_counter = itertools.count(secrets.randbelow(10**12) * 1000)
MAX_PATH_POINTS = 400
#: Colours of the markers in the order of their task's labels, with their names for captions
#: (finger tapping's thumb and index are the first two, as in :data:`COLOURS`).
HEADROOM = 1.35
"""The amplitude plot's height over its tallest bar: room for the legend above the bars."""

MARKER_COLOURS = (("#d55e00", "orange"), ("#0072b2", "blue"), ("#009e73", "green"))


@dataclass(frozen=True)
class PlotEvent:
    """An interruption of the tapping rhythm to be marked on the aperture plot.

    Attributes
    ----------
    kind : ``"hesitation"``, ``"halt"`` or ``"gap"`` (a stretch without usable signal).
    t_start_s, t_end_s : float
        Start and end of the pause in seconds from the first frame.
    """

    kind: str
    t_start_s: float
    t_end_s: float


_BACKEND_SET: list[bool] = []


def plot_rc() -> AbstractContextManager[None]:
    """matplotlib's rc context of every plot (:data:`RC`); imports matplotlib (Agg) on first use."""
    import matplotlib

    if not _BACKEND_SET:
        matplotlib.use("Agg")
        _BACKEND_SET.append(True)
    return matplotlib.rc_context(RC)


def new_figure(width_in: float, height_in: float) -> Figure:
    from matplotlib.figure import Figure

    with plot_rc():
        fig = Figure(figsize=(width_in, height_in), layout="constrained")
    return fig


_ID_RE = re.compile(r'id="([^"]+)"')


def _escape(text: str) -> str:
    return (
        text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")
    )


def code_key(modules: Sequence[ModuleType]) -> str:
    """SHA-256 (hex) of what plots drawn by ``modules`` depend on besides their data: the
    modules' source and matplotlib's version (from the package's metadata: importing
    matplotlib would cost a page whose plots are all kept ~0.3 s). Kept plots whose key
    differs were drawn by other code, and are drawn again."""
    from importlib.metadata import version

    digest = hashlib.sha256(version("matplotlib").encode())
    for module in modules:
        digest.update(inspect.getsource(module).encode())
    return digest.hexdigest()


def to_svg(fig: Figure, *, title: str, name: str, hover: Mapping[str, str] | None = None) -> str:
    """Serialise ``fig`` as an inline ``<svg>`` with unique ids and an accessible title.

    ``hover`` maps an artist's gid to the text a browser shows when the pointer
    rests on it (an SVG ``<title>`` inside that artist's group).
    """
    buf = io.StringIO()
    with plot_rc():
        fig.savefig(buf, format="svg", metadata={"Date": None, "Creator": None})
    svg = buf.getvalue()
    for gid, text in (hover or {}).items():
        svg = svg.replace(f'<g id="{gid}">', f'<g id="{gid}"><title>{_escape(text)}</title>', 1)
    start = svg.find("<svg")
    if start < 0:  # pragma: no cover - matplotlib always writes an <svg>
        raise ValueError("matplotlib did not produce an SVG document")
    svg = svg[start:]
    prefix = f"{name}{next(_counter)}-"
    ids = set(_ID_RE.findall(svg))
    for old in sorted(ids, key=len, reverse=True):
        svg = svg.replace(f'id="{old}"', f'id="{prefix}{old}"')
        svg = svg.replace(f"#{old})", f"#{prefix}{old})")
        svg = svg.replace(f'href="#{old}"', f'href="#{prefix}{old}"')
    # Let the SVG scale with its container; keep the viewBox for the aspect ratio.
    svg = re.sub(r'<svg([^>]*?)\swidth="[^"]*"\sheight="[^"]*"', r"<svg\1", svg, count=1)
    safe_title = (
        title.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")
    )
    svg = svg.replace(
        "<svg",
        f'<svg role="img" aria-label="{safe_title}" class="plot plot-{name}" data-plot="{name}"',
        1,
    )
    head_end = svg.find(">") + 1
    svg = svg[:head_end] + f"<title>{safe_title}</title>" + svg[head_end:]
    return svg


def _value(tap: Mapping[str, Any], key: str) -> float:
    """A tap's number, NaN when absent or null."""
    v = tap.get(key)
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else math.nan


def draw_empty(fig: Figure, message: str) -> None:
    ax = fig.add_subplot()
    ax.set_axis_off()
    ax.text(0.5, 0.5, message, ha="center", va="center", color="#52606d", transform=ax.transAxes)


def _signal_line(
    ax: Axes,
    t: NDArray[np.float64],
    a: NDArray[np.float64],
    interpolated: ArrayLike | None,
    name: str,
) -> None:
    """The signal over time, gap-filled stretches in grey."""
    measured = a.copy()
    if interpolated is not None:
        interp = np.asarray(interpolated, dtype=bool)
        if interp.shape != t.shape:
            raise ValueError(f"interpolated must be (T,)={t.shape}, got {interp.shape}")
        gap = a.copy()
        # Keep one neighbour on each side so interpolated stretches join the line.
        grown = interp | np.roll(interp, 1) | np.roll(interp, -1)
        gap[~grown] = np.nan
        measured[interp] = np.nan
        if interp.any():
            ax.plot(t, gap, color=COLOURS["interpolated"], lw=1.2, label="interpolated")
    ax.plot(t, measured, color=COLOURS["aperture"], lw=1.2, label=name)


def _tap_marks(
    ax: Axes,
    t: NDArray[np.float64],
    a: NDArray[np.float64],
    taps: Sequence[Mapping[str, Any]],
    quantity: CycleQuantity,
) -> None:
    """Each tap's (cycle's) peak as a numbered dot, its start as a faint tick."""
    word = quantity.cycle
    t_peak = np.array([_value(tp, quantity.peak_key) for tp in taps])
    a_peak = np.interp(t_peak, t[np.isfinite(a)], a[np.isfinite(a)])
    a_peak[~np.isfinite(t_peak)] = np.nan
    ax.plot(t_peak, a_peak, "o", ms=3.5, color=COLOURS["tap"], label=f"{word} peak")
    for tp, x, y in zip(taps, t_peak, a_peak, strict=True):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        ax.annotate(
            str(int(tp.get("index", 0)) + 1),
            (x, y),
            xytext=(0, 3),
            textcoords="offset points",
            ha="center",
            fontsize=7.0,  # >= 9 CSS px where the page draws the plot smallest (768 px)
            color="#3e4c59",
        )
    starts = [_value(tp, "t_start_s") for tp in taps]
    for k, start in enumerate(s for s in starts if math.isfinite(s)):
        # The legend names the thin grey lines once ("tap start").
        ax.axvline(
            start, color="#cbd2d9", lw=0.5, zorder=0, label=f"{word} start" if k == 0 else None
        )


def aperture_plot(
    time_s: ArrayLike,
    values: ArrayLike,
    *,
    taps: Sequence[Mapping[str, Any]] = (),
    events: Sequence[PlotEvent] = (),
    interpolated: ArrayLike | None = None,
    top: float | None = None,
    quantity: CycleQuantity = TAPPING,
) -> str:
    """The task's cycle signal over time (finger tapping: the aperture, the thumb–index
    distance) with taps (cycles), hesitations and halts marked.

    Parameters
    ----------
    time_s : (T,) float
        Time of each frame in seconds.
    values : (T,) float
        The signal in ``quantity.unit`` (mm, or degrees); NaN where a marker is missing.
    taps : sequence of tap (cycle) dicts (``result.json`` ``taps`` or ``cycles``)
        Each one's turn (``quantity.peak_key``) is marked with a dot and its
        number; its start ``t_start_s`` with a faint tick.
    events : sequence of PlotEvent
        Hesitations (shaded amber) and halts (shaded red).
    interpolated : (T,) bool, optional
        Frames whose position was gap-filled; drawn in grey.
    top : float, optional
        Upper end of the signal axis (``quantity.unit``), to draw two trials on one scale.
    quantity : CycleQuantity
        What the signal is (axis label, unit, words, cycle keys).

    Returns
    -------
    str
        An ``<svg>`` element.
    """
    q = quantity
    t = np.asarray(time_s, dtype=np.float64)
    a = np.asarray(values, dtype=np.float64)
    if t.ndim != 1 or a.shape != t.shape:
        raise ValueError(f"time_s and values must be (T,) arrays, got {t.shape}, {a.shape}")
    fig = new_figure(7.2, 2.6)
    if t.size == 0 or not np.isfinite(a).any():
        draw_empty(fig, f"No {q.title.lower()} could be measured in this trial.")
        return to_svg(fig, title=f"{q.title} over time: no data", name="aperture")
    with plot_rc():
        ax = fig.add_subplot()
        for ev in events:
            colour = COLOURS.get(ev.kind, COLOURS["hesitation"])
            ax.axvspan(ev.t_start_s, ev.t_end_s, color=colour, alpha=0.22, lw=0)
        _signal_line(ax, t, a, interpolated, q.title.lower())
        if taps:
            _tap_marks(ax, t, a, taps, q)
        kinds = {ev.kind for ev in events}
        if "hesitation" in kinds:
            ax.fill_between([], [], color=COLOURS["hesitation"], alpha=0.3, label="hesitation")
        if "halt" in kinds:
            ax.fill_between([], [], color=COLOURS["halt"], alpha=0.3, label="halt")
        if "gap" in kinds:
            ax.fill_between([], [], color=COLOURS["gap"], alpha=0.3, label="no signal")
        ax.set_xlabel("time (s)")
        ax.set_ylabel(f"{q.signal} ({q.unit})")
        ax.set_xlim(float(t[0]), float(t[-1]))
        upper = float(np.nanmax(a)) * 1.12 if top is None else float(top)
        ax.set_ylim(bottom=min(0.0, float(np.nanmin(a))), top=upper)
        fig.legend(loc="outside upper right", ncols=5)
    n_h = sum(ev.kind == "hesitation" for ev in events)
    n_halt = sum(ev.kind == "halt" for ev in events)
    title = (
        f"{q.title} over time: {len(taps)} {q.cycle}s, {n_h} hesitation(s), {n_halt} halt(s) marked"
    )
    return to_svg(fig, title=title, name="aperture")


def tap_amplitude_plot(
    taps: Sequence[Mapping[str, Any]],
    *,
    decrement_per_tap: float | None = None,
    top: float | None = None,
    quantity: CycleQuantity = TAPPING,
) -> str:
    """Amplitude of each tap (cycle) with the decrement line.

    Parameters
    ----------
    taps : sequence of tap (cycle) dicts with ``quantity.amplitude_key``.
    decrement_per_tap : float, optional
        Slope of the decrement line (``amplitude_decrement_per_cycle``, ``quantity.unit``
        per tap), through the mean measured tap. None (the metrics did not assess it): no
        line, the legend says so; a slope is never fitted here.
    top : float, optional
        Upper end of the amplitude axis (``quantity.unit``), to draw two trials on one scale.
    quantity : CycleQuantity
        The unit, words and keys of the task's cycles.
    """
    q = quantity
    fig = new_figure(3.6, 2.6)
    amp = np.array([_value(tp, q.amplitude_key) for tp in taps], dtype=np.float64)
    if amp.size == 0 or not np.isfinite(amp).any():
        draw_empty(fig, f"No {q.cycle}s were found.")
        return to_svg(
            fig, title=f"{q.cycle.capitalize()} amplitude: no {q.cycle}s", name="amplitude"
        )
    n = _numbers(taps)
    with plot_rc():
        ax = fig.add_subplot()
        # Unreliable taps (peak or closure on filled-in frames) are drawn pale:
        # the metrics leave them out of amplitude statistics.
        reliable = np.array([tp.get("reliable", True) is not False for tp in taps])
        ok = np.isfinite(amp)
        ax.bar(
            n[reliable & ok], amp[reliable & ok], width=0.7, color="#9ec5e0",
            edgecolor=COLOURS["aperture"], lw=0.6,
        )  # fmt: skip
        if (~reliable & ok).any():
            ax.bar(
                n[~reliable & ok], amp[~reliable & ok], width=0.7, color="#eef2f5",
                edgecolor="#9aa5b1", lw=0.6, hatch="//", label=f"unreliable {q.cycle}",
            )  # fmt: skip
        fit = reliable & ok if (reliable & ok).any() else ok
        slope = decrement_per_tap
        if slope is None or not math.isfinite(slope):  # as the metrics table says
            said = ", decrement not assessable"
            ax.plot([], [], " ", label=said[2:])  # a legend line, nothing drawn
        else:
            said = f" with decrement line {slope:+.2f} {q.unit} per {q.cycle}"
            intercept = float(np.mean(amp[fit]) - slope * np.mean(n[fit]))
            ax.plot(
                n, intercept + slope * n, color=COLOURS["halt"], lw=1.4,
                # over all taps; the summary beside it gives the first 10 taps'
                label=f"decrement {slope:+.2f} {q.unit}/{q.cycle}"
                + (f", all {amp.size} {q.cycle}s" if amp.size > 10 else ""),
            )  # fmt: skip
        ax.set_xlabel(f"{q.cycle} number")
        ax.set_ylabel(f"amplitude ({q.unit})")
        ax.set_ylim(0, float(np.nanmax(amp)) * HEADROOM if top is None else float(top))
        # above the bars, in the headroom (lower left it hid the first bars' bases)
        ax.legend(loc="upper center", ncols=2, facecolor="white", frameon=True, edgecolor="none")
        ax.set_xticks(_ticks(n))
    return to_svg(
        fig,
        title=f"Amplitude of {amp.size} {q.cycle}s{said}",
        name="amplitude",
    )


def _numbers(taps: Sequence[Mapping[str, Any]]) -> NDArray[np.float64]:
    """The taps' numbers in the recording, from 1, as the taps table gives them."""
    index = [tp.get("index") for tp in taps]
    if all(isinstance(i, int) for i in index) and len(set(index)) == len(index):
        return np.array(index, dtype=np.float64) + 1.0
    return np.arange(1, len(taps) + 1, dtype=np.float64)


def _ticks(n: NDArray[np.float64]) -> NDArray[np.float64]:
    return n[:: max(1, math.ceil(n.size / 10))]


def velocity_plot(taps: Sequence[Mapping[str, Any]], *, quantity: CycleQuantity = TAPPING) -> str:
    """Peak velocity of each tap (cycle) in its two halves (opening and closing, mm/s;
    supination and pronation, deg/s...)."""
    q = quantity
    towards, back = q.phases
    fig = new_figure(3.6, 2.6)
    if not taps:
        draw_empty(fig, f"No {q.cycle}s were found.")
        title = f"{towards.capitalize()} and {back} velocity: no {q.cycle}s"
        return to_svg(fig, title=title, name="velocity")
    n = _numbers(taps)
    v_open = np.array([_value(tp, q.velocity_keys[0]) for tp in taps])
    v_close = np.array([_value(tp, q.velocity_keys[1]) for tp in taps])
    with plot_rc():
        ax = fig.add_subplot()
        ax.plot(n, v_open, "o-", ms=3, lw=1.2, color=COLOURS["opening"], label=towards)
        ax.plot(n, v_close, "s-", ms=3, lw=1.2, color=COLOURS["closing"], label=back)
        ax.set_xlabel(f"{q.cycle} number")
        ax.set_ylabel(f"peak velocity ({q.unit}/s)")
        finite = np.concatenate([v_open, v_close])
        finite = finite[np.isfinite(finite)]
        ax.set_ylim(0, float(finite.max()) * 1.2 if finite.size else 1.0)
        ax.legend(loc="lower left", ncols=2, facecolor="white", frameon=True, edgecolor="none")
        ax.set_xticks(_ticks(n))
    return to_svg(fig, title=f"Peak {towards} and {back} velocity per {q.cycle}", name="velocity")


def fingertip_paths_plot(
    positions_mm: ArrayLike, *, labels: Sequence[str], quantity: CycleQuantity = TAPPING
) -> str:
    """Paths of the markers (fingertips for finger tapping): front view (x–y), side view
    (z–y) and a 3D view.

    Parameters
    ----------
    positions_mm : (T, M, 3) float
        Marker positions in the rig's frame (left camera: x right, y down,
        z away from the camera), NaN where missing.
    labels : sequence of M str
        Marker names (``thumb``, ``index``, ...).
    quantity : CycleQuantity
        Names what the markers are (``quantity.markers``).
    """
    what = quantity.markers
    p = np.asarray(positions_mm, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 3 or p.shape[1] != len(labels):
        raise ValueError(f"positions_mm must be (T, {len(labels)}, 3), got {p.shape}")
    fig = new_figure(7.2, 2.6)
    if not np.isfinite(p).any():
        draw_empty(fig, f"No {what.lower()} positions were measured.")
        return to_svg(fig, title=f"{what} paths: no data", name="paths")
    # At most ~MAX_PATH_POINTS samples per path: the drawing looks the same and
    # the SVG stays light for browsers and the PDF renderer.
    p = p[:: max(1, -(-p.shape[0] // MAX_PATH_POINTS))]
    with plot_rc():
        ax_front = fig.add_subplot(1, 3, 1)
        ax_side = fig.add_subplot(1, 3, 2)
        ax_3d = fig.add_subplot(1, 3, 3, projection="3d")
        for m, name in enumerate(labels):
            colour = MARKER_COLOURS[m % len(MARKER_COLOURS)][0]
            x, y, z = p[:, m, 0], p[:, m, 1], p[:, m, 2]
            ax_front.plot(x, y, lw=0.8, color=colour, label=name)
            ax_side.plot(z, y, lw=0.8, color=colour, label=name)
            ax_3d.plot(x, z, y, lw=0.6, color=colour, label=name)
        for ax in (ax_front, ax_side):
            ax.invert_yaxis()  # y points down in the camera frame; show "up" as up
            ax.set_aspect("equal", adjustable="datalim")
        ax_front.set_xlabel("x (mm)")
        ax_front.set_ylabel("y (mm)")
        ax_front.set_title("front (camera) view", fontsize=8.5)
        ax_side.set_xlabel("z, depth (mm)")
        ax_side.set_ylabel("y (mm)")
        ax_side.set_title("side view", fontsize=8.5)
        ax_3d.set_xlabel("x", fontsize=7)
        ax_3d.set_ylabel("z", fontsize=7)
        ax_3d.set_zlabel("y", fontsize=7)
        finite = p[np.isfinite(p).all(axis=2)]
        centre = (np.nanmax(finite, axis=0) + np.nanmin(finite, axis=0)) / 2
        half = max(float(np.max(np.ptp(finite, axis=0))) / 2, 1.0)
        ax_3d.set_xlim(centre[0] - half, centre[0] + half)
        ax_3d.set_ylim(centre[2] - half, centre[2] + half)
        ax_3d.set_zlim(centre[1] + half, centre[1] - half)
        ax_3d.set_box_aspect((1, 1, 1))
        ax_3d.tick_params(labelsize=6)
        ax_3d.set_title("3D", fontsize=8.5)
        ax_front.legend(loc="best")
    return to_svg(fig, title=f"{what} paths in front, side and 3D views (mm)", name="paths")

"""A patient's trends: one metric over sessions, per hand and medication state, as inline SVG.

Drawn with the same matplotlib set-up as the plots of one trial
(:mod:`app.plots`: palette, fonts, ids, ``<svg>`` output); the patient page
shows one trend per key metric (:mod:`app.services.patients` gathers the
:class:`TrendPoint` values).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import date, datetime, timedelta
from typing import Any

from app.plots import COLOURS, draw_empty, new_figure, plot_rc, to_svg


@dataclass(frozen=True)
class TrendPoint:
    """One session's value of one metric for one hand, for the trend plots.

    Attributes
    ----------
    recorded_at : date or datetime of the session.
    hand : ``"left"`` or ``"right"``.
    medication_state : ``"on"``, ``"off"`` or ``"unknown"``.
    value : float (NaN or None when the trial has no value).
    """

    recorded_at: date | datetime
    hand: str
    medication_state: str
    value: float | None


#: Sideways spread of the series of one visit, in share of the time axis: hands and
#: medication states measured an hour apart would otherwise hide each other.
DODGE_FRACTION = 0.012
_DODGE_SLOTS = {
    ("left", "off"): -1.5,
    ("left", "on"): -0.5,
    ("right", "off"): 0.5,
    ("right", "on"): 1.5,
}


def trend_plot(
    points: Sequence[TrendPoint],
    *,
    label: str,
    unit: str,
    integer: bool = False,
    limb: str = "hand",
) -> str:
    """One metric over sessions, per side, with medication on and off drawn apart.

    Left and right hands have their own colour; "on" medication is a solid line
    with filled dots, "off" a dashed line with open dots, "unknown" grey
    crosses, so that progression and treatment effect are both visible. Points
    of one visit are spread slightly sideways (:data:`DODGE_FRACTION` of the
    axis per series) so that none hides another; resting the pointer on a
    point shows its date, hand, medication state and value. ``integer`` puts
    ticks on whole numbers only (counts); ``limb`` names the side (hand, foot) on hover.
    """
    fig = new_figure(3.6, 2.3)
    usable = [p for p in points if p.value is not None and math.isfinite(float(p.value))]
    if not usable:
        draw_empty(fig, f"No {label.lower()} measured yet.")
        return to_svg(fig, title=f"{label} over time: no data", name="trend")
    styles: dict[str, dict[str, Any]] = {
        "on": {"ls": "-", "marker": "o", "mfc": None},
        "off": {"ls": "--", "marker": "o", "mfc": "white"},
        "unknown": {"ls": ":", "marker": "x", "mfc": None},
    }
    days = [_as_datetime(p.recorded_at) for p in usable]
    span = max(max(days) - min(days), timedelta(days=90))
    hover: dict[str, str] = {}
    with plot_rc():
        ax = fig.add_subplot()
        for hand in ("left", "right"):
            for med, style in styles.items():
                series = sorted(
                    (p for p in usable if p.hand == hand and p.medication_state == med),
                    key=lambda p: _as_datetime(p.recorded_at),
                )
                if not series:
                    continue
                shift = span * DODGE_FRACTION * _DODGE_SLOTS.get((hand, med), 0.0)
                xs: Any = [_as_datetime(p.recorded_at) + shift for p in series]
                ys = [float(p.value) for p in series]  # type: ignore[arg-type]
                colour = COLOURS[hand]
                ax.plot(xs, ys, ls=style["ls"], lw=1.1, color=colour, label=f"{hand}, {med}")
                for p, x, y in zip(series, xs, ys, strict=True):
                    (dot,) = ax.plot(
                        [x], [y], ls="", marker=style["marker"], ms=4.5, color=colour,
                        mfc=style["mfc"] or colour, alpha=0.85,
                    )  # fmt: skip
                    gid = f"pt{len(hover)}"
                    dot.set_gid(gid)
                    value = f"{y:.0f}" if integer else f"{y:.3g}"
                    hover[gid] = (
                        f"{_as_datetime(p.recorded_at):%Y-%m-%d %H:%M}, {hand} {limb},"
                        f" medication {med}: {value}{' ' + unit if unit and unit != 'count' else ''}"
                    )
        ax.set_ylabel(f"{label} ({unit})" if unit else label)
        ax.legend(loc="best", fontsize=7)
        if integer:
            from matplotlib.ticker import MaxNLocator

            ax.yaxis.set_major_locator(MaxNLocator(integer=True))
            ax.set_ylim(bottom=min(0.0, ax.get_ylim()[0]))
        _date_axis(ax, days)
    title = f"{label} per session over time, per {limb}"
    return to_svg(fig, title=title, name="trend", hover=hover)


#: Up to this many visit days, the x axis is labelled at the visits themselves.
VISIT_TICKS_MAX = 6


def _date_axis(ax: Any, days: list[datetime]) -> None:
    """Dates on the x axis: the visit days themselves when there are at most
    :data:`VISIT_TICKS_MAX` (a year's tick between two visits told neither's date), else 2-5
    concise ticks; a span under 60 days widened to 90 around its middle."""
    # matplotlib.dates has no type hints: its calls are the untyped ones here.
    import matplotlib.dates as mdates

    visits = sorted({d.date() for d in days})
    if len(visits) <= VISIT_TICKS_MAX:
        noon = [datetime(v.year, v.month, v.day, 12) for v in visits]
        ax.set_xticks(
            [mdates.date2num(d) for d in noon],  # type: ignore[no-untyped-call]
            [f"{d.day} {d:%b}\n{d:%Y}" for d in noon],
        )
    else:
        locator = mdates.AutoDateLocator(minticks=2, maxticks=5)  # type: ignore[no-untyped-call]
        ax.xaxis.set_major_locator(locator)
        ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))  # type: ignore[no-untyped-call]
    if max(days) - min(days) < timedelta(days=60):
        centre = min(days) + (max(days) - min(days)) / 2
        ax.set_xlim(
            mdates.date2num(centre - timedelta(days=45)),  # type: ignore[no-untyped-call]
            mdates.date2num(centre + timedelta(days=45)),  # type: ignore[no-untyped-call]
        )


def trend_key(
    points: Sequence[TrendPoint], *, label: str, unit: str, integer: bool, limb: str
) -> str:
    """What :func:`trend_plot` of these arguments shows, as a SHA-256 (lower-case hex): its
    points, words and units, and the plotting code (this module's and :mod:`app.plots`'
    source, matplotlib's version). The key of the trend cache (:mod:`app.reports.trend_cache`).
    """
    shown = {
        "points": [
            [
                _as_datetime(p.recorded_at).isoformat(),
                p.hand,
                p.medication_state,
                None if p.value is None else repr(float(p.value)),
            ]
            for p in points
        ],
        "label": label,
        "unit": unit,
        "integer": integer,
        "limb": limb,
        "code": _code_fingerprint(),
    }
    return hashlib.sha256(json.dumps(shown, sort_keys=True).encode("utf-8")).hexdigest()


@functools.cache
def _code_fingerprint() -> str:
    from app import plots

    return plots.code_key((plots, sys.modules[__name__]))


def _as_datetime(value: date | datetime) -> datetime:
    if isinstance(value, datetime):
        return value.replace(tzinfo=None)
    return datetime(value.year, value.month, value.day)

"""Two trials of one patient side by side: the rows of the trial page's comparison.

The comparison has the visit report's definitions (docs/metrics.md, "Comparisons
within a visit"), over the first 10 taps (cycles) of each trial, so that a number
reads the same on the trial page and in the visit report:

- the other side in the same medication state, same visit: the right–left
  asymmetry, ``100 · (right − left) / mean of both`` (:func:`core.clinical.asymmetry_pct`);
- the same side in the other medication state, same visit: the medication
  response, ``100 · (on − off) / off`` (:func:`core.clinical.medication_response_pct`);
- any other pair (another visit): ``100 · (B − A) / A``, B the compared trial.

Each percentage is said in words ("left 45 % below right"), never as a bare sign.
A decrement (a slope, negative when the amplitude shrinks; a last/first ratio, below
1 then) is said as more or less decrement, with no percentage: a percentage of a
negative slope reads a smaller decrement as a fall.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from app.reports.catalogue import MetricRow, format_metric, is_tap_number, metric_rows
from app.reports.data import ReportData
from app.timezones import local_date
from core.clinical import asymmetry_pct, medication_response_pct

Kind = Literal["asymmetry", "medication", "difference"]


@dataclass(frozen=True)
class PairDefinition:
    """How two trials are compared: whose value comes first in the difference.

    Attributes
    ----------
    kind : ``"asymmetry"``, ``"medication"`` or ``"difference"``
    first, second : str
        The two trials in the difference's order, in words: ``"right"`` and
        ``"left"``, ``"on"`` and ``"off"``, ``"B"`` and ``"A"``.
    first_is_a : bool
        Whether the first of the difference is trial A (the page's own trial).
    difference_title, percent_title : str
        The headings of the difference and of the percentage in words.
    """

    kind: Kind
    first: str
    second: str
    first_is_a: bool
    difference_title: str
    percent_title: str


@dataclass(frozen=True)
class ComparisonRow:
    """One metric of both trials over their first 10 taps (cycles), formatted."""

    key: str
    label: str
    a: str
    b: str
    difference: str
    words: str
    unit: str


def _same_visit(a: ReportData, b: ReportData) -> bool:
    return local_date(a.recorded_at, a.timezone) == local_date(b.recorded_at, b.timezone)


def pair_definition(a: ReportData, b: ReportData) -> PairDefinition:
    """How ``a`` (this trial) and ``b`` (the compared one) are compared (module docstring)."""
    same_visit = a.task == b.task and _same_visit(a, b)
    meds = {a.medication_state, b.medication_state}
    if same_visit and a.hand != b.hand and a.medication_state == b.medication_state:
        return PairDefinition(
            "asymmetry",
            "right",
            "left",
            a.hand == "right",
            "Right − left",
            "Right–left asymmetry: (right − left) / mean of both",
        )
    if same_visit and a.hand == b.hand and meds == {"on", "off"}:
        return PairDefinition(
            "medication",
            "on",
            "off",
            a.medication_state == "on",
            "On − off",
            "Medication response: (on − off) / off",
        )
    return PairDefinition("difference", "B", "A", False, "B − A", "B against A: (B − A) / A")


def _where(pair: PairDefinition, name: str) -> str:
    """``"on the right"``, ``"on medication"``, ``"off medication"``, ``"in B"``."""
    if pair.kind == "asymmetry":
        return f"on the {name}"
    if pair.kind == "medication":
        return f"{name} medication"
    return f"in {name}"


def _percent_words(pair: PairDefinition, first: float, second: float) -> str:
    if pair.kind == "asymmetry":
        pct = asymmetry_pct(first, second)
    elif pair.kind == "medication":
        pct = medication_response_pct(first, second)
    else:
        pct = None if second <= 0 or first < 0 else 100.0 * (first - second) / second
    if pct is None:
        return "–"
    size = f"{abs(pct):.0f} %"
    if size == "0 %":
        return "the same (under 0.5 %)"
    if pair.kind == "medication":  # % of off
        return f"{size} {'higher' if pct > 0 else 'lower'} on medication"
    if pair.kind == "difference":  # % of A
        return f"B {size} {'above' if pct > 0 else 'below'} A"
    low, high = (pair.second, pair.first) if pct > 0 else (pair.first, pair.second)
    return f"{low} lower than {high} by {size} of their mean"


def _decrement_words(pair: PairDefinition, key: str, task: str, unit: str, diff: float) -> str:
    """A larger slope, or a larger last/first ratio, is less decrement."""
    shown = format_metric(key, abs(diff), task).lstrip("+")
    if float(shown) == 0:
        return "the same decrement"
    amount = "" if "_ratio_" in key else f"{shown} {unit} "
    return f"{amount}{'less' if diff > 0 else 'more'} decrement {_where(pair, pair.first)}"


def _count_words(pair: PairDefinition, diff: float) -> str:
    if diff == 0:
        return "the same"
    return f"{abs(diff):.0f} {'more' if diff > 0 else 'fewer'} {_where(pair, pair.first)}"


def _words(pair: PairDefinition, row: MetricRow, task: str, first: float, second: float) -> str:
    key = row.key
    if is_tap_number(key):
        return "–"
    if "_decrement_" in key or "_ratio_" in key:
        return _decrement_words(pair, key, task, row.unit, first - second)
    if key.endswith("_count"):
        return _count_words(pair, first - second)
    return _percent_words(pair, first, second)


def _difference(key: str, task: str, diff: float) -> str:
    text = format_metric(key, diff, task)
    if text == "–":
        return text
    if float(text) == 0:
        return text.lstrip("+-")
    return text if text.startswith(("-", "+")) else "+" + text


def comparison_rows(a: ReportData, b: ReportData) -> tuple[PairDefinition, list[ComparisonRow]]:
    """The main metrics of ``a`` and ``b`` over their first 10 taps (cycles), with the
    difference in the pair's order and the comparison in words (module docstring)."""
    pair = pair_definition(a, b)
    rows_b = {r.key: r for r in metric_rows(b.analysis)}
    out = []
    for row in metric_rows(a.analysis):
        if row.key not in rows_b:
            continue
        va = a.analysis.metrics_first_10.get(row.key)
        vb = b.analysis.metrics_first_10.get(row.key)
        difference, words = "–", "–"
        if va is not None and vb is not None and not is_tap_number(row.key):
            first, second = (float(va), float(vb)) if pair.first_is_a else (float(vb), float(va))
            difference = _difference(row.key, a.task, first - second)
            words = _words(pair, row, a.task, first, second)
        out.append(
            ComparisonRow(
                key=row.key,
                label=row.label,
                a=row.value_first_10 or "–",
                b=rows_b[row.key].value_first_10 or "–",
                difference=difference,
                words=words,
                unit=row.unit,
            )
        )
    return pair, out


__all__ = ["ComparisonRow", "PairDefinition", "comparison_rows", "pair_definition"]

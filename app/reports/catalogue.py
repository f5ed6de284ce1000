"""The catalogue of metrics: label, display unit, UCUM code, decimals and a definition.

Shared by the pages, the reports and the FHIR export; :func:`metric_rows`
turns a result into the lines of a metrics table.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from app.reports.result import TrialResult, read_result
from core.tasks import Task, parse_task, task_key


@dataclass(frozen=True)
class MetricSpec:
    """How a metric is labelled, formatted and coded.

    Attributes
    ----------
    label : str
        Short name for tables.
    unit : str
        Unit as displayed (``mm``, ``Hz``, ``mm/s``, ``mm/tap``; empty for ratios and counts).
    ucum : str
        UCUM code for FHIR (``mm``, ``Hz``, ``mm/s``, ``mm/{tap}``, ``1``).
    decimals : int
        Digits after the decimal point when displayed.
    definition : str
        One sentence a clinician can read.
    primary : bool
        Shown in the main metrics table (else under "More measurements").
    """

    label: str
    unit: str
    ucum: str
    decimals: int
    definition: str
    primary: bool = True


METRICS: dict[str, MetricSpec] = {
    "tap_count": MetricSpec(
        "Taps", "", "1", 0, "Number of complete taps (open–close cycles) in the recording."
    ),
    "frequency_hz": MetricSpec(
        "Tapping frequency",
        "Hz",
        "Hz",
        2,
        "Taps per second while moving: 1 / mean tap duration, pauses excluded.",
    ),
    "amplitude_mm_mean": MetricSpec(
        "Mean amplitude",
        "mm",
        "mm",
        1,
        "Mean peak-to-trough opening: largest thumb–index distance of a tap minus the "
        "distance at its start (the closed position).",
    ),
    "amplitude_mm_cv": MetricSpec(
        "Amplitude variability",
        "",
        "1",
        3,
        "Coefficient of variation of the tap amplitudes (standard deviation / mean).",
    ),
    "amplitude_decrement_mm_per_tap": MetricSpec(
        "Amplitude decrement",
        "mm/tap",
        "mm/{tap}",
        2,
        "Least-squares slope of amplitude against tap number; negative means the taps "
        "shrink (sequence effect).",
    ),
    "amplitude_ratio_last_first_third": MetricSpec(
        "Amplitude ratio, last/first third",
        "",
        "1",
        2,
        "Mean amplitude of the last third of the taps divided by that of the first third; "
        "below 1 means a decrement.",
    ),
    "opening_velocity_mm_s_max": MetricSpec(
        "Peak opening velocity",
        "mm/s",
        "mm/s",
        0,
        "Mean over the taps of each tap's peak opening speed.",
    ),
    "closing_velocity_mm_s_max": MetricSpec(
        "Peak closing velocity",
        "mm/s",
        "mm/s",
        0,
        "Mean over the taps of each tap's peak closing speed.",
    ),
    "inter_tap_interval_cv": MetricSpec(
        "Rhythm variability",
        "",
        "1",
        3,
        "Coefficient of variation of the intervals between tap starts, pauses included.",
    ),
    "hesitation_count": MetricSpec(
        "Hesitations",
        "",
        "1",
        0,
        "Interruptions of the rhythm: taps (without a halt) whose cycle is over 1.5 times "
        "the median of the neighbouring taps, or that follow a closed pause of at least 0.2 s.",
    ),
    "halt_count": MetricSpec(
        "Halts",
        "",
        "1",
        0,
        "Freezes: the fingers stay still for at least 0.3 s. A pause counts once, as "
        "hesitation or halt.",
    ),
    "pause_time_s": MetricSpec(
        "Pause time", "s", "s", 2, "Total duration of the hesitations and halts."
    ),
    "tap_rate_hz": MetricSpec(
        "Tap rate",
        "Hz",
        "Hz",
        2,
        "Taps per second including pauses: 1 / mean interval between tap starts.",
    ),
    # Secondary metrics (shown under "More measurements").
    "reliable_tap_count": MetricSpec(
        "Reliable taps",
        "",
        "1",
        0,
        "Taps whose peak and closures were measured, not filled in; amplitude and velocity "
        "statistics use these.",
        primary=False,
    ),
    "amplitude_mm_sd": MetricSpec(
        "Amplitude SD", "mm", "mm", 1, "Standard deviation of the tap amplitudes.", primary=False
    ),
    "amplitude_mm_max": MetricSpec(
        "Largest amplitude", "mm", "mm", 1, "Amplitude of the largest tap.", primary=False
    ),
    "amplitude_decrement_pct_per_tap": MetricSpec(
        "Amplitude decrement, relative",
        "%/tap",
        "%/{tap}",
        2,
        "Decrement slope as a percentage of the mean amplitude of the first three taps.",
        primary=False,
    ),
    "amplitude_ratio_second_first_half": MetricSpec(
        "Amplitude ratio, second/first half",
        "",
        "1",
        2,
        "Mean amplitude of the second half of the taps divided by that of the first half.",
        primary=False,
    ),
    "amplitude_decrement_onset_tap": MetricSpec(
        "Decrement onset (last steady tap)",
        "",
        "1",
        0,
        "The last tap (counted from 1) before the amplitude starts to fall; empty when "
        "there is no clear decrement.",
        primary=False,
    ),
    "opening_velocity_mm_s_peak": MetricSpec(
        "Fastest opening",
        "mm/s",
        "mm/s",
        0,
        "The largest single-tap peak opening speed.",
        primary=False,
    ),
    "closing_velocity_mm_s_peak": MetricSpec(
        "Fastest closing",
        "mm/s",
        "mm/s",
        0,
        "The largest single-tap peak closing speed.",
        primary=False,
    ),
    "opening_velocity_mm_s_mean": MetricSpec(
        "Mean opening velocity",
        "mm/s",
        "mm/s",
        0,
        "Mean over taps of amplitude / opening duration.",
        primary=False,
    ),
    "closing_velocity_mm_s_mean": MetricSpec(
        "Mean closing velocity",
        "mm/s",
        "mm/s",
        0,
        "Mean over taps of the closing distance / closing duration.",
        primary=False,
    ),
    "opening_velocity_decrement_mm_s_per_tap": MetricSpec(
        "Opening velocity decrement",
        "mm/s per tap",
        "mm/s/{tap}",
        1,
        "Least-squares slope of each tap's peak opening speed against tap number.",
        primary=False,
    ),
    "tap_duration_s_mean": MetricSpec(
        "Mean tap duration",
        "s",
        "s",
        3,
        "Mean duration of one open–close cycle, pauses excluded.",
        primary=False,
    ),
    "inter_tap_interval_s_mean": MetricSpec(
        "Mean interval",
        "s",
        "s",
        3,
        "Mean time between the starts of successive taps.",
        primary=False,
    ),
    "tap_duration_cv": MetricSpec(
        "Tap duration variability",
        "",
        "1",
        3,
        "Coefficient of variation of the tap durations.",
        primary=False,
    ),
    "inter_tap_interval_s_sd": MetricSpec(
        "Interval SD",
        "s",
        "s",
        3,
        "Standard deviation of the intervals between tap starts.",
        primary=False,
    ),
    "tapping_time_s": MetricSpec(
        "Tapping time",
        "s",
        "s",
        2,
        "From the start of the first tap to the end of the last.",
        primary=False,
    ),
    "opening_velocity_decrement_pct_per_tap": MetricSpec(
        "Opening velocity decrement, relative",
        "%/tap",
        "%/{tap}",
        2,
        "Opening velocity slope as a percentage of the first three taps' mean.",
        primary=False,
    ),
    "opening_velocity_ratio_last_first_third": MetricSpec(
        "Opening velocity ratio, last/first third",
        "",
        "1",
        2,
        "Mean peak opening speed of the last third of the taps divided by the first third.",
        primary=False,
    ),
    "opening_velocity_decrement_onset_tap": MetricSpec(
        "Opening velocity decrement onset (last steady tap)",
        "",
        "1",
        0,
        "The last tap (counted from 1) before the opening speed starts to fall; empty without a"
        " clear decrement.",
        primary=False,
    ),
    "closing_velocity_decrement_mm_s_per_tap": MetricSpec(
        "Closing velocity decrement",
        "mm/s per tap",
        "mm/s/{tap}",
        1,
        "Least-squares slope of each tap's peak closing speed against tap number.",
        primary=False,
    ),
    "closing_velocity_ratio_last_first_third": MetricSpec(
        "Closing velocity ratio, last/first third",
        "",
        "1",
        2,
        "Mean peak closing speed of the last third of the taps divided by the first third.",
        primary=False,
    ),
    "gap_count": MetricSpec(
        "Gaps in the recording",
        "",
        "1",
        0,
        "Stretches where a marker could not be measured; taps may be lost there.",
        primary=False,
    ),
}


#: The common keys of every task (docs/interfaces.md) that repeat a task's own metric
#: under another name: shown once, under the task's own name.
ALIAS_KEYS = frozenset(
    {"amplitude_mean", "amplitude_unit", "amplitude_cv", "amplitude_decrement_per_cycle"}
)


def task_text(text: str, task: Task) -> str:
    """A finger-tapping label, unit or definition reworded for ``task``."""
    towards, back = task.phase_words
    unit = task.amplitude_unit
    out = text
    for old, new in (
        (
            "largest thumb–index distance of a tap minus the distance at its start (the closed"
            " position)",
            f"largest {task.signal} of a cycle minus that at its start",
        ),
        ("thumb–index", task.signal),
        # wordings that the word-for-word replacements below would garble
        ("complete taps (open–close cycles)", "complete cycles"),  # not "cycles (cycles)"
        ("the fingers stay", "the movement stays"),
        ("whose cycle is", "whose duration is"),  # not "cycles whose cycle is"
        ("Tapping frequency", "Frequency"),
        ("Tapping time", "Movement time"),
        ("Tap rate", "Cycle rate"),
        ("the fingers", "the movement"),
        ("opening", towards),
        ("Opening", towards.capitalize()),
        ("closing", back),
        ("Closing", back.capitalize()),
        ("open–close cycle", "cycle"),
        ("taps", "cycles"),
        ("Taps", "Cycles"),
        ("tap", "cycle"),
        ("Tap", "Cycle"),
    ):
        out = out.replace(old, new)
    if unit != "mm":
        out = out.replace("mm", unit)
    return out


def task_metric_spec(key: str, task: Task) -> MetricSpec | None:
    """The catalogue entry of a metric of ``task`` (renamed by ``core.cycles.task_key``)."""
    for ft_key, spec in METRICS.items():
        if task_key(ft_key, task) == key:
            return MetricSpec(
                task_text(spec.label, task),
                task_text(spec.unit, task),
                task_text(spec.ucum, task),
                spec.decimals,
                task_text(spec.definition, task),
                spec.primary,
            )
    return None


def _guess_units(key: str) -> tuple[str, str]:
    """Display unit and UCUM code of a metric the catalogue does not know, from its name."""
    for suffix, unit, ucum in (
        ("_deg_s", "deg/s", "deg/s"),
        ("_deg", "deg", "deg"),
        ("_mm_s_per_tap", "mm/s per tap", "mm/s/{tap}"),
        ("_pct_per_tap", "%/tap", "%/{tap}"),
        ("_mm_per_tap", "mm/tap", "mm/{tap}"),
        ("_mm_s", "mm/s", "mm/s"),
        ("_hz", "Hz", "Hz"),
        ("_mm", "mm", "mm"),
        ("_s", "s", "s"),
        ("_px", "px", "{pixel}"),
    ):
        if key.endswith(suffix) or f"{suffix}_" in key:
            return unit, ucum
    return "", "1"


def metric_spec(key: str, task: str = "finger_tapping") -> MetricSpec:
    """The catalogue entry of ``key`` (a metric of ``task``), or one guessed from its name
    (secondary, no definition)."""
    the_task = parse_task(task)
    if the_task is not Task.FINGER_TAPPING:
        found = task_metric_spec(key, the_task)
        if found is not None:
            return found
    spec = METRICS.get(key)
    if spec is not None:
        return spec
    unit, ucum = _guess_units(key)
    return MetricSpec(key.replace("_", " ").capitalize(), unit, ucum, 3, "", primary=False)


def is_tap_number(key: str) -> bool:
    """Whether the metric ``key`` is a tap (cycle) number (0-based in result.json, shown from 1)."""
    return key.endswith(("_onset_tap", "_onset_cycle"))


def display_value(key: str, value: float) -> float:
    """The value a person reads: tap numbers counted from 1 (INTERFACES.md), others as stored."""
    return value + 1 if is_tap_number(key) else value


def format_metric(key: str, value: object, task: str = "finger_tapping") -> str:
    """``value`` formatted with the metric's decimals (no unit); "–" when absent.

    Tap numbers (``*_onset_tap``) are shown counted from 1.
    """
    if value is None or isinstance(value, bool):
        return "–"
    if not isinstance(value, int | float):
        return str(value)
    if not math.isfinite(float(value)):
        return "–"
    value = display_value(key, value)
    spec = METRICS.get(key) if parse_task(task) is Task.FINGER_TAPPING else None
    spec = spec or (task_metric_spec(key, parse_task(task)) if task != "finger_tapping" else None)
    decimals = spec.decimals if spec else (0 if isinstance(value, int) else 3)
    if key.endswith(("_count", "_onset_tap", "_onset_cycle")) and float(value).is_integer():
        decimals = 0
    text = f"{float(value):.{decimals}f}"
    if key.endswith(("_per_tap", "_per_cycle")) and float(value) > 0:
        text = "+" + text
    return text


@dataclass(frozen=True)
class MetricRow:
    """One line of the metrics table."""

    key: str
    label: str
    value: str
    value_first_10: str | None
    unit: str
    definition: str


def metric_rows(
    result: TrialResult | Mapping[str, Any] | None, *, primary: bool | None = True
) -> list[MetricRow]:
    """Rows of the metrics table, catalogue order first, then any other number.

    Parameters
    ----------
    result : TrialResult, or a result.json document
    primary : bool or None
        True: the main metrics only; False: the others only; None: all.
    """
    read = result if isinstance(result, TrialResult) else read_result(result)
    metrics, first10 = read.metrics, read.metrics_first_10
    task = parse_task(read.task)
    ordered = [task_key(k, task) for k in METRICS]
    keys = [k for k in ordered if k in metrics] + [k for k in metrics if k not in ordered]
    aliases = ALIAS_KEYS | ({"cycle_count"} if task is Task.FINGER_TAPPING else set())
    rows = []
    for key in keys:
        if key in aliases:
            continue
        spec = metric_spec(key, task)
        if primary is not None and spec.primary != primary:
            continue
        rows.append(
            MetricRow(
                key=key,
                label=spec.label,
                value=format_metric(key, metrics[key], task),
                value_first_10=format_metric(key, first10[key], task) if key in first10 else None,
                unit=spec.unit,
                definition=spec.definition,
            )
        )
    return rows

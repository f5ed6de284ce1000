"""The metrics each view shows for a task, under the task's names, words and units.

The catalogue (:mod:`app.reports.catalogue`) holds finger tapping's metrics and
rewords them for the other tasks; this module picks, per task, the metrics
the patient page trends (:func:`trend_metrics`) and the ones the reports define
(:func:`primary_specs`).
"""

from __future__ import annotations

from app.reports.catalogue import METRICS, MetricSpec, metric_spec, task_text
from core.tasks import Task, parse_task, task_key


def primary_specs(task: str | Task = Task.FINGER_TAPPING) -> dict[str, MetricSpec]:
    """The main metrics of ``task`` under its own keys, with its labels, units and
    definitions (the reports' definitions section)."""
    the_task = parse_task(task)
    return {
        task_key(key, the_task): metric_spec(task_key(key, the_task), the_task.value)
        for key, spec in METRICS.items()
        if spec.primary
    }


# Metrics shown in trend plots (key, label, unit), finger tapping's names.
TREND_METRICS: tuple[tuple[str, str, str], ...] = (
    ("amplitude_mm_mean", "Mean amplitude", "mm"),
    ("frequency_hz", "Tapping frequency", "Hz"),
    ("opening_velocity_mm_s_max", "Peak opening velocity", "mm/s"),
    ("amplitude_decrement_mm_per_tap", "Amplitude decrement", "mm/tap"),
    ("hesitation_count", "Hesitations and halts", "count"),
)


def trend_metrics(task: str | Task = Task.FINGER_TAPPING) -> tuple[tuple[str, str, str], ...]:
    """The trend metrics of ``task``: :data:`TREND_METRICS` under the task's keys, words
    and units (``amplitude_deg_mean``, "Peak supination velocity", ``deg/s``)."""
    the_task = parse_task(task)
    if the_task is Task.FINGER_TAPPING:
        return TREND_METRICS
    return tuple(
        (task_key(key, the_task), task_text(label, the_task), task_text(unit, the_task))
        for key, label, unit in TREND_METRICS
    )


__all__ = ["TREND_METRICS", "primary_specs", "trend_metrics"]

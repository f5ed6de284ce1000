"""The summary block: what a neurologist reads first about one or more trials.

Over the first 10 taps (the item's own task, ``metrics_first_10``), the four
aspects a rater judges in MDS-UPDRS 3.4 — speed, amplitude, interruptions and
decrement — each value with its unit and the band of the item's wording it
falls into (:mod:`core.clinical`, thresholds in docs/metrics.md). A band is
evidence beside the clinician's own rating, never a score.

The same block serves the trial page (this trial, with the other hand and
the other medication state of the same visit beside it), page 1 of the trial
report and page 1 of the visit report (every trial of the visit, one row group
per task). :class:`SummaryColumn` is one trial; :func:`summary_rows` lays the
values of several trials out in rows.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from app.reports.catalogue import format_metric, metric_spec
from app.reports.result import TrialResult
from core.clinical import (
    ITEM_REPETITIONS,
    Band,
    asymmetry_pct,
    decrement_band,
    interruption_band,
    medication_response_pct,
    unanchored_band,
)
from core.cycles import task_key
from core.tasks import Task, parse_task

FINGER_TAPPING = "finger_tapping"

TASK_TITLES = {
    FINGER_TAPPING: "Finger tapping (MDS-UPDRS 3.4)",
    "hand_movements": "Hand movements (MDS-UPDRS 3.5)",
    "pronation_supination": "Pronation–supination (MDS-UPDRS 3.6)",
    "toe_tapping": "Toe tapping (MDS-UPDRS 3.7)",
    "leg_agility": "Leg agility (MDS-UPDRS 3.8)",
}
TASK_ORDER = (
    FINGER_TAPPING,
    "hand_movements",
    "pronation_supination",
    "toe_tapping",
    "leg_agility",
)
"""Row groups of the visit summary, finger tapping first."""

#: The key metrics compared within a visit (asymmetry, medication response), first 10 taps.
KEY_METRICS = ("frequency_hz", "amplitude_mm_mean", "opening_velocity_mm_s_max")

ASPECT_TITLES = {
    "speed": "Speed",
    "amplitude": "Amplitude",
    "interruptions": "Interruptions",
    "decrement": "Decrement",
}


@dataclass(frozen=True)
class SummaryColumn:
    """One trial in a summary block.

    Attributes
    ----------
    trial_id : int
    task : str
    hand : ``"left"`` or ``"right"``
    medication_state : ``"on"``, ``"off"`` or ``"unknown"``
    result : TrialResult
    clinician_rating : int or None
    rating_comment : str or None
    label_detail : str or None
        What tells this trial from another of the same side and medication state
        beside it (``"trial #13, 10:42 CET"``), added to :attr:`label`; None: nothing
        to tell apart (``app.reports.visit.distinct_labels`` sets it).
    """

    trial_id: int
    task: str
    hand: str
    medication_state: str
    result: TrialResult
    clinician_rating: int | None = None
    rating_comment: str | None = None
    label_detail: str | None = None

    @property
    def base_label(self) -> str:
        """``"Left hand, medication off"`` (``"Left foot, ..."`` for toe tapping)."""
        limb = parse_task(self.task).limb
        return f"{self.hand.capitalize()} {limb}, medication {self.medication_state}"

    @property
    def label(self) -> str:
        """:attr:`base_label`, and ``" — trial #13, 10:42 CET"`` when it has a
        :attr:`label_detail` (another trial of the same side and state is beside it)."""
        detail = f" — {self.label_detail}" if self.label_detail else ""
        return self.base_label + detail

    def value(self, key: str) -> float | None:
        """A metric over the first 10 taps (None when undefined or absent); ``key`` is a
        finger-tapping name, read under the trial's task's name (``core.cycles.task_key``)."""
        value = self.result.metrics_first_10.get(task_key(key, parse_task(self.task)))
        return None if value is None else float(value)

    @property
    def taps_counted(self) -> int:
        """Complete taps (cycles) among the first 10 (fewer when the recording held fewer)."""
        return int(self.value("tap_count") or 0)

    def band(self, aspect: str) -> Band:
        """The band of ``aspect`` over the first 10 taps (docs/metrics.md)."""
        if aspect in ("speed", "amplitude"):
            return unanchored_band(aspect)
        if aspect == "interruptions":
            return interruption_band(
                int(self.value("hesitation_count") or 0), int(self.value("halt_count") or 0)
            )
        if aspect == "decrement":
            # "after the 1st tap" is the first tap counted: taps a correction excluded
            # before it are not the item's taps (docs/metrics.md)
            onset = self.value("amplitude_decrement_onset_tap")
            return decrement_band(
                None if onset is None else self.result.counted_position(int(onset)),
                int(self.value("reliable_tap_count") or 0),
                parse_task(self.task).cycle_word,
            )
        raise ValueError(f"unknown aspect {aspect!r}")


@dataclass(frozen=True)
class SummaryCell:
    """One value of one trial: text with its unit, and the band where the row has one."""

    text: str
    band: Band | None = None


@dataclass(frozen=True)
class SummaryRow:
    """One line of the block: an aspect's value for each trial (columns in order)."""

    aspect: str
    label: str
    unit: str
    cells: tuple[SummaryCell, ...]
    key: str


def _formatted(column: SummaryColumn, key: str) -> str:
    value = column.value(key)
    task = parse_task(column.task)
    if key == "amplitude_decrement_onset_tap":
        # Counted from 1 on every page and report (result.json counts from 0); the tap's
        # number is the recording's, as in the taps table and the plots, and where a
        # correction left taps out before it, its place among the taps counted too.
        if value is None:
            return "none"
        number, counted = int(value) + 1, column.result.counted_position(int(value))
        place = "" if counted == number else f" (the {_ordinal(counted)} counted)"
        return f"after {task.cycle_word} {number}{place}"
    return format_metric(task_key(key, task), value, task.value)


# (aspect, metric key, label); the band is shown on the aspect's first row (interruptions:
# in a row of its own after both, templates/partials/summary_block.html).
ROWS: tuple[tuple[str, str, str], ...] = (
    ("speed", "frequency_hz", "Tapping frequency"),
    ("speed", "opening_velocity_mm_s_max", "Peak opening velocity"),
    ("amplitude", "amplitude_mm_mean", "Mean amplitude"),
    ("interruptions", "hesitation_count", "Hesitations"),
    ("interruptions", "halt_count", "Halts (arrests)"),
    ("decrement", "amplitude_decrement_onset_tap", "Decrement onset"),
    ("decrement", "amplitude_decrement_mm_per_tap", "Decrement slope"),
)


def summary_rows(columns: Sequence[SummaryColumn]) -> list[SummaryRow]:
    """The rows of a summary block for ``columns`` (trials of one task), the band on each
    aspect's first row; labels, units and keys in that task's words."""
    task = parse_task(columns[0].task if columns else None)
    rows: list[SummaryRow] = []
    seen: set[str] = set()
    for aspect, key, label in ROWS:
        first = aspect not in seen
        seen.add(aspect)
        own = task_key(key, task)
        spec = metric_spec(own, task.value)
        unit = "" if key == "amplitude_decrement_onset_tap" else spec.unit
        if task is not Task.FINGER_TAPPING:
            label = spec.label if key != "amplitude_decrement_onset_tap" else label
        cells = tuple(
            SummaryCell(_formatted(c, key), c.band(aspect) if first else None) for c in columns
        )
        rows.append(SummaryRow(aspect=aspect, label=label, unit=unit, cells=cells, key=own))
    return rows


def _ordinal(n: int) -> str:
    return f"{n}{'th' if 10 <= n % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(n % 10, 'th')}"


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'s' if n != 1 else ''}"


def short_taps_note(column: SummaryColumn) -> str | None:
    """A note when fewer than 10 taps (cycles) are counted (band 4 is the clinician's):
    fewer completed in the recording, or fewer left by a correction, which it says."""
    n = column.taps_counted
    if n >= ITEM_REPETITIONS:
        return None
    word = parse_task(column.task).cycle_word
    removed = column.result.removed_cycles
    if removed:
        return (
            f"Only {_plural(n, word)} counted: a correction left out {removed} of the"
            f" {_plural(len(column.result.task_cycles) + removed, 'complete ' + word)} in the"
            f" recording; the item asks for {ITEM_REPETITIONS}."
        )
    lost = column.result.cycles_in_gaps
    if lost:
        why = (
            "lost frames"
            if column.result.sync.dropped_frames_left or column.result.sync.dropped_frames_right
            else "frames where the markers were not seen"
        )
        made = len(column.result.task_cycles) + lost
        return (
            f"About {made} {word}s were made; only {n} could be measured whole: the others"
            f" fell in gaps of {why}. The item asks for {ITEM_REPETITIONS}."
        )
    return (
        f"Only {_plural(n, 'complete ' + word)} in the recording; the item asks for"
        f" {ITEM_REPETITIONS}."
    )


@dataclass(frozen=True)
class Comparison:
    """A percentage comparison of one key metric between two trials of a visit."""

    key: str
    label: str
    text: str


def _pct(value: float | None) -> str:
    return "–" if value is None else f"{value:+.0f} %"


def _own(key: str, column: SummaryColumn) -> tuple[str, str]:
    """The key and label of a key metric in the column's task."""
    task = parse_task(column.task)
    own = task_key(key, task)
    return own, metric_spec(own, task.value).label


def asymmetry_rows(right: SummaryColumn, left: SummaryColumn) -> list[Comparison]:
    """Right–left asymmetry of the key metrics (``core.clinical.asymmetry_pct``), one task."""
    return [
        Comparison(*_own(key, right), _pct(asymmetry_pct(right.value(key), left.value(key))))
        for key in KEY_METRICS
    ]


def medication_rows(on: SummaryColumn, off: SummaryColumn) -> list[Comparison]:
    """Medication response of the key metrics (``core.clinical.medication_response_pct``)."""
    return [
        Comparison(*_own(key, on), _pct(medication_response_pct(on.value(key), off.value(key))))
        for key in KEY_METRICS
    ]


def neighbours(
    this: SummaryColumn, visit: Sequence[SummaryColumn]
) -> tuple[SummaryColumn | None, SummaryColumn | None]:
    """The other hand in the same medication state, and the same hand in the other state.

    Among ``visit`` (the visit's trials of the same task, newest last); None where absent.
    """
    same_task = [c for c in visit if c.task == this.task and c.trial_id != this.trial_id]
    other_hand = [
        c for c in same_task if c.hand != this.hand and c.medication_state == this.medication_state
    ]
    other_med = [
        c
        for c in same_task
        if c.hand == this.hand
        and c.medication_state != this.medication_state
        and {c.medication_state, this.medication_state} == {"on", "off"}
    ]
    return (other_hand[-1] if other_hand else None, other_med[-1] if other_med else None)

"""The examination tasks a trial can record (MDS-UPDRS part III items 3.4–3.8).

A trial records one task on one side. Finger tapping (3.4) is the default, as
before tasks existed; hand movements (3.5), pronation–supination (3.6), toe
tapping (3.7) and leg agility (3.8) have their own marker protocols (``docs/protocols.md``) and cycle
signals, and share the cycle metrics (``docs/metrics.md``). The values are the
strings of the command line (``--task``), the REST API (``task``) and
result.json (``task``), docs/interfaces.md.
"""

from __future__ import annotations

from enum import StrEnum

from core.errors import InputError


class Task(StrEnum):
    """One MDS-UPDRS bradykinesia item measured by a trial."""

    FINGER_TAPPING = "finger_tapping"
    HAND_MOVEMENTS = "hand_movements"
    PRONATION_SUPINATION = "pronation_supination"
    TOE_TAPPING = "toe_tapping"
    LEG_AGILITY = "leg_agility"

    @property
    def updrs_item(self) -> str:
        """The MDS-UPDRS item number, ``"3.4"`` … ``"3.8"``."""
        return _ITEMS[self]

    @property
    def heading(self) -> str:
        """``"Hand movements (MDS-UPDRS 3.5)"``."""
        return f"{_NAMES[self]} (MDS-UPDRS {self.updrs_item})"

    @property
    def label(self) -> str:
        """``"Hand movements"``."""
        return _NAMES[self]

    @property
    def amplitude_unit(self) -> str:
        """Unit of the cycle amplitude: ``"deg"`` for pronation–supination and leg agility
        (rotations), else ``"mm"``."""
        return "deg" if self in (Task.PRONATION_SUPINATION, Task.LEG_AGILITY) else "mm"

    @property
    def limb(self) -> str:
        """``"foot"`` for toe tapping, ``"leg"`` for leg agility, else ``"hand"``."""
        return _LIMBS.get(self, "hand")

    @property
    def signal(self) -> str:
        """What the cycle signal measures, in words: ``"thumb–index distance"``,
        ``"rotation of the hand about the forearm"`` (:mod:`core.protocols`)."""
        return _SIGNALS[self]

    @property
    def cycle_word(self) -> str:
        """``"tap"`` for finger tapping, ``"cycle"`` for the other tasks."""
        return "tap" if self is Task.FINGER_TAPPING else "cycle"

    @property
    def phase_words(self) -> tuple[str, str]:
        """The two halves of a cycle: (towards the turn, back), e.g. ``("opening", "closing")``."""
        return PHASE_WORDS[self]


_ITEMS = {
    Task.FINGER_TAPPING: "3.4",
    Task.HAND_MOVEMENTS: "3.5",
    Task.PRONATION_SUPINATION: "3.6",
    Task.TOE_TAPPING: "3.7",
    Task.LEG_AGILITY: "3.8",
}
_NAMES = {
    Task.FINGER_TAPPING: "Finger tapping",
    Task.HAND_MOVEMENTS: "Hand movements",
    Task.PRONATION_SUPINATION: "Pronation–supination",
    Task.TOE_TAPPING: "Toe tapping",
    Task.LEG_AGILITY: "Leg agility",
}
_LIMBS = {Task.TOE_TAPPING: "foot", Task.LEG_AGILITY: "leg"}

_SIGNALS = {
    Task.FINGER_TAPPING: "thumb–index distance",
    Task.HAND_MOVEMENTS: "finger–wrist distance",
    Task.PRONATION_SUPINATION: "rotation of the hand about the forearm",
    Task.TOE_TAPPING: "toe lift",
    Task.LEG_AGILITY: "rise of the thigh about the hip",
}

#: The words for the two halves of a cycle: (towards the turn, back).
PHASE_WORDS = {
    Task.FINGER_TAPPING: ("opening", "closing"),
    Task.HAND_MOVEMENTS: ("opening", "closing"),
    Task.PRONATION_SUPINATION: ("supination", "pronation"),
    Task.TOE_TAPPING: ("lift", "lowering"),
    Task.LEG_AGILITY: ("lift", "lowering"),
}

TASKS: tuple[str, ...] = tuple(t.value for t in Task)
"""Every task value, in the order of the MDS-UPDRS items."""

DEFAULT_TASK = Task.FINGER_TAPPING


def parse_task(value: str | Task | None) -> Task:
    """The :class:`Task` named by ``value`` (None or empty: finger tapping).

    Raises
    ------
    InputError
        ``value`` names no task; the message lists the ones there are.
    """
    if value is None or value == "":
        return DEFAULT_TASK
    if isinstance(value, Task):
        return value
    text = str(value).strip().lower().replace("-", "_")
    try:
        return Task(text)
    except ValueError:
        raise InputError(
            f"unknown task {str(value)[:40]!r}; choose one of {', '.join(TASKS)}."
        ) from None


def task_key(key: str, task: Task) -> str:
    """A finger-tapping metric or tap key renamed for ``task`` (``amplitude_mm_mean`` ->
    ``amplitude_deg_mean``, ``opening_velocity_mm_s_max`` -> ``supination_velocity_deg_s_max``,
    ``tap_count`` -> ``cycle_count``); finger tapping's own keys are returned unchanged."""
    if task is Task.FINGER_TAPPING:
        return key
    unit = task.amplitude_unit
    towards, back = task.phase_words
    out = key
    for old, new in (
        ("inter_tap_interval", "inter_cycle_interval"),
        ("tapping_time_s", "movement_time_s"),
        ("reliable_tap_count", "reliable_cycle_count"),
        ("tap_count", "cycle_count"),
        ("tap_duration", "cycle_duration"),
        ("tap_rate_hz", "cycle_rate_hz"),
        ("_per_tap", "_per_cycle"),
        ("_onset_tap", "_onset_cycle"),
        ("opening_", f"{towards}_"),
        ("closing_", f"{back}_"),
        ("max_aperture", f"max_{'angle' if unit == 'deg' else 'signal'}"),
        ("closed_aperture", f"start_{'angle' if unit == 'deg' else 'signal'}"),
        ("_mm_s_", f"_{unit}_s_"),
        ("_mm_s", f"_{unit}_s"),
        ("_mm_", f"_{unit}_"),
    ):
        out = out.replace(old, new)
    if out.endswith("_mm"):
        out = out[: -len("_mm")] + f"_{unit}"
    return out


__all__ = ["DEFAULT_TASK", "PHASE_WORDS", "TASKS", "Task", "parse_task", "task_key"]

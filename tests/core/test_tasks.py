"""The examination tasks: values, units and the parsing of a task name."""

from __future__ import annotations

import pytest

from core.errors import InputError
from core.tasks import DEFAULT_TASK, TASKS, Task, parse_task


def test_the_task_values_are_those_of_the_interfaces() -> None:
    assert TASKS == ("finger_tapping", "hand_movements", "pronation_supination", "toe_tapping")
    assert DEFAULT_TASK is Task.FINGER_TAPPING
    assert [Task(v).updrs_item for v in TASKS] == ["3.4", "3.5", "3.6", "3.7"]


def test_only_pronation_supination_measures_degrees() -> None:
    assert {t.value: t.amplitude_unit for t in Task} == {
        "finger_tapping": "mm",
        "hand_movements": "mm",
        "pronation_supination": "deg",
        "toe_tapping": "mm",
    }
    assert Task.TOE_TAPPING.limb == "foot" and Task.HAND_MOVEMENTS.limb == "hand"


@pytest.mark.parametrize(
    ("text", "task"),
    [
        (None, Task.FINGER_TAPPING),
        ("", Task.FINGER_TAPPING),
        ("toe_tapping", Task.TOE_TAPPING),
        (" Hand-Movements ", Task.HAND_MOVEMENTS),
        (Task.PRONATION_SUPINATION, Task.PRONATION_SUPINATION),
    ],
)
def test_parse_task(text: str | Task | None, task: Task) -> None:
    assert parse_task(text) is task


def test_an_unknown_task_is_refused_with_the_choices() -> None:
    with pytest.raises(InputError, match=r"leg_agility.*finger_tapping, hand_movements"):
        parse_task("leg_agility")

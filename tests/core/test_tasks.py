"""The examination tasks: values, units and the parsing of a task name."""

from __future__ import annotations

import pytest

from core.errors import InputError
from core.tasks import DEFAULT_TASK, TASKS, Task, parse_task


def test_the_task_values_are_those_of_the_interfaces() -> None:
    assert TASKS == (
        "finger_tapping",
        "hand_movements",
        "pronation_supination",
        "toe_tapping",
        "leg_agility",
    )
    assert DEFAULT_TASK is Task.FINGER_TAPPING
    assert [Task(v).updrs_item for v in TASKS] == ["3.4", "3.5", "3.6", "3.7", "3.8"]


def test_the_rotations_measure_degrees_and_the_rest_millimetres() -> None:
    assert {t.value: t.amplitude_unit for t in Task} == {
        "finger_tapping": "mm",
        "hand_movements": "mm",
        "pronation_supination": "deg",
        "toe_tapping": "mm",
        "leg_agility": "deg",
    }
    assert [t.limb for t in Task] == ["hand", "hand", "hand", "foot", "leg"]


@pytest.mark.parametrize(
    ("text", "task"),
    [
        (None, Task.FINGER_TAPPING),
        ("", Task.FINGER_TAPPING),
        ("toe_tapping", Task.TOE_TAPPING),
        ("LEG_AGILITY", Task.LEG_AGILITY),
        (" Hand-Movements ", Task.HAND_MOVEMENTS),
        (Task.PRONATION_SUPINATION, Task.PRONATION_SUPINATION),
    ],
)
def test_parse_task(text: str | Task | None, task: Task) -> None:
    assert parse_task(text) is task


def test_an_unknown_task_is_refused_with_the_choices() -> None:
    with pytest.raises(InputError, match=r"'gait'.*finger_tapping, .*, leg_agility\.$"):
        parse_task("gait")

"""What the plots of a task's cycles show, from the task's definition (:mod:`core.tasks`).

Finger tapping's plots show the aperture (the thumb–index distance, mm) with
its taps; another task's show its cycle signal (:mod:`core.protocols`: the
finger–wrist distance, the rotation of the hand about the forearm in degrees,
the toe lift, the rise of the thigh in degrees) with its cycles, in its own words and unit, read from its
result.json keys (:func:`core.tasks.task_key`). The plots (:mod:`app.plots`)
and the templates' words (:mod:`app.templating`) both take a
:class:`CycleQuantity`, so that no task needs plots or captions of its own.
"""

from __future__ import annotations

from dataclasses import dataclass

from core.tasks import Task, parse_task, task_key

#: Shorter words for a signal axis where the task's own (:attr:`core.tasks.Task.signal`)
#: would not fit beside the plot (a 2.6-inch axis holds about 25 characters at 9 pt).
_AXIS_WORDS = {
    Task.PRONATION_SUPINATION: "hand rotation angle",
    Task.LEG_AGILITY: "thigh rise angle",
}


@dataclass(frozen=True)
class CycleQuantity:
    """What the plots of one task's cycles show (finger tapping's by default).

    Attributes
    ----------
    signal : str
        The cycle signal in words, as the signal axis names it (``"thumb–index distance"``;
        at most about 20 characters, so that the axis label fits the plot's height).
    unit : str
        Its unit (``"mm"`` or ``"deg"``); velocities are in ``unit``/s.
    cycle : str
        ``"tap"`` or ``"cycle"``.
    phases : (str, str)
        The two halves of a cycle (``("opening", "closing")``).
    title : str
        The signal plot's name in its title (``"Aperture"``).
    markers : str
        What the markers are, for the paths plot (``"Fingertip"``).
    peak_key, amplitude_key : str
        The result.json keys of a cycle's turn time (s) and amplitude (``unit``).
    velocity_keys : (str, str)
        The keys of a cycle's peak velocities in the two halves (``unit``/s).
    """

    signal: str = "thumb–index distance"
    unit: str = "mm"
    cycle: str = "tap"
    phases: tuple[str, str] = ("opening", "closing")
    title: str = "Aperture"
    markers: str = "Fingertip"
    peak_key: str = "t_max_aperture_s"
    amplitude_key: str = "amplitude_mm"
    velocity_keys: tuple[str, str] = ("opening_velocity_mm_s_max", "closing_velocity_mm_s_max")


TAPPING = CycleQuantity()


def quantity_of(task: Task | str) -> CycleQuantity:
    """What the plots of ``task`` show: its cycle signal and unit, its words and the
    result.json keys of its cycles."""
    task = parse_task(task)
    if task is Task.FINGER_TAPPING:
        return TAPPING
    return CycleQuantity(
        signal=_AXIS_WORDS.get(task, task.signal),
        unit=task.amplitude_unit,
        cycle=task.cycle_word,
        phases=task.phase_words,
        title=task.signal[0].upper() + task.signal[1:],  # the whole words in titles
        markers="Marker",
        peak_key=task_key(TAPPING.peak_key, task),
        amplitude_key=task_key(TAPPING.amplitude_key, task),
        velocity_keys=(
            task_key(TAPPING.velocity_keys[0], task),
            task_key(TAPPING.velocity_keys[1], task),
        ),
    )


__all__ = ["TAPPING", "CycleQuantity", "quantity_of"]

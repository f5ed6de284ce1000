"""The measurements set against the MDS-UPDRS wording, and compared within a visit.

The MDS-UPDRS part III items 3.4–3.8 (finger tapping, hand movements,
pronation–supination, toe tapping, leg agility) anchor their ratings on the same words
(Goetz et al. 2008): "slight" (1) is *one or two interruptions or
hesitations* or an amplitude that *decrements near the end of the 10
repetitions*; "mild" (2) *3 to 5 interruptions* or a decrement *midway*;
"moderate" (3) *more than 5 interruptions or at least one longer arrest
(freeze)* or a decrement *starting after the 1st repetition*. Those two
aspects are countable, and :func:`interruption_band` and :func:`decrement_band`
say which of these words the measured counts fall under, with the thresholds
of ``docs/metrics.md`` (section "Against the MDS-UPDRS wording").

Slowing ("slight / mild / moderate slowing") and amplitude carry no number
in the wording; :func:`unanchored_band` says so rather than inventing a
cut-off. Band 4 ("cannot or can only barely perform the task") is left to
the clinician.

A band is **evidence** for the clinician's own rating, never a computed score:
it is never summed or combined into an item rating here.

:func:`asymmetry_pct` and :func:`medication_response_pct` are the two
comparisons of the visit report (right versus left, on versus off medication).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: Number of repetitions the MDS-UPDRS items 3.4–3.8 ask for.
ITEM_REPETITIONS = 10

#: Interruptions (hesitations + halts) up to this count: "one or two interruptions" (slight).
INTERRUPTIONS_SLIGHT_MAX = 2
#: Up to this count: "3 to 5 interruptions" (mild); above it "more than 5" (moderate).
INTERRUPTIONS_MILD_MAX = 5

#: A decrement whose last steady repetition (counted from 1) is at most this one
#: "starts after the 1st tap" (moderate).
DECREMENT_MODERATE_LAST_STEADY = 1
#: At most this one: the decrement starts "midway" (mild); later: "near the end" (slight).
DECREMENT_MILD_LAST_STEADY = 6
#: Fewer reliable repetitions than this and the onset of a decrement cannot be located
#: (``core.metrics.decrement_onset`` needs 5 points).
DECREMENT_MIN_REPETITIONS = 5

BAND_NAMES = {0: "normal", 1: "slight", 2: "mild", 3: "moderate", 4: "severe"}

ASPECTS = ("speed", "amplitude", "interruptions", "decrement")


@dataclass(frozen=True)
class Band:
    """Where a measured aspect falls in the MDS-UPDRS wording.

    Attributes
    ----------
    aspect : {"speed", "amplitude", "interruptions", "decrement"}
    level : int or None
        0–3, the rating whose words the measurement matches; None when the
        wording gives no number for the aspect or the recording cannot tell.
    wording : str
        The scale's words for that level (or why there is no level), to print
        beside the value.
    """

    aspect: str
    level: int | None
    wording: str

    @property
    def name(self) -> str:
        """``"slight"``, ``"mild"``...; ``"no anchor"`` or ``"not assessable"`` without a level."""
        if self.level is not None:
            return BAND_NAMES[self.level]
        return "no anchor" if self.aspect in ("speed", "amplitude") else "not assessable"


def _count(value: int | float, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{what} must be a finite number, got {value!r}")
    if value < 0 or float(value) != int(value):
        raise ValueError(f"{what} must be a whole number >= 0, got {value!r}")
    return int(value)


def interruption_band(hesitations: int, halts: int) -> Band:
    """The band of the interruptions over the first 10 repetitions.

    Parameters
    ----------
    hesitations, halts : int
        ``hesitation_count`` and ``halt_count`` of ``metrics_first_10``. A halt
        (the fingers still for at least 0.3 s, docs/metrics.md) is the
        wording's "longer arrest (freeze)"; both count as interruptions.

    Returns
    -------
    Band
        0 none; 1 for 1–2; 2 for 3–5; 3 for more than 5 or any halt.
    """
    n_hes = _count(hesitations, "hesitations")
    n_halt = _count(halts, "halts")
    total = n_hes + n_halt
    if n_halt > 0:
        return Band("interruptions", 3, "at least one longer arrest (freeze)")
    if total > INTERRUPTIONS_MILD_MAX:
        return Band("interruptions", 3, f"more than {INTERRUPTIONS_MILD_MAX} interruptions")
    if total > INTERRUPTIONS_SLIGHT_MAX:
        return Band(
            "interruptions",
            2,
            f"{INTERRUPTIONS_SLIGHT_MAX + 1} to {INTERRUPTIONS_MILD_MAX} interruptions",
        )
    if total > 0:
        return Band("interruptions", 1, "one or two interruptions or hesitations")
    return Band("interruptions", 0, "no interruption")


def decrement_band(last_steady: int | None, reliable_repetitions: int, word: str = "tap") -> Band:
    """The band of the amplitude decrement over the first 10 repetitions.

    Parameters
    ----------
    last_steady : int or None
        The last repetition before the amplitude starts to fall, **counted
        from 1** (``amplitude_decrement_onset_tap`` of ``metrics_first_10``
        plus one); None when no decrement was found.
    reliable_repetitions : int
        Repetitions whose amplitude was measured (``reliable_tap_count``).
    word : str
        What one repetition is called in the item's wording (``Task.cycle_word``:
        "tap" for finger tapping, "cycle" for the other tasks).

    Returns
    -------
    Band
        None when fewer than 5 repetitions were measured; 0 without a
        decrement; 3 when the fall starts after the 1st repetition; 2 after
        the 2nd to 6th ("midway"); 1 after the 7th or later ("near the end").
    """
    n = _count(reliable_repetitions, "reliable_repetitions")
    if n < DECREMENT_MIN_REPETITIONS:
        return Band(
            "decrement",
            None,
            f"not assessable: {n} measured {word}{'' if n == 1 else 's'}, at least "
            f"{DECREMENT_MIN_REPETITIONS} are needed",
        )
    if last_steady is None:
        return Band("decrement", 0, "no decrement")
    k = _count(last_steady, "last_steady")
    if k < 1:
        raise ValueError(f"last_steady counts from 1, got {last_steady!r}")
    if k <= DECREMENT_MODERATE_LAST_STEADY:
        return Band("decrement", 3, f"decrements starting after the 1st {word}")
    if k <= DECREMENT_MILD_LAST_STEADY:
        return Band("decrement", 2, f"decrements midway in the 10-{word} sequence")
    return Band("decrement", 1, f"decrements near the end of the 10 {word}s")


def unanchored_band(aspect: str) -> Band:
    """The band of speed or amplitude: the wording gives no number, so none is computed."""
    if aspect == "speed":
        return Band(
            "speed",
            None,
            "the scale words slowing as slight, mild or moderate without a number;"
            " compare with the other hand and medication state",
        )
    if aspect == "amplitude":
        return Band(
            "amplitude",
            None,
            "the scale's anchors name no amplitude size;"
            " compare with the other hand and medication state",
        )
    raise ValueError(f"aspect must be 'speed' or 'amplitude', got {aspect!r}")


def asymmetry_pct(right: float | None, left: float | None) -> float | None:
    """Right–left asymmetry in %: ``100 · (right − left) / mean(right, left)``.

    Positive when the right hand's value is larger. None when a value is
    missing or the mean is not positive (the index needs positive quantities:
    frequencies, amplitudes, speeds).
    """
    if right is None or left is None or not (math.isfinite(right) and math.isfinite(left)):
        return None
    mean = (right + left) / 2
    if mean <= 0:
        return None
    return 100.0 * (right - left) / mean


def medication_response_pct(on: float | None, off: float | None) -> float | None:
    """Medication response in %: ``100 · (on − off) / off``.

    Positive when the value is larger on medication. None when a value is
    missing or the off value is not positive.
    """
    if on is None or off is None or not (math.isfinite(on) and math.isfinite(off)):
        return None
    if off <= 0:
        return None
    return 100.0 * (on - off) / off


__all__ = [
    "ASPECTS",
    "BAND_NAMES",
    "ITEM_REPETITIONS",
    "Band",
    "asymmetry_pct",
    "decrement_band",
    "interruption_band",
    "medication_response_pct",
    "unanchored_band",
]

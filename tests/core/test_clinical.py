"""The MDS-UPDRS wording bands (each threshold at its boundary) and the visit comparisons."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core import clinical
from core.clinical import (
    Band,
    asymmetry_pct,
    decrement_band,
    interruption_band,
    medication_response_pct,
    unanchored_band,
)
from core.metrics import compute_metrics
from core.simulation.kinematics import TappingScenario, simulate_tapping

# --- interruptions: 0 | 1-2 | 3-5 | >5 or any halt ----------------------------------------


@pytest.mark.parametrize(
    ("hesitations", "halts", "level"),
    [
        (0, 0, 0),
        (1, 0, 1),
        (2, 0, 1),  # upper edge of "one or two"
        (3, 0, 2),  # lower edge of "3 to 5"
        (5, 0, 2),  # upper edge of "3 to 5"
        (6, 0, 3),  # "more than 5"
        (0, 1, 3),  # one longer arrest (freeze) is moderate by itself
        (2, 1, 3),
    ],
)
def test_interruption_band_at_each_boundary(hesitations, halts, level):
    band = interruption_band(hesitations, halts)
    assert band.aspect == "interruptions"
    assert band.level == level
    assert band.name == clinical.BAND_NAMES[level]


def test_interruption_band_counts_halts_as_interruptions():
    # Two hesitations and a halt are three interruptions; the halt alone decides (3).
    assert interruption_band(2, 1).wording == "at least one longer arrest (freeze)"
    assert interruption_band(3, 0).wording == "3 to 5 interruptions"


def test_interruption_thresholds_are_the_documented_ones():
    text = (_docs() / "metrics.md").read_text(encoding="utf-8")
    assert f"| {clinical.INTERRUPTIONS_SLIGHT_MAX + 1}–{clinical.INTERRUPTIONS_MILD_MAX} " in text
    assert f"more than {clinical.INTERRUPTIONS_MILD_MAX}" in text


@pytest.mark.parametrize("bad", [-1, 1.5, math.nan, None, True])
def test_interruption_band_rejects_non_counts(bad):
    with pytest.raises(ValueError, match="hesitations"):
        interruption_band(bad, 0)


# --- decrement: onset after tap 1 | 2-6 | 7+ ----------------------------------------------


@pytest.mark.parametrize(
    ("last_steady", "level"),
    [
        (None, 0),
        (1, 3),  # "starting after the 1st tap"
        (2, 2),  # lower edge of "midway"
        (6, 2),  # upper edge of "midway"
        (7, 1),  # "near the end"
        (8, 1),
    ],
)
def test_decrement_band_at_each_boundary(last_steady, level):
    band = decrement_band(last_steady, 10)
    assert (band.aspect, band.level) == ("decrement", level)


def test_decrement_band_speaks_of_the_tasks_repetitions():
    assert decrement_band(1, 10).wording == "decrements starting after the 1st tap"
    assert decrement_band(1, 10, "cycle").wording == "decrements starting after the 1st cycle"
    assert decrement_band(4, 10, "cycle").wording == "decrements midway in the 10-cycle sequence"
    assert decrement_band(9, 10, "cycle").wording == "decrements near the end of the 10 cycles"


def test_decrement_band_needs_five_measured_taps():
    assert decrement_band(None, 5).level == 0
    band = decrement_band(None, 4)
    assert band.level is None and band.name == "not assessable"
    assert band.wording == "not assessable: 4 measured taps, at least 5 are needed"
    assert decrement_band(None, 1, "cycle").wording.startswith("not assessable: 1 measured cycle,")


def test_decrement_band_counts_from_one():
    with pytest.raises(ValueError, match="counts from 1"):
        decrement_band(0, 10)


def test_speed_and_amplitude_have_no_computed_band():
    for aspect in ("speed", "amplitude"):
        band = unanchored_band(aspect)
        assert band.level is None and band.name == "no anchor"
        assert "compare with the other hand" in band.wording
    with pytest.raises(ValueError):
        unanchored_band("decrement")


def test_band_is_frozen():
    band = Band("decrement", 1, "x")
    with pytest.raises(AttributeError):
        band.level = 2  # type: ignore[misc]


# --- the bands on measured recordings ------------------------------------------------------


def _first_10(**scenario):
    truth = simulate_tapping(
        TappingScenario(duration_s=6.0, fps=100.0, rhythm_jitter=0.02, **scenario), seed=3
    )
    return compute_metrics(truth.positions_mm, 100.0).metrics_first_10


def test_bands_of_simulated_recordings():
    regular = _first_10()
    assert interruption_band(regular["hesitation_count"], regular["halt_count"]).level == 0
    assert decrement_band(None, regular["reliable_tap_count"]).level == 0
    assert regular["amplitude_decrement_onset_tap"] is None

    # Hesitations before taps 3 and 6 (0-based 2, 5) and a halt before tap 8: band 3.
    halting = _first_10(hesitations=(2, 5), halts=((7, 0.5),))
    assert (halting["hesitation_count"], halting["halt_count"]) == (2, 1)
    assert interruption_band(halting["hesitation_count"], halting["halt_count"]).level == 3


# --- comparisons ----------------------------------------------------------------------------


def test_asymmetry_is_right_minus_left_over_their_mean():
    assert asymmetry_pct(3.0, 2.0) == pytest.approx(40.0)  # 100 * 1 / 2.5
    assert asymmetry_pct(2.0, 3.0) == pytest.approx(-40.0)  # swapping hands flips the sign
    assert asymmetry_pct(2.0, 2.0) == 0.0
    assert asymmetry_pct(None, 2.0) is None
    assert asymmetry_pct(0.0, 0.0) is None
    assert asymmetry_pct(np.nan, 2.0) is None


def test_medication_response_is_on_minus_off_over_off():
    assert medication_response_pct(45.0, 36.0) == pytest.approx(25.0)
    assert medication_response_pct(36.0, 45.0) == pytest.approx(-20.0)  # not symmetric
    assert medication_response_pct(1.0, 0.0) is None
    assert medication_response_pct(None, 1.0) is None


def _docs():
    from pathlib import Path

    return Path(__file__).resolve().parents[2] / "docs"

"""Taps made but lost in gaps are said as such, not as a recording too short.

A browser take with ~20 taps, 15 of them in gaps of lost frames, was summed up as
"Only 5 complete taps in the recording; the item asks for 10", as if the patient or
the recording had stopped early.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from app.reports.result import read_result
from app.reports.summary import SummaryColumn, short_taps_note
from core.metrics import compute_metrics
from core.simulation.kinematics import TappingScenario, simulate_tapping

FPS = 100.0  # Hz


def _tapping(gap_s: tuple[float, float] | None) -> dict:
    """result.json's tapping part of 8 s of simulated tapping, no markers in ``gap_s``."""
    pos = np.array(simulate_tapping(TappingScenario(duration_s=8.0, fps=FPS), seed=5).positions_mm)
    pos = pos[:, :2]
    if gap_s is not None:
        pos[round(gap_s[0] * FPS) : round(gap_s[1] * FPS)] = np.nan  # lost or unseen
    return {"fps": FPS, **compute_metrics(pos, FPS).to_result()}


def test_the_taps_lost_in_a_gap_are_counted():
    made = len(_tapping(None)["taps"])
    assert _tapping(None)["tapping_analysis"]["cycles_in_gaps"] == 0
    doc = _tapping((1.5, 6.5))
    lost = doc["tapping_analysis"]["cycles_in_gaps"]
    assert lost > 0
    # taps: the gap's edges may cut one more on each side, counted in neither
    assert made - 2 <= len(doc["taps"]) + lost <= made


def test_the_note_says_how_many_taps_were_made_and_why_few_were_measured():
    result = read_result(_tapping((1.5, 6.5)))
    n = len(result.taps)
    assert n < 10 and result.cycles_in_gaps > 0
    column = SummaryColumn(1, "finger_tapping", "right", "off", result)
    made = n + result.cycles_in_gaps
    assert short_taps_note(column) == (
        f"About {made} taps were made; only {n} could be measured whole: the others fell in"
        " gaps of frames where the markers were not seen. The item asks for 10."
    )
    lost = dataclasses.replace(
        result, sync=dataclasses.replace(result.sync, dropped_frames_left=(40, 40, 41))
    )
    note = short_taps_note(dataclasses.replace(column, result=lost)) or ""
    assert "fell in gaps of lost frames." in note, note

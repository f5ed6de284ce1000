"""The trial page's comparison of two trials has the visit report's definitions (no database).

Right against left is ``100 · (right − left) / mean of both`` over the first 10 taps,
on the trial page as in the visit report (docs/metrics.md), whichever hand the page
shows; the sign is said in words, and a smaller decrement never reads as a fall.
"""

from __future__ import annotations

import dataclasses
from datetime import timedelta

from sample_trial import sample_report_data, synthetic_trial

from app.reports.comparison import comparison_rows
from app.reports.data import ReportData
from app.reports.visit import task_groups
from core.clinical import asymmetry_pct


def _trial(trial_id: int, hand: str, med: str, *, days: int = 0, **kw) -> ReportData:
    base = sample_report_data()
    _, doc = synthetic_trial(**kw)
    return dataclasses.replace(
        base,
        trial_id=trial_id,
        hand=hand,
        medication_state=med,
        result=doc,
        recorded_at=base.recorded_at + timedelta(days=days, minutes=trial_id),
        timezone="Europe/Prague",
    )


def _row(rows, key):
    return next(r for r in rows if r.key == key)


def test_right_against_left_is_the_visit_report_s_asymmetry_from_either_hand():
    right = _trial(3, "right", "off", amplitude0_mm=30.0, frequency_hz=2.0)
    left = _trial(9, "left", "off", amplitude0_mm=45.0, frequency_hz=2.5)
    (group,) = task_groups([right, left])
    ((med, visit_rows),) = group.asymmetry
    assert med == "off"
    visit = {c.key: c.text for c in visit_rows}
    expected = asymmetry_pct(26.4, 41.4)  # first-10 mean amplitudes: 30 − 3.6, 45 − 3.6
    assert expected is not None and expected < 0
    assert visit["amplitude_mm_mean"] == f"{expected:+.0f} %"  # the visit report: −44 %
    for a, b in ((right, left), (left, right)):
        pair, rows = comparison_rows(a, b)
        assert pair.kind == "asymmetry" and pair.difference_title == "Right − left"
        amp = _row(rows, "amplitude_mm_mean")
        # The same number as the visit report, its sign in words, from either hand's page.
        assert amp.words == f"right lower than left by {abs(expected):.0f} % of their mean"
        assert amp.difference == "-15.0"  # right − left, first 10 taps (mm)
        assert (amp.a, amp.b) == (("26.4", "41.4") if a is right else ("41.4", "26.4"))
        freq = _row(rows, "frequency_hz")
        assert freq.words == f"right lower than left by {abs(asymmetry_pct(2.0, 2.5)):.0f} %" + (
            " of their mean"
        )
        assert "%" not in freq.difference and not freq.words.startswith(("+", "-", "−"))


def test_a_smaller_decrement_on_medication_reads_as_less_decrement():
    off = _trial(3, "right", "off", decrement_mm_per_tap=-1.12)
    on = _trial(6, "right", "on", decrement_mm_per_tap=-0.55, amplitude0_mm=60.0)
    for a, b in ((off, on), (on, off)):
        pair, rows = comparison_rows(a, b)
        assert pair.kind == "medication" and pair.difference_title == "On − off"
        dec = _row(rows, "amplitude_decrement_mm_per_tap")
        assert dec.difference == "+0.57"  # on − off: the slope is less negative on medication
        assert dec.words == "0.57 mm/tap less decrement on medication"
        assert "%" not in dec.words
        amp = _row(rows, "amplitude_mm_mean")
        assert amp.words.endswith("% higher on medication")  # 100 · (on − off) / off
    # The other way round it is more decrement, not a "+" that reads as better.
    _, rows = comparison_rows(_trial(3, "right", "off", decrement_mm_per_tap=-0.3), on)
    assert _row(rows, "amplitude_decrement_mm_per_tap").words == (
        "0.25 mm/tap more decrement on medication"
    )


def test_counts_and_onsets_are_said_in_numbers_of_events_not_percent():
    right = _trial(3, "right", "off", pause_after_tap=4)  # a hesitation in the first 10 taps
    left = _trial(9, "left", "off")
    _, rows = comparison_rows(left, right)
    assert _row(rows, "hesitation_count").words == "1 more on the right"
    onset = [r for r in rows if r.key.endswith("_onset_tap")]
    assert all(r.difference == "–" and r.words == "–" for r in onset)


def test_trials_of_other_visits_are_b_against_a():
    now = _trial(3, "right", "off", amplitude0_mm=30.0)
    year_ago = _trial(1, "right", "on", days=-365, amplitude0_mm=40.0)
    pair, rows = comparison_rows(now, year_ago)  # another visit: no medication response
    assert pair.kind == "difference" and pair.difference_title == "B − A"
    amp = _row(rows, "amplitude_mm_mean")
    assert amp.difference == "+10.0"
    assert amp.words == f"B {100 * 10.0 / 26.4:.0f} % above A"

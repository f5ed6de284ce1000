"""The summary block and the visit's task groups, from result documents (no database)."""

from __future__ import annotations

import dataclasses
import re

import pytest
from sample_trial import sample_report_data, synthetic_trial

from app.reports.catalogue import format_metric, metric_rows
from app.reports.rendering import render_report_html, render_visit_html
from app.reports.result import read_result
from app.reports.summary import SummaryColumn, neighbours, summary_rows
from app.reports.visit import SessionFacts, VisitData, task_groups
from core.version import ALGORITHM_VERSION, software_version


def _column(trial_id=1, hand="right", med="off", **kw) -> SummaryColumn:
    _, doc = synthetic_trial(**kw)
    return SummaryColumn(trial_id, "finger_tapping", hand, med, read_result(doc))


def test_summary_rows_carry_value_unit_and_band_of_each_aspect():
    col = _column(pause_after_tap=4, decrement_mm_per_tap=-0.8)
    rows = {r.key: r for r in summary_rows([col])}
    assert rows["frequency_hz"].cells[0].text == "2.50" and rows["frequency_hz"].unit == "Hz"
    assert rows["amplitude_mm_mean"].unit == "mm"
    assert rows["opening_velocity_mm_s_max"].unit == "mm/s"
    # One band per aspect, on its first row.
    banded = [(r.aspect, r.cells[0].band) for r in rows.values() if r.cells[0].band]
    assert [a for a, _ in banded] == ["speed", "amplitude", "interruptions", "decrement"]
    bands = dict(banded)
    assert bands["interruptions"].level == 1  # one hesitation (before tap 5)
    assert bands["decrement"].level == 3  # falls from the first tap on
    assert bands["speed"].level is None and bands["amplitude"].level is None


def test_decrement_onset_is_shown_counted_from_one():
    col = _column()  # result.json: amplitude_decrement_onset_tap = 0
    assert col.result.metrics_first_10["amplitude_decrement_onset_tap"] == 0
    row = next(r for r in summary_rows([col]) if r.key == "amplitude_decrement_onset_tap")
    assert row.cells[0].text == "after tap 1"
    # The metrics tables show tap numbers from 1 too (they showed 0 before).
    assert format_metric("amplitude_decrement_onset_tap", 0) == "1"
    doc = {"metrics": {"amplitude_decrement_onset_tap": 3}}
    (more,) = [r for r in metric_rows(doc, primary=None) if r.key.endswith("onset_tap")]
    assert more.value == "4" and "counted from 1" in more.definition


def test_neighbours_are_the_other_hand_and_the_other_medication_state():
    this = _column(1, "right", "off")
    visit = [
        this,
        _column(2, "left", "off"),
        _column(3, "right", "on"),
        _column(4, "left", "on"),
    ]
    other_hand, other_med = neighbours(this, visit)
    assert (other_hand.trial_id, other_med.trial_id) == (2, 3)
    assert neighbours(this, [this]) == (None, None)


def _visit(trials: dict[tuple[str, str], float]) -> VisitData:
    base = sample_report_data()
    datas = []
    for i, ((hand, med), amp) in enumerate(trials.items()):
        _, doc = synthetic_trial(amplitude0_mm=amp, frequency_hz=2.0 + 0.5 * (med == "on"))
        datas.append(
            dataclasses.replace(
                base,
                trial_id=10 + i,
                hand=hand,
                medication_state=med,
                result=doc,
                clinician_rating=2 if med == "off" else 1,
                rating_comment=f"comment {hand} {med}",
            )
        )
    return VisitData(
        patient_code="PD-0042",
        session_id=1,
        visit_date=base.recorded_at.date(),
        timezone="Europe/Prague",
        sessions=(SessionFacts(1, base.recorded_at, "off", "none", time_since_levodopa_min=720),),
        trials=tuple(datas),
        software_version=software_version(),
        generated_at=base.generated_at,
    )


def test_task_groups_compare_hands_and_medication_states():
    visit = _visit(
        {("left", "off"): 40.0, ("right", "off"): 50.0, ("left", "on"): 48.0, ("right", "on"): 55.0}
    )
    (group,) = task_groups(visit.trials)
    assert group.task == "finger_tapping"
    assert [(c.medication_state, c.hand) for c in group.columns] == [
        ("off", "right"),
        ("off", "left"),
        ("on", "right"),
        ("on", "left"),
    ]
    asym = dict(group.asymmetry)
    assert set(asym) == {"off", "on"}
    amp = {c.key: c.text for c in asym["off"]}["amplitude_mm_mean"]
    # first-10 mean amplitudes: 50 - 0.8*4.5 = 46.4 and 40 - 3.6 = 36.4
    assert amp == f"{100 * (46.4 - 36.4) / ((46.4 + 36.4) / 2):+.0f} %"
    response = dict(group.medication)
    freq = {c.key: c.text for c in response["right"]}["frequency_hz"]
    assert freq == "+25 %"  # 2.5 Hz on against 2.0 Hz off


def test_a_single_trial_has_no_comparisons():
    (group,) = task_groups(_visit({("left", "off"): 40.0}).trials)
    assert group.asymmetry == () and group.medication == ()


def test_visit_html_is_a_pure_function_of_its_data():
    visit = _visit({("left", "off"): 40.0, ("right", "off"): 50.0})
    html = render_visit_html(visit)
    assert html == render_visit_html(visit)
    assert "Right–left asymmetry" in html and "comment left off" in html
    assert ALGORITHM_VERSION in html and software_version() in html
    assert "Interpretation" in html and "Signature" in html
    assert not re.search(r'(?:src|href)="(?!#)', html)


@pytest.mark.parametrize("render", [render_report_html])
def test_trial_report_opens_with_the_summary_and_names_the_software(render):
    data = sample_report_data()
    html = render(data)
    summary = html.index("data-summary")
    assert summary < html.index('data-plot-name="aperture"') < html.index('id="h-detail"')
    assert f"algorithm {ALGORITHM_VERSION}" in html and software_version() in html
    assert "Slowing from the 6th tap." in html  # the clinician's comment
    assert (
        html.count('id="h-definitions"') == 1
        and 'class="definition"' not in html.split('id="h-more"')[0]
    )  # definitions printed once: not in the main table, in the definitions section


def _with_first_taps_excluded(col: SummaryColumn, k: int) -> SummaryColumn:
    """``col`` as a correction that excluded its first ``k`` taps leaves it: the taps kept
    keep their numbers, the excluded ones are listed apart, and the onset (a tap's
    index) is the first tap kept."""
    taps = list(col.result.taps)
    first_10 = dict(col.result.metrics_first_10)
    first_10["amplitude_decrement_onset_tap"] = taps[k]["index"]
    first_10["tap_count"] = min(10, len(taps) - k)
    result = dataclasses.replace(
        col.result, taps=tuple(taps[k:]), metrics_first_10=first_10, removed_cycles=k
    )
    return dataclasses.replace(col, result=result)


def test_the_decrement_band_counts_from_the_first_tap_kept_after_a_correction():
    """A fall right after the first tap counted is "starting after the 1st tap" (band 3)
    whatever number the recording gave that tap: excluding a false start before it does
    not make it "midway" (the band counted the recording's numbers before)."""
    col = _with_first_taps_excluded(_column(decrement_mm_per_tap=-0.8), 1)
    rows = {r.key: r for r in summary_rows([col])}
    assert rows["amplitude_decrement_onset_tap"].cells[0].text == "after tap 2 (the 1st counted)"
    band = next(
        r.cells[0].band for r in rows.values() if r.aspect == "decrement" and r.cells[0].band
    )
    assert band.level == 3
    # without the correction: the same tap numbers as before, no "counted" aside
    plain = {r.key: r for r in summary_rows([_column(decrement_mm_per_tap=-0.8)])}
    assert plain["amplitude_decrement_onset_tap"].cells[0].text == "after tap 1"


def test_the_short_recording_note_says_when_a_correction_left_the_taps_out():
    from app.reports.summary import short_taps_note

    col = _column()
    n = len(col.result.taps)
    assert n >= 10 and short_taps_note(col) is None
    cut = _with_first_taps_excluded(col, n - 6)
    assert short_taps_note(cut) == (
        f"Only 6 taps counted: a correction left out {n - 6} of the {n} complete taps in the"
        " recording; the item asks for 10."
    )
    short = dataclasses.replace(
        col, result=dataclasses.replace(col.result, metrics_first_10={"tap_count": 6})
    )
    assert short_taps_note(short) == "Only 6 complete taps in the recording; the item asks for 10."


def test_the_amplitude_and_velocity_plots_number_the_taps_as_the_recording_does():
    """After a correction the plots' tap numbers are the taps table's (2-11 when tap 1 was
    excluded), not 1-10: "after tap 2" in the summary is the bar labelled 2."""
    from app.plots import _numbers

    col = _with_first_taps_excluded(_column(), 1)
    assert _numbers(col.result.taps)[:3].tolist() == [2.0, 3.0, 4.0]
    assert _numbers([{"amplitude_mm": 1.0}, {"amplitude_mm": 2.0}]).tolist() == [1.0, 2.0]

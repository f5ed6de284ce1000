"""A clinician's corrections (core.corrections) against core's own computation."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from core.corrections import Corrections, correct_metrics, revised_document, swap_thumb_index
from core.markers_csv import MEASURED, MarkerTable
from core.metrics import compute_metrics, tapping_metrics
from core.simulation.kinematics import TappingScenario, simulate_tapping

FPS = 100.0


@cache
def _table() -> MarkerTable:
    truth = simulate_tapping(
        TappingScenario(
            duration_s=6.0,
            fps=FPS,
            amplitude_mm=50.0,
            frequency_hz=3.0,
            decrement_mm_per_tap=-0.8,
            hesitations=(6,),
            hesitation_s=0.25,
            halts=((12, 0.5),),
        ),
        seed=3,
    )
    pos = truth.positions_mm[:, :2]
    t = pos.shape[0]
    return MarkerTable(
        fps=FPS,
        frames=np.arange(t, dtype=np.int64),
        labels=("thumb", "index"),
        positions_mm=pos,
        status=np.full((t, 2), MEASURED),
        reprojection_px=np.zeros((t, 2)),
    )


@cache
def _core():
    table = _table()
    return compute_metrics(table.positions_mm, FPS, measured=table.status == MEASURED)


def _without(taps, events, drop_taps=(), drop_pauses=()):
    kept = [t for t in taps if t.index not in drop_taps]
    idx = {t.index for t in kept}
    ev = [
        e
        for e in events
        if e["kind"] == "gap" or (e["tap_index"] in idx and e["tap_index"] not in drop_pauses)
    ]
    return kept, ev


def test_no_correction_is_core_itself():
    out = correct_metrics(_table(), Corrections())
    assert out.metrics.metrics == _core().metrics  # exact: the same computation
    assert out.metrics.metrics_first_10 == _core().metrics_first_10
    assert [t.index for t in out.metrics.taps] == [t.index for t in _core().taps]
    assert out.excluded_taps == () and out.dismissed_events == ()


@pytest.mark.parametrize("k", [0, 4, 9])
def test_excluding_a_tap_gives_core_without_that_tap(k):
    core = _core()
    out = correct_metrics(_table(), Corrections(exclude_taps=(k,)))
    kept, events = _without(core.taps, core.events, drop_taps={k})
    assert out.metrics.metrics == tapping_metrics(kept, events)
    assert out.metrics.metrics["tap_count"] == core.metrics["tap_count"] - 1
    amps = [t.amplitude_mm for t in core.taps if t.index != k]
    assert out.metrics.metrics["amplitude_mm_mean"] == pytest.approx(np.mean(amps), abs=1e-12)
    assert [t.index for t in out.excluded_taps] == [k]
    assert k not in [t.index for t in out.metrics.taps]
    # The first ten that count skip the excluded tap.
    first = [t for t in core.taps if t.index != k][:10]
    assert out.metrics.metrics_first_10["tap_count"] == len(first)
    assert out.metrics.metrics_first_10["amplitude_mm_mean"] == pytest.approx(
        np.mean([t.amplitude_mm for t in first if t.reliable]), abs=1e-12
    )


def test_dismissing_a_pause_removes_exactly_that_event():
    core = _core()
    pauses = [e for e in core.events if e["kind"] in ("hesitation", "halt")]
    assert core.metrics["hesitation_count"] >= 1 and core.metrics["halt_count"] >= 1
    hes = next(e for e in pauses if e["kind"] == "hesitation")
    out = correct_metrics(_table(), Corrections(dismiss_pauses=(hes["tap_index"],)))
    dropped = sum(
        1 for e in pauses if e["tap_index"] == hes["tap_index"] and e["kind"] == "hesitation"
    )
    assert out.metrics.metrics["hesitation_count"] == core.metrics["hesitation_count"] - dropped
    assert out.metrics.metrics["halt_count"] == core.metrics["halt_count"]
    assert out.metrics.metrics["tap_count"] == core.metrics["tap_count"]
    kept, events = _without(core.taps, core.events, drop_pauses={hes["tap_index"]})
    assert out.metrics.metrics == tapping_metrics(kept, events)


def test_window_keeps_the_taps_wholly_inside():
    core = _core()
    t0, t1 = 1.0, 4.0
    out = correct_metrics(_table(), Corrections(window_s=(t0, t1)))
    inside = [t for t in core.taps if t.t_start_s >= t0 and t.t_end_s <= t1]
    assert [t.index for t in out.metrics.taps] == [t.index for t in inside]
    assert 0 < len(inside) < len(core.taps)
    assert {t.index for t in out.outside_window_taps} == {
        t.index for t in core.taps if t not in inside
    }
    kept, events = _without(
        core.taps, core.events, drop_taps={t.index for t in core.taps} - {t.index for t in inside}
    )
    assert out.metrics.metrics == tapping_metrics(kept, events)


def test_swapped_labels_change_no_metric_but_the_names():
    table = _table()
    swapped = swap_thumb_index(table)
    assert swapped.labels == ("index", "thumb")
    np.testing.assert_array_equal(swapped.positions_mm, table.positions_mm)
    out = correct_metrics(table, Corrections(swap_labels=True))
    assert out.metrics.metrics == _core().metrics
    # Convention: the columns in the other order with the labels saying so measure the same.
    reordered = MarkerTable(
        fps=FPS,
        frames=table.frames,
        labels=("index", "thumb"),
        positions_mm=table.positions_mm[:, ::-1],
        status=table.status,
        reprojection_px=table.reprojection_px,
    )
    assert correct_metrics(reordered, Corrections()).metrics.metrics == _core().metrics
    doc = revised_document({"markers": ["thumb", "index"], "fps": FPS}, out)
    assert doc["markers"] == ["index", "thumb"] and doc["fps"] == FPS


def test_corrections_compose():
    core = _core()
    hes = next(e for e in core.events if e["kind"] == "hesitation")
    c = Corrections(exclude_taps=(2,), dismiss_pauses=(hes["tap_index"],), window_s=(0.0, 5.0))
    out = correct_metrics(_table(), c)
    drop = {2} | {t.index for t in core.taps if t.t_end_s > 5.0}
    kept, events = _without(core.taps, core.events, drop_taps=drop, drop_pauses={hes["tap_index"]})
    assert out.metrics.metrics == tapping_metrics(kept, events)
    assert Corrections.from_dict(c.to_dict()) == c


def test_bad_corrections_are_refused_in_plain_words():
    core = _core()
    n = len(core.taps)
    with pytest.raises(ValueError, match=f"no tap {n + 1} .*{n} taps"):
        correct_metrics(_table(), Corrections(exclude_taps=(n,)))
    paused = {e["tap_index"] for e in core.events if e["kind"] in ("hesitation", "halt")}
    calm = next(t.index for t in core.taps if t.index not in paused)
    with pytest.raises(ValueError, match="no hesitation or halt"):
        correct_metrics(_table(), Corrections(dismiss_pauses=(calm,)))
    with pytest.raises(ValueError, match="no tap would be left"):
        correct_metrics(_table(), Corrections(exclude_taps=tuple(range(n))))
    with pytest.raises(ValueError, match="window_s"):
        Corrections(window_s=(3.0, 1.0))
    with pytest.raises(ValueError, match="exclude_taps"):
        Corrections(exclude_taps=(-1,))
    no_thumb = MarkerTable(
        fps=FPS,
        frames=np.arange(3, dtype=np.int64),
        labels=("a", "b"),
        positions_mm=np.zeros((3, 2, 3)),
        status=np.full((3, 2), MEASURED),
        reprojection_px=np.zeros((3, 2)),
    )
    with pytest.raises(ValueError, match="thumb and index"):
        correct_metrics(no_thumb, Corrections())


def test_a_correction_keeps_every_metric_key_an_analysis_writes():
    """A corrected result.json holds every ``metrics``/``metrics_first_10`` key that the
    analysis's own result.json holds, measured again: a key core adds to the analysis
    (e.g. the common keys of every task) must be recomputed by ``revised_document`` too,
    never dropped and never copied unchanged from the analysis."""
    from core.pipeline import Analysis

    table = _table()
    base = Analysis(
        fps=FPS,
        frame_numbers=table.frames,
        positions_mm=table.positions_mm,
        status=table.status,
        reprojection_px=table.reprojection_px,
        marker_names=table.labels,
        sync={},
        metrics=_core(),
    ).result_document()
    doc = revised_document(base, correct_metrics(table, Corrections(exclude_taps=(0, 1))))
    for part in ("metrics", "metrics_first_10"):
        assert set(doc[part]) == set(base[part]), part
    assert doc["metrics"]["tap_count"] == base["metrics"]["tap_count"] - 2
    for part in ("metrics", "metrics_first_10"):  # the common keys, where core writes them
        if "cycle_count" in doc[part]:
            assert doc[part]["cycle_count"] == doc[part]["tap_count"], part

# ruff: noqa: F811  (pytest fixtures imported from test_pages are parameters here)
"""Patients' trend plots drawn once and kept on disk (app.reports.trend_cache).

The worker draws a patient's plots when a result changes; the patient page
reads them; a plot missing there is drawn by the page and kept; what the plot
shows (a value, a medication state, the plotting code) names its file, so a
stale plot is never shown; erasure and restore remove the kept plots.
"""

from __future__ import annotations

import errno
import logging
import re
from datetime import UTC, date, datetime

import pytest
from sqlalchemy import select
from test_pages import client, login, seeded  # noqa: F401 - pytest fixtures

import app.reports.trend_cache as trend_cache_module
from app.models import Job, RecordingSession, Trial
from app.reports.trend_cache import KEEP_PER_PATIENT, TrendSvgCache, cached_trend_plot
from app.services import patients
from app.storage import Storage
from app.trends import TrendPoint, trend_key

POINTS = [
    TrendPoint(datetime(2024, 3, 1, 9, tzinfo=UTC), "right", "off", 40.0),
    TrendPoint(datetime(2025, 3, 1, 9, tzinfo=UTC), "right", "on", 35.5),
]
WORDS = {"label": "Amplitude", "unit": "mm", "limb": "hand"}


@pytest.fixture
def drawn(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The labels of the trend plots drawn during the test (by the page or the worker)."""
    calls: list[str] = []
    draw = trend_cache_module.trend_plot

    def counting(points, **kw):
        calls.append(kw["label"])
        return draw(points, **kw)

    monkeypatch.setattr(trend_cache_module, "trend_plot", counting)
    return calls


def _cache(app_settings) -> TrendSvgCache:
    return TrendSvgCache.of(Storage.from_settings(app_settings))


def test_the_key_changes_with_what_the_plot_shows_and_only_then():
    key = trend_key(POINTS, integer=False, **WORDS)
    assert re.fullmatch(r"[0-9a-f]{64}", key)
    assert trend_key(list(POINTS), integer=False, **WORDS) == key
    # a date given as a day is the same point as that day's midnight
    day = [TrendPoint(date(2024, 3, 1), "right", "off", 1.0)]
    midnight = [TrendPoint(datetime(2024, 3, 1), "right", "off", 1.0)]
    assert trend_key(day, integer=False, **WORDS) == trend_key(midnight, integer=False, **WORDS)
    changed = [
        [POINTS[0], TrendPoint(POINTS[1].recorded_at, "right", "on", 35.50001)],
        [POINTS[0], TrendPoint(POINTS[1].recorded_at, "right", "off", 35.5)],
        [POINTS[0], TrendPoint(POINTS[1].recorded_at, "left", "on", 35.5)],
        [POINTS[0], TrendPoint(POINTS[1].recorded_at, "right", "on", None)],
        POINTS[:1],
    ]
    keys = {trend_key(p, integer=False, **WORDS) for p in changed}
    keys |= {
        trend_key(POINTS, integer=True, **WORDS),
        trend_key(POINTS, integer=False, label="Frequency", unit="mm", limb="hand"),
        trend_key(POINTS, integer=False, label="Amplitude", unit="deg", limb="hand"),
        trend_key(POINTS, integer=False, label="Amplitude", unit="mm", limb="foot"),
    }
    assert key not in keys and len(keys) == len(changed) + 4


def test_a_plot_is_drawn_once_and_its_ids_are_its_own(tmp_path, drawn):
    cache = TrendSvgCache(tmp_path / "trends", max_bytes=10**7)
    svg, new = cached_trend_plot(cache, 7, POINTS, **WORDS)
    assert new and drawn == ["Amplitude"] and svg.startswith("<svg")
    again, new = cached_trend_plot(cache, 7, POINTS, **WORDS)
    assert not new and again == svg and drawn == ["Amplitude"]
    (kept,) = cache.files()
    assert kept.name == f"7-{trend_key(POINTS, integer=False, **WORDS)}.svg"
    # Plots kept by different processes share a page: each process numbers its plots'
    # ids from a random start (app.plots.to_svg), so two kept plots have no id in common.
    other, _ = cached_trend_plot(cache, 7, POINTS[:1], **WORDS)
    ids = set(re.findall(r'id="([^"]+)"', svg))
    other_ids = set(re.findall(r'id="([^"]+)"', other))
    assert ids and other_ids and not ids & other_ids


def test_a_plot_that_cannot_be_kept_is_still_shown(tmp_path, drawn, monkeypatch, caplog):
    cache = TrendSvgCache(tmp_path / "trends", max_bytes=10**7)

    def full(final, body):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(cache, "write", full)
    with caplog.at_level(logging.WARNING, logger="app.reports.trend_cache"):
        svg, new = cached_trend_plot(cache, 7, POINTS, **WORDS)
    assert new and svg.startswith("<svg") and cache.files() == []
    assert "No space left on device" in caplog.text and "patient 7" in caplog.text
    assert "35.5" not in caplog.text  # no patient data in the log


def test_a_patient_keeps_a_bounded_number_of_plots(tmp_path):
    cache = TrendSvgCache(tmp_path / "trends", max_bytes=10**7)
    for i in range(KEEP_PER_PATIENT + 5):
        cache.put(1, f"{i:064x}", "<svg>a</svg>")
    cache.put(2, "f" * 64, "<svg>b</svg>")
    assert len([p for p in cache.files() if p.name.startswith("1-")]) == KEEP_PER_PATIENT
    small = TrendSvgCache(tmp_path / "small", max_bytes=3 * len("<svg>a</svg>"))
    for i in range(5):
        small.put(3, f"{i:064x}", "<svg>a</svg>")
    assert len(small.files()) == 3
    with pytest.raises(ValueError, match="SVG"):
        cache.put(1, "e" * 64, "%PDF")
    with pytest.raises(ValueError, match="SHA-256"):
        cache.path(1, "../etc")
    assert cache.forget_patient(1) == KEEP_PER_PATIENT
    assert [p.name for p in cache.files()] == [f"2-{'f' * 64}.svg"]
    assert cache.clear() == 1 and cache.files() == []


def test_the_page_keeps_its_plots_and_a_change_draws_only_what_it_changes(
    client, seeded, app_settings, db_sessionmaker, drawn
):
    login(client)
    page = f"/patients/{seeded['patient_id']}"
    first = client.get(page)
    assert first.status_code == 200 and first.text.count('data-plot="trend"') == 5
    assert len(drawn) == 5 and len(_cache(app_settings).files()) == 5
    second = client.get(page)
    assert second.text == first.text and len(drawn) == 5  # read, not drawn
    # Another medication state for the first visit changes every point of it: all 5 again.
    with db_sessionmaker() as db:
        session = db.scalars(
            select(RecordingSession).where(RecordingSession.patient_id == seeded["patient_id"])
        ).first()
        session.medication_state = "on"
        db.commit()
    third = client.get(page)
    assert third.text != first.text and len(drawn) == 10
    assert len(_cache(app_settings).files()) == 10


def test_the_worker_draws_the_plots_the_page_then_reads(
    client, seeded, app_settings, db_sessionmaker, drawn
):
    sessions = db_sessionmaker
    storage = Storage.from_settings(app_settings)
    trial_id = seeded["trials"][(1, "right")]
    assert patients.draw_trend_plots(sessions, storage, trial_id, "UTC") == 5
    assert patients.draw_trend_plots(sessions, storage, trial_id, "UTC") == 0
    login(client)
    r = client.get(f"/patients/{seeded['patient_id']}")
    assert r.text.count('data-plot="trend"') == 5 and len(drawn) == 5  # none drawn by the page
    # A hidden trial's job draws nothing.
    with sessions() as db:
        db.get(Trial, trial_id).deleted_at = datetime.now(UTC)
        db.commit()
    _cache(app_settings).clear()
    assert patients.draw_trend_plots(sessions, storage, trial_id, "UTC") == 0


def test_erasing_the_patient_removes_their_plots(
    client, seeded, app_settings, db_sessionmaker, drawn
):
    from app.models import Patient
    from app.services.erasure import erase_patient

    cache = _cache(app_settings)
    other = cache.put(999, "a" * 64, "<svg>another patient's plot</svg>")
    storage = Storage.from_settings(app_settings)
    trial_id = seeded["trials"][(1, "right")]
    assert patients.draw_trend_plots(db_sessionmaker, storage, trial_id, "UTC") == 5
    with db_sessionmaker() as db:
        code = db.get(Patient, seeded["patient_id"]).code
        erase_patient(db, storage, None, code)
    assert cache.files() == [other]


@pytest.fixture
def erased_while_drawing(seeded, app_settings, db_sessionmaker, monkeypatch) -> list[bool]:
    """The seeded patient is erased while the first trend plot is drawn (after it is drawn,
    before it is kept); the list holds True once that happened."""
    from app.models import Patient
    from app.services.erasure import erase_patient

    storage = Storage.from_settings(app_settings)
    with db_sessionmaker() as db:
        code = db.get(Patient, seeded["patient_id"]).code
    draw = trend_cache_module.trend_plot
    erased: list[bool] = []

    def erased_meanwhile(points, **kw):
        svg = draw(points, **kw)
        if not erased:
            with db_sessionmaker() as db:
                erase_patient(db, storage, None, code)
            erased.append(True)
        return svg

    monkeypatch.setattr(trend_cache_module, "trend_plot", erased_meanwhile)
    return erased


def test_plots_drawn_while_their_patient_is_erased_remove_themselves(
    seeded, app_settings, db_sessionmaker, erased_while_drawing
):
    storage = Storage.from_settings(app_settings)
    trial_id = seeded["trials"][(1, "right")]
    assert patients.draw_trend_plots(db_sessionmaker, storage, trial_id, "UTC") == 5
    assert erased_while_drawing and _cache(app_settings).files() == []


def test_nothing_is_drawn_while_another_analysis_of_the_patient_is_pending(
    seeded, app_settings, db_sessionmaker, drawn
):
    """A batch of recordings: the plots are drawn once, by the last analysis's report job."""
    from app import jobs

    storage = Storage.from_settings(app_settings)
    trial_id = seeded["trials"][(1, "right")]
    with db_sessionmaker() as db, db.begin():
        job = jobs.enqueue(db, "analyze_trial", trial_id=seeded["trials"][(1, "left")])
    assert patients.draw_trend_plots(db_sessionmaker, storage, trial_id, "UTC") == 0
    assert drawn == []
    with db_sessionmaker() as db, db.begin():
        db.get(Job, job.id).status = "succeeded"
    assert patients.draw_trend_plots(db_sessionmaker, storage, trial_id, "UTC") == 5


def test_plots_the_page_draws_while_its_patient_is_erased_remove_themselves(
    client, seeded, app_settings, erased_while_drawing
):
    login(client)
    r = client.get(f"/patients/{seeded['patient_id']}")
    assert r.status_code == 200 and erased_while_drawing
    assert _cache(app_settings).files() == []

"""The clinic's time zone: typed and shown in it, stored in UTC, a visit is a local day."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest
from pydantic import ValidationError

from app.models import Patient, RecordingSession
from app.services.common import visit_sessions
from app.settings import Settings
from app.templating import jinja_env
from app.timezones import from_local


def test_typed_in_the_clinic_zone_stored_in_utc():
    assert from_local("2026-03-01T10:30", "Europe/Prague") == datetime(
        2026, 3, 1, 9, 30, tzinfo=UTC
    )
    assert from_local("2026-07-01T10:30", "Europe/Prague") == datetime(
        2026, 7, 1, 8, 30, tzinfo=UTC
    )
    assert from_local("2026-03-01T10:30", "UTC") == datetime(2026, 3, 1, 10, 30, tzinfo=UTC)
    with pytest.raises(ValueError):
        from_local("tomorrow", "UTC")


def test_shown_in_the_clinic_zone_with_its_name():
    when = datetime(2026, 3, 1, 9, 30, tzinfo=UTC)
    render = jinja_env.from_string("{{ t | datetime(tz) }}").render
    assert render(t=when, tz="Europe/Prague") == "2026-03-01 10:30 CET"
    assert render(t=when, tz="UTC") == "2026-03-01 09:30 UTC"


def test_a_time_without_a_zone_is_shown_in_the_page_s_clinic_zone():
    """A UI review found the review page's date (the UTC day) a day off the trial page's
    (the clinic's day), and the signature and hiding times in UTC unlabelled beside the
    clinic's. A filter without a zone takes the page's ``clinic_tz``, else UTC, and
    always names it."""
    late = datetime(2026, 3, 1, 23, 30, tzinfo=UTC)
    page = jinja_env.from_string("{{ t | date }} / {{ t | datetime }}").render
    assert page(t=late, clinic_tz="Pacific/Auckland") == "2026-03-02 / 2026-03-02 12:30 NZDT"
    assert page(t=late) == "2026-03-01 / 2026-03-01 23:30 UTC"


def test_an_unknown_zone_is_refused_with_a_message(tmp_path):
    with pytest.raises(ValidationError, match="not a time zone name"):
        Settings(data_dir=tmp_path, timezone="Mars/Olympus")
    assert Settings(data_dir=tmp_path).timezone == "UTC"


def test_a_visit_is_one_calendar_day_in_the_clinic_zone():
    # 23:30 UTC and 00:30 UTC the next day: one evening in Chicago, two days in UTC.
    late = RecordingSession(id=1, recorded_at=datetime(2026, 3, 1, 23, 30, tzinfo=UTC))
    later = RecordingSession(id=2, recorded_at=datetime(2026, 3, 2, 0, 30, tzinfo=UTC))
    Patient(code="PD-1", sessions=[late, later])
    assert [s.id for s in visit_sessions(late, "America/Chicago")] == [1, 2]
    assert [s.id for s in visit_sessions(late, "UTC")] == [1]

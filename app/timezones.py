"""The clinic's time zone: dates are entered and shown in it, and stored in UTC.

``Settings.timezone`` (``BRADYSCOPE_TIMEZONE``, an IANA name such as
``Europe/Prague``; default UTC) names it. A *visit* is the sessions of one
patient on one calendar day in this zone.
"""

from __future__ import annotations

from datetime import UTC, date, datetime
from zoneinfo import ZoneInfo


def to_zone(value: datetime, tz: str | None) -> datetime:
    """``value`` (aware; naive is read as UTC) in the time zone ``tz`` (None: unchanged)."""
    if value.tzinfo is None:
        value = value.replace(tzinfo=UTC)
    if tz is None:
        return value
    return value.astimezone(ZoneInfo(tz))


def local_date(value: datetime, tz: str) -> date:
    """The calendar day of ``value`` in the zone ``tz``."""
    return to_zone(value, tz).date()


def from_local(text: str, tz: str) -> datetime:
    """A date and time typed in the zone ``tz`` (ISO 8601, e.g. a ``datetime-local`` value), as UTC.

    A value that names its own offset keeps it. Raises ``ValueError`` when it is not a date.
    """
    when = datetime.fromisoformat(text.strip())
    if when.tzinfo is None:
        when = when.replace(tzinfo=ZoneInfo(tz))
    return when.astimezone(UTC)

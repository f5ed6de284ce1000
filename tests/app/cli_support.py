"""``bradyscope admin`` run in the test's own process against a test's settings (SQLite or
PostgreSQL), as an operator runs it: the data directory and the database from the
environment."""

from __future__ import annotations

import pytest

from app.cli import main
from app.settings import Settings


def admin_cli(settings: Settings, monkeypatch: pytest.MonkeyPatch, *args: str) -> int:
    """The exit status of ``bradyscope admin ARGS`` on ``settings``' data, database and
    retention period."""
    monkeypatch.setenv("BRADYSCOPE_DATA_DIR", str(settings.data_dir))
    for name, value in (
        ("BRADYSCOPE_DATABASE_URL", settings.database_url),
        ("BRADYSCOPE_RETENTION_DAYS", settings.retention_days),
    ):
        if value is None or value == "":
            monkeypatch.delenv(name, raising=False)
        else:
            monkeypatch.setenv(name, str(value))
    return main(["admin", *args])

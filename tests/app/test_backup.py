# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Backup -> wipe -> restore reproduces every row and every file byte for byte (issue 18).

On SQLite (online backup API) and PostgreSQL (pg_dump / pg_restore), through the
``bradyscope admin backup`` and ``restore`` commands. The data are made through the
API (patients, a rig-file calibration, a session, a trial with its two videos, a
result with its markers file, audit events) so that every table that holds
something is compared.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from api_support import (
    Api,
    add_result,
    make_api_key,
    seed_recording_target,
    trial_files,
    video_pair,  # noqa: F401
)
from cli_support import admin_cli
from conftest import PG_SERVER, create_pg_database, drop_pg_database
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, select, text

from app.chain import verify_chain
from app.db import dispose_engines, get_sessionmaker
from app.main import create_app
from app.models import Base
from app.settings import Settings


def _fill(settings: Settings, video_pair: tuple[Path, Path]) -> None:
    sessions = get_sessionmaker(settings)
    app = create_app(settings)
    with TestClient(app) as client:
        api = Api(app, client, settings, sessions, make_api_key(sessions))
        seeded = seed_recording_target(api)
        r = client.post(
            f"/api/v1/sessions/{seeded.session_id}/trials",
            data={"hand": "left"},
            files=trial_files(*video_pair),
            headers=api.headers,
        )
        assert r.status_code == 201, r.text
        add_result(api, r.json()["id"])
        assert (
            client.get(f"/api/v1/trials/{r.json()['id']}/result", headers=api.headers).status_code
            == 200
        )
        client.post("/api/v1/patients", json={"code": "PD-ÄÖ-2"}, headers=api.headers)


def _snapshot(settings: Settings) -> tuple[dict[str, list[tuple[Any, ...]]], dict[str, str]]:
    """Every row of every table (ordered by primary key) and every file's SHA-256."""
    rows: dict[str, list[tuple[Any, ...]]] = {}
    with get_sessionmaker(settings)() as db:
        for table in Base.metadata.sorted_tables:
            order = list(table.primary_key.columns)
            rows[table.name] = [tuple(r) for r in db.execute(select(table).order_by(*order))]
        rows["alembic_version"] = [
            tuple(r) for r in db.execute(text("SELECT * FROM alembic_version"))
        ]
    files = {
        p.relative_to(settings.data_dir).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted((settings.data_dir / "files").rglob("*"))
        if p.is_file()
    }
    return rows, files


def _round_trip(
    settings: Settings,
    backup_dir: Path,
    wipe: Any,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    rows_before, files_before = _snapshot(settings)
    assert rows_before["trials"] and rows_before["videos"] and rows_before["results"]
    assert rows_before["audit_events"] and len(files_before) == 3
    key_before = settings.audit_key_path.read_bytes()
    assert admin_cli(settings, monkeypatch, "backup", str(backup_dir)) == 0
    manifest = json.loads((backup_dir / "manifest.json").read_text())
    assert manifest["format"] == "bradyscope.backup/1"
    listed = {e["path"]: e["sha256"] for e in manifest["files"]}
    assert {k: v for k, v in listed.items() if k.startswith("files/")} == files_before
    # the backup's own audit event is written after the copy: compare from here on
    rows_before, files_before = _snapshot(settings)
    rows_before["audit_events"] = rows_before["audit_events"][:-1]

    dispose_engines()
    wipe()
    assert not (settings.data_dir / "files").exists()
    assert admin_cli(settings, monkeypatch, "restore", str(backup_dir)) == 0
    rows_after, files_after = _snapshot(settings)
    restore_event = rows_after["audit_events"].pop()  # the restore audits itself
    assert restore_event[4] == "restore"
    head = rows_after.pop("audit_head")
    rows_before.pop("audit_head")
    for table, before in rows_before.items():
        assert rows_after[table] == before, table
    assert head[0][1] == len(rows_before["audit_events"]) + 1
    assert files_after == files_before
    assert settings.audit_key_path.read_bytes() == key_before
    with get_sessionmaker(settings)() as db:
        assert verify_chain(db).ok  # the chain goes on across the restore
    # restoring again over data is refused without --force
    capsys.readouterr()
    assert admin_cli(settings, monkeypatch, "restore", str(backup_dir)) == 2
    assert "already holds data" in capsys.readouterr().err
    # ... and with --force, while the service runs (an operations review replaced the
    # database under two workers; one failed a trial on a file not yet copied back)
    from app.storage import hold_service_lock

    running = hold_service_lock(settings.data_dir)  # what a serve or a worker holds
    assert admin_cli(settings, monkeypatch, "restore", "--force", str(backup_dir)) == 2
    assert "bradyscope is running on" in capsys.readouterr().err
    running.close()
    if not settings.is_sqlite:  # a worker on another machine: its connection
        elsewhere = create_engine(str(settings.database_url))
        try:
            with elsewhere.connect():
                assert admin_cli(settings, monkeypatch, "restore", "--force", str(backup_dir)) == 2
            assert "other connection(s) to the database are open" in capsys.readouterr().err
        finally:
            elsewhere.dispose()
    dispose_engines()
    capsys.readouterr()
    status = admin_cli(settings, monkeypatch, "restore", "--force", str(backup_dir))
    assert status == 0, capsys.readouterr().err


def test_backup_wipe_restore_sqlite(
    app_settings: Settings,
    video_pair,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    _fill(app_settings, video_pair)

    def wipe() -> None:
        shutil.rmtree(app_settings.data_dir)

    _round_trip(app_settings, tmp_path / "backup", wipe, monkeypatch, capsys)


@pytest.mark.postgres
def test_backup_wipe_restore_postgres(
    pg_admin_url: str,
    pg_settings: Settings,
    video_pair,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    _fill(pg_settings, video_pair)
    url = str(pg_settings.database_url)

    def wipe() -> None:  # a new, empty database of the same name, and no data directory
        drop_pg_database(pg_admin_url, url)
        name = url.rsplit("/", 1)[1]
        import sqlalchemy as sa

        engine = sa.create_engine(pg_admin_url, isolation_level="AUTOCOMMIT")
        with engine.connect() as conn:
            conn.execute(sa.text(f'CREATE DATABASE "{name}"'))
        engine.dispose()
        shutil.rmtree(pg_settings.data_dir)

    _round_trip(pg_settings, tmp_path / "backup", wipe, monkeypatch, capsys)
    assert PG_SERVER and create_pg_database  # the conftest helpers used above


def test_a_damaged_backup_is_refused_before_anything_changes(
    app_settings: Settings,
    video_pair,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    _fill(app_settings, video_pair)
    backup_dir = tmp_path / "backup"
    assert admin_cli(app_settings, monkeypatch, "backup", str(backup_dir)) == 0
    victim = next((backup_dir / "files").rglob("*.csv"))
    victim.write_bytes(victim.read_bytes()[:-1] + b"X")
    dispose_engines()
    shutil.rmtree(app_settings.data_dir)
    capsys.readouterr()
    assert admin_cli(app_settings, monkeypatch, "restore", str(backup_dir)) == 2
    assert "damaged" in capsys.readouterr().err
    assert not (app_settings.data_dir / "bradyscope.sqlite3").exists()
    # a backup into a directory that holds something, or into the data directory, is refused
    assert admin_cli(app_settings, monkeypatch, "backup", str(backup_dir)) == 2
    assert admin_cli(app_settings, monkeypatch, "backup", str(app_settings.data_dir / "b")) == 2


def test_pg_tools_older_than_the_server_are_refused(
    app_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    from app import backup

    monkeypatch.setattr(backup, "_tool_major", lambda tool: 14)
    monkeypatch.setattr(backup, "_server_major", lambda settings: 16)
    with pytest.raises(backup.BackupError, match="postgresql-client-16"):
        backup.check_pg_tools(app_settings, "pg_dump")


def test_a_backup_that_does_not_fit_leaves_nothing_and_says_so(
    app_settings: Settings,
    video_pair,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """An operations review backed up onto a full disk: a traceback, and a directory
    holding the database and part of the files, which a second try refused as not empty."""
    import errno

    from app import backup

    _fill(app_settings, video_pair)
    real_copy = backup._copy
    copied: list[Path] = []

    def copy_until_full(src: Path, dst: Path):
        if copied:
            raise OSError(errno.ENOSPC, "No space left on device")
        copied.append(dst)
        return real_copy(src, dst)

    monkeypatch.setattr(backup, "_copy", copy_until_full)
    target = tmp_path / "backup"
    assert admin_cli(app_settings, monkeypatch, "backup", str(target)) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and "nothing was kept there" in err
    assert "Traceback" not in err and "\n" not in err.strip()
    assert target.is_dir() and list(target.iterdir()) == []
    monkeypatch.setattr(backup, "_copy", real_copy)
    assert admin_cli(app_settings, monkeypatch, "backup", str(target)) == 0  # the same place again

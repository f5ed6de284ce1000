"""`bradyscope admin` on a fresh data directory: users and API keys."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from sqlalchemy import select

from app.apikeys import hash_api_key, parse_api_key, verify_api_key
from app.cli import main
from app.db import dispose_engines, get_sessionmaker
from app.models import ApiClient, BrowserSession, User
from app.passwords import verify_password
from app.settings import Settings


@pytest.fixture
def fresh_dir(tmp_path, monkeypatch):
    data_dir = tmp_path / "fresh"
    monkeypatch.setenv("BRADYSCOPE_DATA_DIR", str(data_dir))
    monkeypatch.delenv("BRADYSCOPE_DATABASE_URL", raising=False)
    monkeypatch.delenv("BRADYSCOPE_PASSWORD", raising=False)
    yield data_dir
    dispose_engines()


def _db(data_dir):
    return get_sessionmaker(Settings(data_dir=data_dir))()


def test_the_data_directory_is_closed_to_other_users(fresh_dir, tmp_path):
    """A security review found the database, videos and reports readable by every local
    account (umask 022). ``admin`` closes the directory (files made before included);
    ``worker`` and ``serve`` also make every later file for their user only."""
    fresh_dir.mkdir(mode=0o755)
    (fresh_dir / "before.txt").write_text("x")
    assert main(["admin", "list-users"]) == 0
    assert fresh_dir.stat().st_mode & 0o777 == 0o700
    worker_dir = tmp_path / "worker"
    bin_dir = os.path.dirname(sys.executable)
    env = {**os.environ, "BRADYSCOPE_DATA_DIR": str(worker_dir)}
    proc = subprocess.run(
        [os.path.join(bin_dir, "bradyscope"), "worker", "--once"],
        env=env, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert worker_dir.stat().st_mode & 0o777 == 0o700
    made = [p for p in worker_dir.rglob("*") if p.is_file()]
    assert made and all(p.stat().st_mode & 0o077 == 0 for p in made), [
        (p.name, oct(p.stat().st_mode)) for p in made
    ]


def test_console_script_creates_user_on_fresh_data_dir(fresh_dir):
    env = {**os.environ, "BRADYSCOPE_PASSWORD": "amber kettle sunrise"}
    bin_dir = os.path.dirname(sys.executable)
    proc = subprocess.run(
        [
            os.path.join(bin_dir, "bradyscope"),
            "admin",
            "create-user",
            "Dr.Who@Clinic.org",
            "--role",
            "clinician",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    assert proc.returncode == 0, proc.stderr
    with _db(fresh_dir) as db:
        user = db.scalars(select(User)).one()
    assert (user.email, user.role, user.is_active) == ("dr.who@clinic.org", "clinician", True)
    assert user.password_hash.startswith("$argon2id$")
    assert verify_password(user.password_hash, "amber kettle sunrise")
    assert not verify_password(user.password_hash, "wrong kettle sunrise")


def test_duplicate_user_is_one_sentence_and_exit_2(fresh_dir, monkeypatch, capsys):
    monkeypatch.setenv("BRADYSCOPE_PASSWORD", "amber kettle sunrise")
    assert main(["admin", "create-user", "a@b.org", "--role", "admin"]) == 0
    assert main(["admin", "create-user", "A@B.org", "--role", "clinician"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("bradyscope admin: a user a@b.org already exists")
    assert "Traceback" not in capsys.readouterr().err


def test_missing_or_short_password_is_refused(fresh_dir, monkeypatch, capsys):
    monkeypatch.setattr(sys.stdin, "isatty", lambda: False, raising=False)  # no prompt
    assert main(["admin", "create-user", "a@b.org", "--role", "admin"]) == 2
    assert "BRADYSCOPE_PASSWORD" in capsys.readouterr().err
    monkeypatch.setenv("BRADYSCOPE_PASSWORD", "short")
    assert main(["admin", "create-user", "a@b.org", "--role", "admin"]) == 2
    assert "at least 15" in capsys.readouterr().err
    assert main(["admin", "create-user", "not-an-email", "--role", "admin"]) == 2


def test_password_is_prompted_twice_in_a_terminal(fresh_dir, monkeypatch):
    import getpass

    answers = iter(["prompted violet harbour", "prompted violet harbour"])
    monkeypatch.setattr(getpass, "getpass", lambda prompt="": next(answers))
    monkeypatch.setattr(sys.stdin, "isatty", lambda: True, raising=False)
    assert main(["admin", "create-user", "p@b.org", "--role", "clinician"]) == 0
    with _db(fresh_dir) as db:
        assert verify_password(
            db.scalars(select(User)).one().password_hash, "prompted violet harbour"
        )


def test_api_key_is_printed_once_and_only_its_hash_stored(fresh_dir, capsys):
    assert main(["admin", "create-api-key", "his-gateway", "--scopes", "results:read"]) == 0
    out, err = capsys.readouterr()
    key = out.strip()
    assert out.count("\n") == 1 and parse_api_key(key) is not None
    assert key not in err
    with _db(fresh_dir) as db:
        client = db.scalars(select(ApiClient)).one()
    assert client.name == "his-gateway" and client.scopes == ["results:read"]
    assert client.key_prefix == parse_api_key(key)
    assert client.key_hash == hash_api_key(key) and verify_api_key(key, client.key_hash)
    assert key not in (client.key_hash, client.key_prefix)
    assert client.revoked_at is None

    assert main(["admin", "create-api-key", "his-gateway"]) == 2  # names are unique
    assert main(["admin", "revoke-api-key", "his-gateway"]) == 0
    with _db(fresh_dir) as db:
        assert db.scalars(select(ApiClient)).one().revoked_at is not None
    capsys.readouterr()
    assert main(["admin", "list-api-keys"]) == 0
    listing = capsys.readouterr().out
    assert "his-gateway" in listing and "revoked" in listing and key not in listing


def test_two_keys_differ(fresh_dir, capsys):
    main(["admin", "create-api-key", "a"])
    main(["admin", "create-api-key", "b"])
    keys = [line for line in capsys.readouterr().out.splitlines() if line.startswith("bsk_")]
    assert len(set(keys)) == 2


def test_set_password_replaces_hash(fresh_dir, monkeypatch):
    monkeypatch.setenv("BRADYSCOPE_PASSWORD", "first copper lantern")
    main(["admin", "create-user", "a@b.org", "--role", "admin"])
    monkeypatch.setenv("BRADYSCOPE_PASSWORD", "second walnut meadow")
    assert main(["admin", "set-password", "a@b.org"]) == 0
    with _db(fresh_dir) as db:
        assert verify_password(db.scalars(select(User)).one().password_hash, "second walnut meadow")
    assert main(["admin", "set-password", "nobody@b.org"]) == 2


def test_set_password_logs_the_user_out_of_every_browser(fresh_dir, monkeypatch):
    from app.auth import authenticate_session_cookie
    from app.login import login_user

    monkeypatch.setenv("BRADYSCOPE_PASSWORD", "first copper lantern")
    main(["admin", "create-user", "a@b.org", "--role", "clinician"])
    main(["admin", "create-user", "c@b.org", "--role", "clinician"])
    settings = Settings(data_dir=fresh_dir)
    with _db(fresh_dir) as db:
        tokens = [
            login_user(db, settings=settings, email=email, password="first copper lantern").token
            for email in ("a@b.org", "a@b.org", "c@b.org")
        ]
        assert all(authenticate_session_cookie(db, t) is not None for t in tokens)
        db.commit()
    monkeypatch.setenv("BRADYSCOPE_PASSWORD", "second walnut meadow")
    assert main(["admin", "set-password", "a@b.org"]) == 0
    with _db(fresh_dir) as db:
        assert [row.user.email for row in db.scalars(select(BrowserSession))] == ["c@b.org"]
        assert [authenticate_session_cookie(db, t) is not None for t in tokens] == [
            False,
            False,
            True,  # another user's browser stays logged in
        ]


def test_check_migrations_passes_on_a_fresh_data_dir(fresh_dir, capsys):
    assert main(["admin", "check-migrations"]) == 0
    assert "agree" in capsys.readouterr().err


def test_the_access_log_keeps_no_query_string():
    """A query can hold a patient code (``/patients?q=``) or a clinician's words
    (``?reason=``): the access log, which outlives an erasure, keeps the path only."""
    import logging

    from app.cli.serve import uvicorn_config

    uvicorn_config(object(), host="127.0.0.1", port=1)
    records: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: records.append(record.getMessage())  # type: ignore[method-assign]
    access = logging.getLogger("uvicorn.access")
    access.addHandler(handler)
    try:
        access.info(
            '%s - "%s %s HTTP/%s" %d', "127.0.0.1:5", "GET", "/patients?q=DEMO-7", "1.1", 200
        )
    finally:
        access.removeHandler(handler)
    assert records == ['127.0.0.1:5 - "GET /patients HTTP/1.1" 200']


def test_admin_takes_the_data_directory_after_its_action_too(tmp_path, monkeypatch, capsys):
    """An operations review: 'admin create-api-key qa --data-dir X' was refused; and
    'admin migrate' printed nothing on success."""
    monkeypatch.delenv("BRADYSCOPE_DATABASE_URL", raising=False)
    monkeypatch.delenv("BRADYSCOPE_DATA_DIR", raising=False)
    after = tmp_path / "after"
    assert main(["admin", "migrate", "--data-dir", str(after)]) == 0
    assert (after / "bradyscope.sqlite3").is_file()
    assert "is at revision" in capsys.readouterr().err
    before = tmp_path / "before"
    assert main(["admin", "--data-dir", str(before), "list-users"]) == 0
    assert (before / "bradyscope.sqlite3").is_file()
    dispose_engines()

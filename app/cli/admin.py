"""`bradyscope admin`: users, API keys and the database (INTERFACES.md).

Every sub-command first brings the database to the newest migration (under the
start-up lock), so it works on a fresh data directory.

- ``create-user EMAIL --role clinician|admin``: the password comes from
  ``BRADYSCOPE_PASSWORD`` or is asked twice at the prompt (never an argument,
  which would end up in the shell history).
- ``set-password EMAIL``: same password sources; re-activates the account,
  ends its browser sessions and lifts any login delay or lock.
- ``list-users``, ``deactivate-user EMAIL`` (ends its sessions; its API keys
  stop working), ``set-role EMAIL ROLE``, ``unlock EMAIL`` (lifts the login
  delays and lock of an account, from every address).
- ``create-api-key NAME [--scopes S ...] [--owner EMAIL] [--expires-days N]``:
  prints the new key once, on stdout; only its hash is stored.
- ``revoke-api-key NAME``, ``list-api-keys`` (owner, expiry, last use), ``migrate``.
- ``check-migrations``: exit 2 if ``app/models.py`` and ``migrations/`` disagree
  (``alembic check`` against the migrated database).
- ``export-audit [--since ISO]``: the audit trail as JSON lines on stdout;
  ``verify-audit``: recompute its hash chain (exit 2 when it was tampered with).
- ``erase-patient CODE``, ``apply-retention [--dry-run]``: erase a patient's
  data (``app.services.erasure``).
- ``backup DIR``, ``restore DIR [--force]``: ``app.backup``. ``restore`` does not
  migrate first (the backup brings its own schema); it migrates afterwards.
"""

from __future__ import annotations

import argparse
import getpass
import os
import re
import sys
from datetime import timedelta
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.errors import ConflictError, InvalidRequestError, NotFoundError
from app.settings import Settings, settings_with

if TYPE_CHECKING:
    from app.audit import SystemActor
    from app.models import User

_EMAIL_RE = re.compile(r"^[^@\s]+@[^@\s]+\.[^@\s]+$")
PASSWORD_ENV = "BRADYSCOPE_PASSWORD"


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from app.apikeys import DEFAULT_SCOPES, SCOPES
    from app.models import ROLES

    p = sub.add_parser("admin", help="create users and API keys; migrate the database")
    p.add_argument(
        "--data-dir", type=Path, default=None, help="overrides BRADYSCOPE_DATA_DIR (default ./data)"
    )
    asub = p.add_subparsers(dest="admin_command", required=True, metavar="ACTION")

    u = asub.add_parser("create-user", help="create a clinician or admin account")
    u.add_argument("email")
    u.add_argument("--role", choices=ROLES, required=True)
    u.add_argument("--name", default=None, help="display name")
    u.set_defaults(admin_func=create_user)

    pw = asub.add_parser("set-password", help="set a user's password (and re-activate them)")
    pw.add_argument("email")
    pw.set_defaults(admin_func=set_password)

    lu = asub.add_parser("list-users", help="list accounts: role, state, last login, login delays")
    lu.set_defaults(admin_func=list_users)

    du = asub.add_parser(
        "deactivate-user", help="deactivate an account (logs it out; its API keys stop working)"
    )
    du.add_argument("email")
    du.set_defaults(admin_func=deactivate_user)

    sr = asub.add_parser("set-role", help="change an account's role")
    sr.add_argument("email")
    sr.add_argument("role", choices=ROLES)
    sr.set_defaults(admin_func=set_role)

    ul = asub.add_parser("unlock", help="lift the login delays and lock of an account")
    ul.add_argument("email")
    ul.set_defaults(admin_func=unlock_user)

    k = asub.add_parser("create-api-key", help="create an API client; prints its key once")
    k.add_argument("name")
    k.add_argument(
        "--owner", default=None, metavar="EMAIL", help="the user answerable for this key"
    )
    k.add_argument(
        "--expires-days",
        type=int,
        default=None,
        metavar="N",
        help="the key stops working after N days (default BRADYSCOPE_API_KEY_DAYS, 365)",
    )
    k.add_argument(
        "--scopes",
        nargs="+",
        choices=SCOPES,
        default=list(DEFAULT_SCOPES),
        metavar="SCOPE",
        help=f"granted scopes among {', '.join(SCOPES)} (default: {', '.join(DEFAULT_SCOPES)})",
    )
    k.set_defaults(admin_func=create_api_key)

    r = asub.add_parser("revoke-api-key", help="revoke an API client's key")
    r.add_argument("name")
    r.set_defaults(admin_func=revoke_api_key)

    ls = asub.add_parser("list-api-keys", help="list API clients (never their keys)")
    ls.set_defaults(admin_func=list_api_keys)

    m = asub.add_parser("migrate", help="bring the database to the newest migration")
    m.set_defaults(admin_func=lambda settings, args: 0)

    c = asub.add_parser(
        "check-migrations", help="fail if the models and the migrations disagree (alembic check)"
    )
    c.set_defaults(admin_func=check_migrations)

    ea = asub.add_parser("export-audit", help="write the audit trail as JSON lines to stdout")
    ea.add_argument(
        "--since", default=None, metavar="ISO", help="only events at or after this time (UTC)"
    )
    ea.set_defaults(admin_func=export_audit)

    va = asub.add_parser("verify-audit", help="check the audit trail's hash chain")
    va.set_defaults(admin_func=verify_audit)

    ep = asub.add_parser(
        "erase-patient", help="erase a patient's videos, results and records (audit kept)"
    )
    ep.add_argument("code")
    ep.set_defaults(admin_func=erase_patient)

    ar = asub.add_parser(
        "apply-retention",
        help="erase every patient past BRADYSCOPE_RETENTION_DAYS since their last recording",
    )
    ar.add_argument("--dry-run", action="store_true", help="only list who would be erased")
    ar.set_defaults(admin_func=apply_retention)

    bk = asub.add_parser("backup", help="back up the database and the stored files into DIR")
    bk.add_argument("directory", type=Path, metavar="DIR")
    bk.set_defaults(admin_func=backup)

    rs = asub.add_parser("restore", help="restore a backup made with 'admin backup'")
    rs.add_argument("directory", type=Path, metavar="DIR")
    rs.add_argument(
        "--force",
        action="store_true",
        help="replace a database and data directory that already hold data",
    )
    rs.set_defaults(admin_func=restore, migrate_first=False)

    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.db import migrate

    settings = settings_with(data_dir=args.data_dir)
    if getattr(args, "migrate_first", True):
        migrate(settings)
    return int(args.admin_func(settings, args) or 0)


def _read_password(settings: Settings, email: str) -> str:
    from app.passwords import check_password_strength

    password = os.environ.get(PASSWORD_ENV)
    if password is None:
        if not sys.stdin.isatty():
            raise InvalidRequestError(
                f"no password given; set {PASSWORD_ENV} or run the command in a terminal."
            )
        password = getpass.getpass("Password: ")
        if getpass.getpass("Repeat the password: ") != password:
            raise InvalidRequestError("the two passwords differ; run the command again.")
    check_password_strength(password, email=email, min_length=settings.password_min_length)
    return password


def cli_actor() -> SystemActor:
    """Who acts on the command line: the system, named after the operating-system user."""
    from app.audit import SystemActor

    try:
        who = getpass.getuser()
    except (KeyError, OSError):
        who = str(os.getuid())
    return SystemActor(f"cli:{who}"[:64])


def _normal_email(email: str) -> str:
    email = email.strip().lower()
    if not _EMAIL_RE.match(email):
        raise InvalidRequestError(f"{email!r} is not an e-mail address; give one like a@b.org.")
    return email


def create_user(settings: Settings, args: argparse.Namespace) -> int:
    from app.db import session_scope
    from app.models import User
    from app.passwords import hash_password

    email = _normal_email(args.email)
    password = _read_password(settings, email)
    try:
        with session_scope(settings) as db:
            if db.scalar(select(User.id).where(User.email == email)) is not None:
                raise ConflictError(
                    f"a user {email} already exists; use 'bradyscope admin set-password {email}'."
                )
            db.add(
                User(
                    email=email,
                    password_hash=hash_password(password),
                    role=args.role,
                    display_name=args.name,
                )
            )
    except IntegrityError as exc:  # created concurrently by someone else
        raise ConflictError(f"a user {email} already exists.") from exc
    print(f"created {args.role} {email}", file=sys.stderr)
    return 0


def _user(db: Session, email: str) -> User:
    from app.models import User

    user = db.scalars(select(User).where(User.email == email)).first()
    if user is None:
        raise NotFoundError(f"there is no user {email}; create it with 'admin create-user'.")
    return user


def _end_sessions(db: Session, user_id: int) -> int:
    from app.models import BrowserSession

    rows = list(db.scalars(select(BrowserSession).where(BrowserSession.user_id == user_id)))
    for row in rows:
        db.delete(row)
    return len(rows)


def _audit_admin(db: Session, action: str, user_id: int) -> None:
    """An account change made on the command line, in the audit trail (actor: system)."""
    from app.audit import audit

    audit(db, cli_actor(), action, "user", user_id)


def set_password(settings: Settings, args: argparse.Namespace) -> int:
    from app import throttle
    from app.db import session_scope
    from app.passwords import hash_password

    email = _normal_email(args.email)
    password = _read_password(settings, email)
    with session_scope(settings) as db:
        user = _user(db, email)
        user.password_hash = hash_password(password)
        user.is_active = True
        # Log the user out everywhere: the old password may be known to someone else.
        _end_sessions(db, user.id)
        # Guesses at the old password say nothing about the new one.
        throttle.unlock(db, email)
        _audit_admin(db, "set_password", user.id)
    print(f"password of {email} changed", file=sys.stderr)
    return 0


def list_users(settings: Settings, args: argparse.Namespace) -> int:
    from app import throttle
    from app.db import session_scope
    from app.models import User, utcnow

    now = utcnow()
    with session_scope(settings) as db:
        print("email\trole\tstate\tlast login\tlogin throttle")
        for user in db.scalars(select(User).order_by(User.email)):
            state = "active" if user.is_active else "deactivated"
            last = f"{user.last_login_at:%Y-%m-%d %H:%M}" if user.last_login_at else "never"
            streak = throttle.account_state(db, settings, user.email)
            if streak is None or streak.failures == 0:
                held = "-"
            elif streak.locked:
                held = f"LOCKED after {streak.failures} failures (admin unlock)"
            elif streak.blocked_until is not None and streak.blocked_until > now:
                held = (
                    f"{streak.failures} failures, waits until {streak.blocked_until:%H:%M:%S} UTC"
                )
            else:
                held = f"{streak.failures} failures"
            print(f"{user.email}\t{user.role}\t{state}\t{last}\t{held}")
    return 0


def deactivate_user(settings: Settings, args: argparse.Namespace) -> int:
    from app.db import session_scope

    email = _normal_email(args.email)
    with session_scope(settings) as db:
        user = _user(db, email)
        user.is_active = False
        ended = _end_sessions(db, user.id)
        _audit_admin(db, "deactivate", user.id)
    print(
        f"{email} deactivated ({ended} browser session(s) ended; API keys it owns stop working);"
        " 'admin set-password' re-activates it",
        file=sys.stderr,
    )
    return 0


def set_role(settings: Settings, args: argparse.Namespace) -> int:
    from app.db import session_scope

    email = _normal_email(args.email)
    with session_scope(settings) as db:
        user = _user(db, email)
        before = user.role
        user.role = args.role
        # A role change takes effect at once: the sessions carry the old scopes' CSRF state.
        _end_sessions(db, user.id)
        _audit_admin(db, f"set_role:{args.role}", user.id)
    print(f"{email}: role {before} -> {args.role} (logged out everywhere)", file=sys.stderr)
    return 0


def unlock_user(settings: Settings, args: argparse.Namespace) -> int:
    from app import throttle
    from app.db import session_scope
    from app.models import User

    email = _normal_email(args.email)
    with session_scope(settings) as db:
        removed = throttle.unlock(db, email)
        user = db.scalars(select(User).where(User.email == email)).first()
        if user is not None:
            _audit_admin(db, "unlock", user.id)
    what = "lifted" if removed else "none was held"
    print(f"login delays and lock of {email}: {what}", file=sys.stderr)
    return 0


def create_api_key(settings: Settings, args: argparse.Namespace) -> int:
    from app.apikeys import generate_api_key, hash_api_key
    from app.db import session_scope
    from app.models import ApiClient, utcnow

    name = args.name.strip()
    if not name or len(name) > 100:
        raise InvalidRequestError("give the API client a name of 1 to 100 characters.")
    days = settings.api_key_days if args.expires_days is None else args.expires_days
    if not 1 <= days <= 3650:
        raise InvalidRequestError("--expires-days must be between 1 and 3650.")
    expires_at = utcnow() + timedelta(days=days)
    key, prefix = generate_api_key()
    try:
        with session_scope(settings) as db:
            owner_id = _user(db, _normal_email(args.owner)).id if args.owner else None
            if db.scalar(select(ApiClient.id).where(ApiClient.name == name)) is not None:
                raise ConflictError(
                    f"an API client named {name!r} already exists; choose another name or "
                    "revoke it first."
                )
            client = ApiClient(
                name=name,
                key_prefix=prefix,
                key_hash=hash_api_key(key),
                scopes=sorted(set(args.scopes)),
                owner_user_id=owner_id,
                expires_at=expires_at,
            )
            db.add(client)
            db.flush()
            from app.audit import audit

            audit(db, cli_actor(), "create", "api_client", client.id)
    except IntegrityError as exc:
        raise ConflictError(f"an API client named {name!r} already exists.") from exc
    print(key)
    print(
        f"API key for {name!r} (scopes: {', '.join(sorted(set(args.scopes)))}), valid until"
        f" {expires_at:%Y-%m-%d}. It is shown only now; store it safely.",
        file=sys.stderr,
    )
    return 0


def revoke_api_key(settings: Settings, args: argparse.Namespace) -> int:
    from app.db import session_scope
    from app.models import ApiClient, utcnow

    with session_scope(settings) as db:
        client = db.scalars(select(ApiClient).where(ApiClient.name == args.name)).first()
        if client is None:
            raise NotFoundError(f"there is no API client named {args.name!r}.")
        if client.revoked_at is None:
            client.revoked_at = utcnow()
            from app.audit import audit

            audit(db, cli_actor(), "revoke", "api_client", client.id)
    print(f"API key of {args.name!r} revoked", file=sys.stderr)
    return 0


def list_api_keys(settings: Settings, args: argparse.Namespace) -> int:
    from app.db import session_scope
    from app.models import ApiClient, User, utcnow

    now = utcnow()
    with session_scope(settings) as db:
        print("name\tkey\tstate\towner\texpires\tlast used\tscopes")
        for c in db.scalars(select(ApiClient).order_by(ApiClient.name)):
            if c.revoked_at:
                state = f"revoked {c.revoked_at:%Y-%m-%d}"
            elif c.expires_at is not None and c.expires_at <= now:
                state = "expired"
            else:
                state = "active"
            owner = db.get(User, c.owner_user_id) if c.owner_user_id else None
            owner_text = (
                "-"
                if owner is None
                else owner.email + ("" if owner.is_active else " (deactivated)")
            )
            expires = f"{c.expires_at:%Y-%m-%d}" if c.expires_at else "never"
            used = f"{c.last_used_at:%Y-%m-%d %H:%M}" if c.last_used_at else "never"
            print(
                f"{c.name}\tbsk_{c.key_prefix}_…\t{state}\t{owner_text}\t{expires}\t{used}"
                f"\t{' '.join(c.scopes)}"
            )
    return 0


def check_migrations(settings: Settings, args: argparse.Namespace) -> int:
    from alembic import command
    from alembic.util.exc import AutogenerateDiffsDetected

    from app.db import alembic_config
    from app.errors import AppError

    try:
        command.check(alembic_config(settings.effective_database_url, stdout=sys.stderr))
    except AutogenerateDiffsDetected as exc:
        raise AppError(
            f"the models differ from the migrations ({exc}); write a migration for the change."
        ) from exc
    print("models and migrations agree", file=sys.stderr)
    return 0


def export_audit(settings: Settings, args: argparse.Namespace) -> int:
    import json

    from app.audit import audit
    from app.db import session_scope
    from app.services import audit_log

    since = audit_log.parse_time(args.since, "--since") if args.since else None
    f = audit_log.make_filter(since=since)
    count = 0
    with session_scope(settings) as db:
        for event in audit_log.iter_events(db, f):
            sys.stdout.write(json.dumps(audit_log.as_document(event), ensure_ascii=False) + "\n")
            count += 1
        audit(db, cli_actor(), "export", "audit")
    sys.stdout.flush()
    print(f"{count} audit events exported", file=sys.stderr)
    return 0


def verify_audit(settings: Settings, args: argparse.Namespace) -> int:
    from app.chain import verify_chain
    from app.db import session_scope
    from app.errors import AppError

    with session_scope(settings) as db:
        report = verify_chain(db)
    if report.unchained_before:
        print(
            f"{report.unchained_before} events from before the chain began are not sealed.",
            file=sys.stderr,
        )
    if not report.ok:
        for problem in report.problems:
            print(f"  {problem}", file=sys.stderr)
        raise AppError(
            f"the audit trail was tampered with: {len(report.problems)} problem(s) above;"
            " restore the database from a backup and investigate."
        )
    print(
        f"audit trail intact: {report.chained} chained events; head {report.head_seq}"
        f" {report.head_hash} (note it elsewhere to detect a truncation later)"
    )
    return 0


def erase_patient(settings: Settings, args: argparse.Namespace) -> int:
    from app.db import session_scope
    from app.services.erasure import erase_patient as erase
    from app.storage import Storage

    with session_scope(settings) as db:
        report = erase(db, Storage.from_settings(settings), cli_actor(), args.code.strip())
    rows = ", ".join(f"{n} {table}" for table, n in sorted(report.rows.items())) or "no rows"
    print(
        f"patient {args.code.strip()} erased (id {report.patient_id}): {rows};"
        f" {report.files_removed} files removed"
        + (f", {report.files_missing} already missing" if report.files_missing else ""),
        file=sys.stderr,
    )
    return 0


def apply_retention(settings: Settings, args: argparse.Namespace) -> int:
    from app.db import session_scope
    from app.services.erasure import apply_retention as retention
    from app.storage import Storage

    if settings.retention_days is None:
        raise InvalidRequestError(
            "no retention period is set; set BRADYSCOPE_RETENTION_DAYS (e.g. 3650) first."
        )
    with session_scope(settings) as db:
        done = retention(
            db,
            Storage.from_settings(settings),
            cli_actor(),
            settings.retention_days,
            dry_run=args.dry_run,
        )
    verb = "would be erased" if args.dry_run else "erased"
    print(
        f"{len(done)} patient(s) {verb} (retention {settings.retention_days} days)", file=sys.stderr
    )
    return 0


def backup(settings: Settings, args: argparse.Namespace) -> int:
    from app.audit import audit
    from app.backup import backup as make_backup
    from app.db import session_scope

    summary = make_backup(settings, args.directory)
    with session_scope(settings) as db:
        audit(db, cli_actor(), "backup", "database")
    print(
        f"backup of the {summary.database} database (revision {summary.revision}) and"
        f" {summary.files - 1} files, {summary.size_bytes / 1e6:.1f} MB, in {summary.directory}",
        file=sys.stderr,
    )
    return 0


def restore(settings: Settings, args: argparse.Namespace) -> int:
    from app.audit import audit
    from app.backup import restore as put_back
    from app.db import session_scope

    summary = put_back(settings, args.directory, force=args.force)
    with session_scope(settings) as db:
        audit(db, cli_actor(), "restore", "database")
    print(
        f"restored {summary.files} files ({summary.size_bytes / 1e6:.1f} MB) into"
        f" {settings.data_dir}; database at revision {summary.revision}",
        file=sys.stderr,
    )
    return 0

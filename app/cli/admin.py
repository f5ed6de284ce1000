"""`bradyscope admin`: users, API keys and the database (INTERFACES.md).

Every sub-command first brings the database to the newest migration (under the
start-up lock), so it works on a fresh data directory.

- ``create-user EMAIL --role clinician|admin|auditor``: the password comes from
  ``BRADYSCOPE_PASSWORD`` or is asked twice at the prompt (never an argument,
  which would end up in the shell history).
- ``set-password EMAIL``: same password sources; re-activates the account,
  ends its browser sessions and lifts any login delay or lock.
- ``list-users``, ``deactivate-user EMAIL`` (ends its sessions; its API keys
  stop working), ``set-role EMAIL ROLE``, ``unlock EMAIL`` (lifts the login
  delays and lock of an account, from every address).
- ``create-api-key NAME [--scopes S ...] [--owner EMAIL] [--expires-days N]``:
  prints the new key once, on stdout; only its hash is stored. An owned key may
  not hold a scope its owner's role lacks, and at each use works with only those
  its owner's role holds then (``set-role`` narrows it at once).
- ``revoke-api-key NAME``, ``list-api-keys`` (owner, expiry, last use).
- The record as a whole (``migrate``, ``check-migrations``, ``export-audit``,
  ``verify-audit``, ``erase-patient``, ``apply-retention``, ``backup``,
  ``restore``): :mod:`app.cli.admin_records`.
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

from app.cli import admin_records
from app.cli.admin_records import cli_actor
from app.errors import ConflictError, InvalidRequestError, NotFoundError
from app.settings import Settings, settings_with

if TYPE_CHECKING:
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

    u = asub.add_parser("create-user", help="create a clinician, admin or auditor account")
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
        default=None,
        metavar="SCOPE",
        help=f"granted scopes among {', '.join(SCOPES)} (default: {', '.join(DEFAULT_SCOPES)},"
        " those of them the owner's role holds when there is an owner); an owned key never"
        " does more than its owner's role",
    )
    k.set_defaults(admin_func=create_api_key)

    r = asub.add_parser("revoke-api-key", help="revoke an API client's key")
    r.add_argument("name")
    r.set_defaults(admin_func=revoke_api_key)

    ls = asub.add_parser("list-api-keys", help="list API clients (never their keys)")
    ls.set_defaults(admin_func=list_api_keys)

    admin_records.register(asub)
    for action in asub.choices.values():  # also after the action: admin ACTION --data-dir D
        action.add_argument(
            "--data-dir", type=Path, default=argparse.SUPPRESS, help=argparse.SUPPRESS
        )

    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.db import migrate
    from app.storage import close_to_others

    settings = settings_with(data_dir=args.data_dir)
    close_to_others(settings.data_dir, umask=False)
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
            user = User(
                email=email,
                password_hash=hash_password(password),
                role=args.role,
                display_name=args.name,
            )
            db.add(user)
            db.flush()
            _audit_admin(db, "create", user.id)
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
        narrowed = _narrowed_keys(db, user)
    print(f"{email}: role {before} -> {args.role} (logged out everywhere)", file=sys.stderr)
    for line in narrowed:
        print(line, file=sys.stderr)
    return 0


def _narrowed_keys(db: Session, owner: User) -> list[str]:
    """A line per active API key of ``owner`` holding scopes the owner's role lacks: the
    key keeps them stored but works without them from its next request on."""
    from app.auth import owned_key_scopes
    from app.models import ApiClient

    lines = []
    keys = db.scalars(
        select(ApiClient).where(ApiClient.owner_user_id == owner.id, ApiClient.revoked_at.is_(None))
    )
    for key in keys:
        allowed = owned_key_scopes(key.scopes, owner.role)
        lacking = sorted(set(key.scopes) - allowed)
        if lacking:
            lines.append(
                f"API key {key.name!r}: works without {', '.join(lacking)} from now on (scopes:"
                f" {', '.join(sorted(allowed)) or 'none'})"
            )
    return lines


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


def _key_scopes(requested: list[str] | None, owner: User | None) -> list[str]:
    """The scopes of a new key: those asked for (or the default ones), sorted. A key with an
    owner may not hold a scope the owner's role lacks (it would never work: see
    :func:`app.auth.owned_key_scopes`); asked for, that is refused; by default, such
    scopes are left out, and a role holding none of the defaults must name its scopes."""
    from app.apikeys import DEFAULT_SCOPES
    from app.auth import owned_key_scopes

    scopes = sorted(set(requested if requested is not None else DEFAULT_SCOPES))
    if owner is None:
        return scopes
    allowed = owned_key_scopes(scopes, owner.role)
    lacking = [s for s in scopes if s not in allowed]
    if requested is not None and lacking:
        raise InvalidRequestError(
            f"the owner {owner.email} has the role {owner.role}, which lacks"
            f" {', '.join(lacking)}; a key never does more than its owner, so give only"
            " scopes the role holds (or another owner)."
        )
    if not allowed:
        raise InvalidRequestError(
            f"the owner {owner.email} has the role {owner.role}, which holds none of the"
            " default scopes; name the key's scopes with --scopes (an auditor's key:"
            " --scopes audit:read)."
        )
    return sorted(allowed)


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
            owner = _user(db, _normal_email(args.owner)) if args.owner else None
            scopes = _key_scopes(args.scopes, owner)
            if db.scalar(select(ApiClient.id).where(ApiClient.name == name)) is not None:
                raise ConflictError(
                    f"an API client named {name!r} already exists; choose another name or "
                    "revoke it first."
                )
            client = ApiClient(
                name=name,
                key_prefix=prefix,
                key_hash=hash_api_key(key),
                scopes=scopes,
                owner_user_id=owner.id if owner is not None else None,
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
        f"API key for {name!r} (scopes: {', '.join(scopes)}), valid until"
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
    from app.auth import owned_key_scopes
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
            scopes = " ".join(c.scopes)
            if owner is not None:  # what the owner's role lacks does not work
                allowed = owned_key_scopes(c.scopes, owner.role)
                scopes = " ".join(
                    x if x in allowed else f"({x}: not {owner.role})" for x in c.scopes
                )
            print(
                f"{c.name}\tbsk_{c.key_prefix}_…\t{state}\t{owner_text}\t{expires}\t{used}"
                f"\t{scopes}"
            )
    return 0

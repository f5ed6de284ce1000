"""`bradyscope admin`: users, API keys and the database (INTERFACES.md).

Every sub-command first brings the database to the newest migration (under the
start-up lock), so it works on a fresh data directory.

- ``create-user EMAIL --role clinician|admin``: the password comes from
  ``BRADYSCOPE_PASSWORD`` or is asked twice at the prompt (never an argument,
  which would end up in the shell history).
- ``set-password EMAIL``: same password sources.
- ``create-api-key NAME [--scopes S ...]``: prints the new key once, on stdout;
  only its hash is stored.
- ``revoke-api-key NAME``, ``list-api-keys``, ``migrate``.
- ``check-migrations``: exit 2 if ``app/models.py`` and ``migrations/`` disagree
  (``alembic check`` against the migrated database).
"""

from __future__ import annotations

import argparse
import getpass
import os
import re
import sys
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from app.errors import ConflictError, InvalidRequestError, NotFoundError
from app.settings import Settings, settings_with

_EMAIL_RE = re.compile(r"^[^@\s]+@[^@\s]+\.[^@\s]+$")
PASSWORD_ENV = "BRADYSCOPE_PASSWORD"


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from app.apikeys import SCOPES
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

    k = asub.add_parser("create-api-key", help="create an API client; prints its key once")
    k.add_argument("name")
    k.add_argument(
        "--scopes",
        nargs="+",
        choices=SCOPES,
        default=list(SCOPES),
        metavar="SCOPE",
        help=f"granted scopes (default: all of {', '.join(SCOPES)})",
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

    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.db import migrate

    settings = settings_with(data_dir=args.data_dir)
    migrate(settings)
    return int(args.admin_func(settings, args) or 0)


def _read_password() -> str:
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
    check_password_strength(password)
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
    password = _read_password()
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


def set_password(settings: Settings, args: argparse.Namespace) -> int:
    from app.db import session_scope
    from app.models import BrowserSession, User
    from app.passwords import hash_password

    email = _normal_email(args.email)
    password = _read_password()
    with session_scope(settings) as db:
        user = db.scalars(select(User).where(User.email == email)).first()
        if user is None:
            raise NotFoundError(f"there is no user {email}; create it with 'admin create-user'.")
        user.password_hash = hash_password(password)
        user.is_active = True
        # Log the user out everywhere: the old password may be known to someone else.
        for session in db.scalars(select(BrowserSession).where(BrowserSession.user_id == user.id)):
            db.delete(session)
    print(f"password of {email} changed", file=sys.stderr)
    return 0


def create_api_key(settings: Settings, args: argparse.Namespace) -> int:
    from app.apikeys import generate_api_key, hash_api_key
    from app.db import session_scope
    from app.models import ApiClient

    name = args.name.strip()
    if not name or len(name) > 100:
        raise InvalidRequestError("give the API client a name of 1 to 100 characters.")
    key, prefix = generate_api_key()
    try:
        with session_scope(settings) as db:
            if db.scalar(select(ApiClient.id).where(ApiClient.name == name)) is not None:
                raise ConflictError(
                    f"an API client named {name!r} already exists; choose another name or "
                    "revoke it first."
                )
            db.add(
                ApiClient(
                    name=name,
                    key_prefix=prefix,
                    key_hash=hash_api_key(key),
                    scopes=sorted(set(args.scopes)),
                )
            )
    except IntegrityError as exc:
        raise ConflictError(f"an API client named {name!r} already exists.") from exc
    print(key)
    print(
        f"API key for {name!r} (scopes: {', '.join(sorted(set(args.scopes)))}). It is shown "
        "only now; store it safely.",
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
    print(f"API key of {args.name!r} revoked", file=sys.stderr)
    return 0


def list_api_keys(settings: Settings, args: argparse.Namespace) -> int:
    from app.db import session_scope
    from app.models import ApiClient

    with session_scope(settings) as db:
        for c in db.scalars(select(ApiClient).order_by(ApiClient.name)):
            state = f"revoked {c.revoked_at:%Y-%m-%d}" if c.revoked_at else "active"
            print(f"{c.name}\tbsk_{c.key_prefix}_…\t{state}\t{' '.join(c.scopes)}")
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

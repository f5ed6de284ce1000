"""Login throttling: growing delays per account and per (address, account) pair.

Two failure streaks are kept for every login attempt, each a row of
:class:`app.models.LoginThrottle`:

- the **pair** (client address, account): ``settings.login_max_failures``
  free attempts, then delays;
- the **account** from all addresses together: twice as many free attempts,
  then delays.

After the free attempts each further attempt must wait ``login_delay_s``,
doubling up to ``login_max_delay_s``; after ``login_lock_after_failures``
consecutive failures (NIST SP 800-63B allows at most 100) the account is
locked until ``bradyscope admin unlock EMAIL`` (or ``set-password``). A
success resets both streaks; a streak below the lock is forgotten after
``login_window_s`` without attempts. No limit is kept per address alone, so
many users behind one hospital NAT never lock each other out, and an unknown
e-mail address is throttled exactly like a known one (no enumeration).

Atomicity: an attempt is **counted when it is admitted**, before its password
is checked, by a compare-and-set ``UPDATE ... WHERE failures = :seen`` in a
transaction of its own. Two concurrent attempts cannot both take the same
count, on SQLite (one writer at a time) and on PostgreSQL (the second UPDATE
waits for the first's row lock, then finds the count changed and retries), so
20 concurrent wrong passwords get at most ``login_max_failures`` password
checks.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any, cast

from sqlalchemy import CursorResult, Executable, delete, or_, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from app.errors import RateLimitedError
from app.models import LoginThrottle, utcnow
from app.settings import Settings

ACCOUNT_FACTOR = 2
"""The account from all addresses gets this many times the free attempts of one pair."""
_MAX_RACES = 200  # compare-and-set retries before giving up (never reached in practice)


def _rowcount(db: Session, statement: Executable) -> int:
    """Run an UPDATE/DELETE and return how many rows it touched."""
    result = cast("CursorResult[Any]", db.execute(statement))
    return int(result.rowcount or 0)


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def normalise_email(email: str) -> str:
    return email.strip().lower()


def email_hash(email: str) -> str:
    """SHA-256 (hex) of the normalised e-mail address, as stored in ``LoginThrottle``."""
    return _sha256(normalise_email(email))


@dataclass(frozen=True)
class Streak:
    """One throttle row's identity and its number of free attempts."""

    key: str
    email_hash: str
    ip: str | None
    free_attempts: int


def streaks(settings: Settings, e_hash: str, ip: str | None) -> tuple[Streak, Streak]:
    """The (address, account) pair's streak and the account's streak, in checking order."""
    limit = int(settings.login_max_failures)
    pair = Streak(_sha256(f"pair|{ip or '-'}|{e_hash}"), e_hash, ip or None, limit)
    account = Streak(_sha256(f"account|{e_hash}"), e_hash, None, limit * ACCOUNT_FACTOR)
    return pair, account


def delay_s(settings: Settings, failures: int, free_attempts: int) -> float:
    """Seconds to wait before the next attempt after ``failures`` counted attempts."""
    if failures < free_attempts:
        return 0.0
    exponent = min(failures - free_attempts, 60)
    return float(min(settings.login_delay_s * 2.0**exponent, settings.login_max_delay_s))


def _refusal(settings: Settings, wait_s: float | None) -> RateLimitedError:
    if wait_s is None:
        return RateLimitedError(
            "This account is locked after too many failed logins; ask an administrator to"
            " unlock it ('bradyscope admin unlock EMAIL') or to set a new password.",
            retry_after_s=None,
        )
    seconds = max(1, math.ceil(wait_s))
    when = f"{seconds} seconds" if seconds < 120 else f"{math.ceil(seconds / 60)} minutes"
    return RateLimitedError(
        f"Too many failed logins; wait {when} before trying again, or ask an administrator"
        " to unlock the account.",
        retry_after_s=seconds,
    )


def _ensure_row(db: Session, streak: Streak, now: datetime) -> None:
    values = {
        "key": streak.key,
        "email_hash": streak.email_hash,
        "ip": streak.ip,
        "failures": 0,
        "blocked_until": None,
        "last_attempt_at": now,
    }
    if db.get_bind().dialect.name == "postgresql":
        db.execute(postgresql.insert(LoginThrottle).values(values).on_conflict_do_nothing())
    else:
        db.execute(sqlite.insert(LoginThrottle).values(values).on_conflict_do_nothing())


def _take(db: Session, settings: Settings, streak: Streak) -> None:
    """Count one attempt on ``streak`` (committed), or raise :class:`RateLimitedError`."""
    lock_after = int(settings.login_lock_after_failures)
    forget_after = timedelta(seconds=float(settings.login_window_s))
    for _ in range(_MAX_RACES):
        now = utcnow()
        row = db.execute(
            select(
                LoginThrottle.failures, LoginThrottle.blocked_until, LoginThrottle.last_attempt_at
            ).where(LoginThrottle.key == streak.key)
        ).one_or_none()
        if row is None:
            _ensure_row(db, streak, now)
            db.commit()
            continue
        seen, blocked_until, last_attempt_at = int(row[0]), row[1], row[2]
        if seen >= lock_after:
            db.rollback()
            raise _refusal(settings, None)
        if blocked_until is not None and blocked_until > now:
            db.rollback()
            raise _refusal(settings, (blocked_until - now).total_seconds())
        base = 0 if now - last_attempt_at > forget_after else seen
        failures = base + 1
        wait = delay_s(settings, failures, streak.free_attempts)
        taken = _rowcount(
            db,
            update(LoginThrottle)
            .where(
                LoginThrottle.key == streak.key,
                LoginThrottle.failures == seen,
                or_(LoginThrottle.blocked_until.is_(None), LoginThrottle.blocked_until <= now),
            )
            .values(
                failures=failures,
                blocked_until=now + timedelta(seconds=wait) if wait > 0 else None,
                last_attempt_at=now,
            )
            .execution_options(synchronize_session=False),
        )
        db.commit()
        if taken == 1:
            return
        # Another attempt took this count first: read the streak again.
    raise RateLimitedError(
        "Too many simultaneous logins for this account; wait a moment and retry.",
        retry_after_s=1,
    )


def admit_attempt(db: Session, settings: Settings, email: str, ip: str | None) -> None:
    """Count a login attempt for ``email`` from ``ip`` before its password is checked.

    Commits (the count must be visible to concurrent attempts at once), so call
    it before the use case writes anything of its own.

    Raises
    ------
    app.errors.RateLimitedError
        The pair or the account must wait (429 with ``Retry-After``), or the
        account is locked until an administrator unlocks it.
    """
    for streak in streaks(settings, email_hash(email), ip):
        _take(db, settings, streak)


def record_success(db: Session, settings: Settings, email: str, ip: str | None) -> None:
    """A correct password: both streaks start again (in the caller's transaction)."""
    keys = [s.key for s in streaks(settings, email_hash(email), ip)]
    db.execute(
        delete(LoginThrottle)
        .where(LoginThrottle.key.in_(keys))
        .execution_options(synchronize_session=False)
    )


def unlock(db: Session, email: str) -> int:
    """Forget every streak of the account (all addresses); returns how many rows went."""
    return _rowcount(
        db,
        delete(LoginThrottle)
        .where(LoginThrottle.email_hash == email_hash(email))
        .execution_options(synchronize_session=False),
    )


def forget_stale(db: Session, settings: Settings) -> int:
    """Remove streaks forgotten anyway (no attempt for ``login_window_s``, not locked)."""
    cutoff = utcnow() - timedelta(seconds=float(settings.login_window_s))
    return _rowcount(
        db,
        delete(LoginThrottle)
        .where(
            LoginThrottle.last_attempt_at < cutoff,
            LoginThrottle.failures < int(settings.login_lock_after_failures),
        )
        .execution_options(synchronize_session=False),
    )


@dataclass(frozen=True)
class ThrottleState:
    """What ``admin list-users`` shows about an account's throttling."""

    failures: int
    blocked_until: datetime | None
    locked: bool


def account_state(db: Session, settings: Settings, email: str) -> ThrottleState | None:
    """The account's own streak (all addresses), or None when it has none."""
    _, account = streaks(settings, email_hash(email), None)
    row = db.execute(
        select(LoginThrottle.failures, LoginThrottle.blocked_until).where(
            LoginThrottle.key == account.key
        )
    ).one_or_none()
    if row is None:
        return None
    return ThrottleState(
        failures=int(row[0]),
        blocked_until=row[1],
        locked=int(row[0]) >= int(settings.login_lock_after_failures),
    )

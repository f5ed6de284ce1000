"""The audit trail's hash chain: each event sealed with a keyed hash of the one before.

Every audit event gets the next number ``seq`` and
``hash = HMAC-SHA256(key, previous hash + the event's fields)``; the newest
number and hash are kept in the one-row table ``audit_head``, whose row is
updated in the same transaction as the event is inserted. Updating that row
locks it (PostgreSQL) or takes SQLite's write lock, so concurrent use cases
append one after the other and the chain never forks; a rolled-back use case
rolls its number back too, so the numbers have no gaps.

The key is a random secret in a file outside the database
(``settings.audit_key_path``, default ``<data dir>/audit.key``, mode 0600):
someone who can rewrite the database but not read that file cannot forge a
hash, so a deleted, altered or inserted row shows in :func:`verify_chain`.
Removing rows from the end *and* moving ``audit_head`` back is the one change
the chain alone cannot see; record the head that ``verify-audit`` prints
elsewhere now and then to catch that too.

Events written before the chain existed (revision 0010) have no number and
are reported as not chained. The rows kept beside the trail (an update's values,
the patients a list returned) are checked against the ``details`` their events
seal by :mod:`app.audit_check`, which ``verify-audit`` runs after this.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from weakref import WeakKeyDictionary

from sqlalchemy import Engine, func, select, update
from sqlalchemy.orm import Session

from app.errors import StorageReadOnlyError
from app.models import AuditEvent, AuditHead

GENESIS = "0" * 64
"""The "previous hash" of the first chained event."""

_key_paths: WeakKeyDictionary[Engine, Path] = WeakKeyDictionary()
_keys: dict[Path, bytes] = {}
_keys_lock = threading.Lock()


def register_key_file(engine: Engine, path: Path) -> None:
    """Tell the audit trail where the key of ``engine``'s database lives (``app.db`` does it)."""
    _key_paths[engine] = path


def load_key(path: Path) -> bytes:
    """The key in ``path``, created (32 random bytes, hex, mode 0600) if there is none yet."""
    with _keys_lock:
        key = _keys.get(path)
        if key is not None:
            return key
        try:
            if not path.exists():
                path.parent.mkdir(parents=True, exist_ok=True)
                try:
                    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
                except FileExistsError:
                    pass  # another process made it at the same moment: read theirs
                else:
                    with os.fdopen(fd, "w") as fh:
                        fh.write(secrets.token_hex(32) + "\n")
                        fh.flush()
                        os.fsync(fh.fileno())
            text = path.read_text(encoding="ascii").strip()
        except OSError as exc:
            raise StorageReadOnlyError(
                f"the audit key {path} cannot be read or created ({exc.strerror}); nothing can be"
                " recorded, so nothing is done. Check the data directory's disk and permissions."
            ) from exc
        if len(text) < 32:
            raise StorageReadOnlyError(
                f"the audit key {path} is damaged (too short); restore it from a backup."
            )
        key = text.encode("ascii")
        _keys[path] = key
        return key


def forget_key(path: Path) -> None:
    """Read ``path`` again at the next use (after a restore put another key there)."""
    with _keys_lock:
        _keys.pop(path, None)


def key_for(db: Session) -> bytes:
    """The chain key of the database ``db`` is bound to."""
    bind = db.get_bind()
    engine = bind if isinstance(bind, Engine) else bind.engine
    path = _key_paths.get(engine)
    if path is None:
        raise RuntimeError(
            "no audit key is known for this database engine; create engines with app.db.make_engine"
        )
    return load_key(path)


def _canonical_time(at: datetime) -> str:
    return at.astimezone(UTC).isoformat(timespec="microseconds")


def fields_of(event: AuditEvent) -> list[Any]:
    """The sealed fields of an event, in a fixed order (everything but ``id`` and ``hash``).

    ``details`` (revision 0018) comes last and only when it is set, so the seals of the
    events made before it stay what they were.
    """
    fields: list[Any] = [
        event.seq,
        _canonical_time(event.at),
        event.actor_type,
        event.actor_id,
        event.action,
        event.resource_type,
        event.resource_id,
        event.patient_id,
        event.outcome,
        event.ip,
        event.request_id,
    ]
    if event.details is not None:
        fields.append(event.details)
    return fields


def seal(key: bytes, previous_hash: str, event: AuditEvent) -> str:
    """``HMAC-SHA256(key, previous_hash + canonical JSON of the event's fields)``, hex."""
    payload = json.dumps(
        fields_of(event), separators=(",", ":"), ensure_ascii=False, sort_keys=True
    )  # sort_keys: a JSON column may give its keys back in another order
    return hmac.new(key, f"{previous_hash}\n{payload}".encode(), hashlib.sha256).hexdigest()


def append(db: Session, event: AuditEvent) -> AuditEvent:
    """Number, seal and add ``event`` in ``db``'s transaction (locks the chain's head until commit)."""
    key = key_for(db)
    seq, previous = db.execute(
        update(AuditHead)
        .where(AuditHead.id == 1)
        .values(seq=AuditHead.seq + 1)
        .returning(AuditHead.seq, AuditHead.hash)
    ).one()
    event.seq = int(seq)
    event.hash = seal(key, str(previous), event)
    db.add(event)
    db.execute(update(AuditHead).where(AuditHead.id == 1).values(hash=event.hash))
    return event


# --------------------------------------------------------------------------- verification


@dataclass
class ChainReport:
    """What :func:`verify_chain` found. ``problems`` is empty when the trail is intact."""

    chained: int = 0
    unchained_before: int = 0
    head_seq: int = 0
    head_hash: str = GENESIS
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def _events(db: Session) -> Iterator[AuditEvent]:
    query = (
        select(AuditEvent)
        .where(AuditEvent.seq.is_not(None))
        .order_by(AuditEvent.seq)
        .execution_options(yield_per=2000)
    )
    yield from db.scalars(query)


def verify_chain(db: Session, *, max_problems: int = 20) -> ChainReport:
    """Recompute the chain: every deleted, altered or inserted event shows as a problem."""
    key = key_for(db)
    report = ChainReport()
    head = db.get(AuditHead, 1)
    if head is None:
        report.problems.append("the chain's head row (audit_head) is missing.")
        return report
    report.head_seq, report.head_hash = int(head.seq), str(head.hash)
    first_chained_id = db.scalar(select(func.min(AuditEvent.id)).where(AuditEvent.seq.is_not(None)))
    unchained = select(func.count()).select_from(AuditEvent).where(AuditEvent.seq.is_(None))
    if first_chained_id is None:
        report.unchained_before = int(db.scalar(unchained) or 0)
    else:
        report.unchained_before = int(
            db.scalar(unchained.where(AuditEvent.id < first_chained_id)) or 0
        )
        late = list(
            db.scalars(
                select(AuditEvent.id)
                .where(AuditEvent.seq.is_(None), AuditEvent.id > first_chained_id)
                .limit(max_problems)
            )
        )
        for event_id in late:
            report.problems.append(
                f"event id {event_id} has no place in the chain: it was inserted behind its back."
            )

    def problem(text: str) -> bool:
        report.problems.append(text)
        return len(report.problems) >= max_problems

    previous_hash = GENESIS
    expected_seq = 1  # the head starts at 0 (revision 0010)
    last_seq = 0
    for event in _events(db):
        seq = int(event.seq or 0)
        if seq != expected_seq:
            missing = f"{expected_seq}" if seq == expected_seq + 1 else f"{expected_seq}-{seq - 1}"
            if problem(f"events {missing} are missing before event {seq} (deleted?)."):
                break
        recomputed = seal(key, previous_hash, event)
        if not hmac.compare_digest(recomputed, str(event.hash or "")):
            if problem(
                f"event {seq} (id {event.id}) does not match its seal: it was altered, inserted,"
                " or an event before it was removed."
            ):
                break
        previous_hash = str(event.hash or "")
        expected_seq = seq + 1
        last_seq = seq
        report.chained += 1
    if report.chained and last_seq != report.head_seq:
        problem(
            f"the chain ends at event {last_seq} but its head says {report.head_seq}: events were"
            " removed from the end, or inserted after it."
        )
    elif report.chained and not hmac.compare_digest(previous_hash, report.head_hash):
        problem("the newest event does not match the chain's head: it was altered or replaced.")
    elif not report.chained and report.head_seq:
        problem(f"the chain's head says {report.head_seq} events, but none is left.")
    return report

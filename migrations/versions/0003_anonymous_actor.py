"""Audit events may have the actor type ``anonymous`` (e.g. a failed login).

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22

A failed login was recorded as ``system``, which reads as if the server did
it. The CHECK constraint on ``audit_events.actor_type`` gains ``anonymous``.
On SQLite the batch operation recreates the table, which drops the
append-only triggers of revision 0002: they are dropped first and recreated
afterwards. On PostgreSQL the constraint is altered in place (the triggers
stay).
"""

from collections.abc import Sequence

from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0003"
down_revision: str | Sequence[str] | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

MESSAGE = "audit events are append-only"
NEW_TYPES = "'user', 'api_client', 'system', 'anonymous'"
OLD_TYPES = "'user', 'api_client', 'system'"


def _sqlite_triggers(create: bool) -> None:
    for event in ("UPDATE", "DELETE"):
        name = f"audit_events_no_{event.lower()}"
        if create:
            op.execute(
                f"CREATE TRIGGER {name} BEFORE {event} ON audit_events "
                f"BEGIN SELECT RAISE(ABORT, '{MESSAGE}'); END"
            )
        else:
            op.execute(f"DROP TRIGGER IF EXISTS {name}")


def _replace_check(types: str) -> None:
    if op.get_bind().dialect.name == "postgresql":
        op.drop_constraint(op.f("ck_audit_events_actor_type"), "audit_events", type_="check")
        op.create_check_constraint(
            op.f("ck_audit_events_actor_type"), "audit_events", f"actor_type IN ({types})"
        )
        return
    _sqlite_triggers(create=False)
    with op.batch_alter_table("audit_events", recreate="always") as batch_op:
        batch_op.drop_constraint(op.f("ck_audit_events_actor_type"), type_="check")
        batch_op.create_check_constraint(
            op.f("ck_audit_events_actor_type"), f"actor_type IN ({types})"
        )
    _sqlite_triggers(create=True)


def upgrade() -> None:
    _replace_check(NEW_TYPES)


def downgrade() -> None:
    # Rows written as "anonymous" cannot be rewritten (append-only) and would
    # violate the old constraint: refuse rather than lose or alter the trail.
    count = (
        op.get_bind()
        .exec_driver_sql("SELECT count(*) FROM audit_events WHERE actor_type = 'anonymous'")
        .scalar()
    )
    if count:
        raise RuntimeError(
            f"{count} audit events have the actor type 'anonymous'; revision 0002 cannot hold them."
        )
    _replace_check(OLD_TYPES)

"""The audit trail becomes a keyed hash chain; patients can be erased; single sign-on.

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-24

``audit_events`` gains ``seq`` (the event's number in the chain, UNIQUE) and
``hash`` (HMAC-SHA256 of the previous event's hash and this event's fields,
``app.chain``), and ``audit_head`` holds the newest number and hash in one
row. Events written before this revision keep NULL in both (reported as "not
chained" by ``verify-audit``): the key that seals them lives outside the
database, where a migration does not reach. Adding nullable columns and an
index is done in place on SQLite too, so the append-only triggers of revision
0002 stay.

``patients.erased_at``: when the patient's data was erased (its row stays as a
pseudonymised tombstone for the audit trail).

``users.oidc_subject``: the identity provider's ``sub`` of an account that
logged in through single sign-on (UNIQUE), bound at its first such login.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0010"
down_revision: str | Sequence[str] | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

GENESIS = "0" * 64


def upgrade() -> None:
    with op.batch_alter_table("audit_events", recreate="never") as batch_op:
        batch_op.add_column(sa.Column("seq", sa.BigInteger(), nullable=True))
        batch_op.add_column(sa.Column("hash", sa.String(length=64), nullable=True))
        batch_op.create_index(batch_op.f("ix_audit_events_seq"), ["seq"], unique=True)
    head = op.create_table(
        "audit_head",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("seq", sa.BigInteger(), nullable=False),
        sa.Column("hash", sa.String(length=64), nullable=False),
        sa.CheckConstraint("id = 1", name=op.f("ck_audit_head_one_row")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_audit_head")),
    )
    op.bulk_insert(head, [{"id": 1, "seq": 0, "hash": GENESIS}])
    with op.batch_alter_table("patients", recreate="never") as batch_op:
        batch_op.add_column(sa.Column("erased_at", sa.DateTime(timezone=True), nullable=True))
    with op.batch_alter_table("users", recreate="never") as batch_op:
        batch_op.add_column(sa.Column("oidc_subject", sa.String(length=255), nullable=True))
        batch_op.create_index(batch_op.f("ix_users_oidc_subject"), ["oidc_subject"], unique=True)


def downgrade() -> None:
    with op.batch_alter_table("users") as batch_op:
        batch_op.drop_index(batch_op.f("ix_users_oidc_subject"))
        batch_op.drop_column("oidc_subject")
    with op.batch_alter_table("patients") as batch_op:
        batch_op.drop_column("erased_at")
    op.drop_table("audit_head")
    # The chain's columns go with a rebuild of the table on SQLite, which drops the
    # append-only triggers: they are recreated as revision 0002 made them.
    if op.get_bind().dialect.name == "postgresql":
        op.drop_index(op.f("ix_audit_events_seq"), table_name="audit_events")
        op.drop_column("audit_events", "hash")
        op.drop_column("audit_events", "seq")
        return
    for event in ("UPDATE", "DELETE"):
        op.execute(f"DROP TRIGGER IF EXISTS audit_events_no_{event.lower()}")
    with op.batch_alter_table("audit_events", recreate="always") as batch_op:
        batch_op.drop_index(batch_op.f("ix_audit_events_seq"))
        batch_op.drop_column("hash")
        batch_op.drop_column("seq")
    for event in ("UPDATE", "DELETE"):
        op.execute(
            f"CREATE TRIGGER audit_events_no_{event.lower()} BEFORE {event} ON audit_events "
            "BEGIN SELECT RAISE(ABORT, 'audit events are append-only'); END"
        )

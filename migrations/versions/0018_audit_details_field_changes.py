"""An update's audit event names the fields it changed; their values are kept beside it.

Revision ID: 0018
Revises: 0017
Create Date: 2026-11-28

``audit_events.details`` (JSON, NULL for the events made before): what an event concerns
beyond its columns, sealed into the hash chain with them; for an update, the names of
the fields it changed and the SHA-256 of their values. The column is added without
rewriting the table, so the triggers that keep the trail append-only (0002) stay.

``field_changes``: the previous and new values of each update's fields, one row per
update, naming its event (by id, without a foreign key: nothing holds the trail's rows)
and referring to the patient (erased with the patient, as every row of their data is).
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0018"
down_revision: str | Sequence[str] | None = "0017"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("audit_events", sa.Column("details", sa.JSON(), nullable=True))
    op.create_table(
        "field_changes",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("event_id", sa.Integer(), nullable=False),
        sa.Column("patient_id", sa.Integer(), nullable=False),
        sa.Column("changes", sa.JSON(), nullable=False),
        sa.Column("nonce", sa.String(length=32), nullable=False),
        sa.ForeignKeyConstraint(
            ["patient_id"], ["patients.id"], name=op.f("fk_field_changes_patient_id_patients")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_field_changes")),
    )
    op.create_index(op.f("ix_field_changes_event_id"), "field_changes", ["event_id"])
    op.create_index(op.f("ix_field_changes_patient_id"), "field_changes", ["patient_id"])


def downgrade() -> None:
    op.drop_index(op.f("ix_field_changes_patient_id"), table_name="field_changes")
    op.drop_index(op.f("ix_field_changes_event_id"), table_name="field_changes")
    op.drop_table("field_changes")
    # The column goes with a rebuild of the table on SQLite, which drops the append-only
    # triggers: they are recreated as revision 0002 made them (as 0010 does).
    if op.get_bind().dialect.name == "postgresql":
        op.drop_column("audit_events", "details")
        return
    for event in ("UPDATE", "DELETE"):
        op.execute(f"DROP TRIGGER IF EXISTS audit_events_no_{event.lower()}")
    with op.batch_alter_table("audit_events", recreate="always") as batch_op:
        batch_op.drop_column("details")
    for event in ("UPDATE", "DELETE"):
        op.execute(
            f"CREATE TRIGGER audit_events_no_{event.lower()} BEFORE {event} ON audit_events "
            "BEGIN SELECT RAISE(ABORT, 'audit events are append-only'); END"
        )

"""A trial records one task: finger tapping (as before), hand movements, pronation–supination or toe tapping.

Revision ID: 0011
Revises: 0010
Create Date: 2026-11-24

``trials.task`` (MDS-UPDRS items 3.4–3.7, ``core.tasks.Task``), NOT NULL with
the server default ``finger_tapping``, so every trial recorded before is a
finger-tapping trial, and checked by the named constraint ``ck_trials_task``.
Adding a CHECK constraint makes SQLite rebuild the table (batch mode); no
trigger is defined on ``trials``.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0011"
down_revision: str | Sequence[str] | None = "0010"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TASKS = ("finger_tapping", "hand_movements", "pronation_supination", "toe_tapping")


def upgrade() -> None:
    with op.batch_alter_table("trials") as batch_op:
        batch_op.add_column(
            sa.Column("task", sa.String(32), nullable=False, server_default="finger_tapping")
        )
        batch_op.create_check_constraint(
            op.f("ck_trials_task"), "task IN (" + ", ".join(f"'{t}'" for t in TASKS) + ")"
        )


def downgrade() -> None:
    with op.batch_alter_table("trials") as batch_op:
        batch_op.drop_constraint(op.f("ck_trials_task"), type_="check")
        batch_op.drop_column("task")

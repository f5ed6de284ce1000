"""A trial may be recorded by another rig than its session's (another placement of the cameras).

Revision ID: 0015
Revises: 0014
Create Date: 2026-11-28

``trials.rig_id`` (nullable, a foreign key to ``rigs``): toe tapping and leg
agility film the foot and the leg from another placement than the hand tasks,
calibrated as a rig of its own; the trial then names that rig, and its
analysis uses that rig's calibration. NULL (every trial stored before): the
session's rig, as before.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0015"
down_revision: str | Sequence[str] | None = "0014"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("trials") as batch_op:
        batch_op.add_column(sa.Column("rig_id", sa.Integer(), nullable=True))
        batch_op.create_foreign_key(op.f("fk_trials_rig_id_rigs"), "rigs", ["rig_id"], ["id"])


def downgrade() -> None:
    stored = op.get_bind().execute(
        sa.text("SELECT count(*) FROM trials WHERE rig_id IS NOT NULL")
    ).scalar_one()
    if stored:
        raise RuntimeError(
            f"{stored} trial(s) name a rig of their own; revision 0014 cannot say so, and their"
            " analyses would use the session's rig. Keep this revision."
        )
    with op.batch_alter_table("trials") as batch_op:
        batch_op.drop_constraint(op.f("fk_trials_rig_id_rigs"), type_="foreignkey")
        batch_op.drop_column("rig_id")

"""A trial may record leg agility (MDS-UPDRS 3.8) besides the tasks of 3.4–3.7.

Revision ID: 0014
Revises: 0013
Create Date: 2026-11-28

The named constraint ``ck_trials_task`` is widened to the five tasks of
``core.tasks.Task``. Going back refuses while any leg agility trial is stored:
the narrower constraint would not hold, and deleting those trials to make it
hold would lose measurements.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0014"
down_revision: str | Sequence[str] | None = "0013"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

BEFORE = ("finger_tapping", "hand_movements", "pronation_supination", "toe_tapping")
AFTER = (*BEFORE, "leg_agility")


def _constrain(tasks: tuple[str, ...]) -> None:
    with op.batch_alter_table("trials") as batch_op:
        batch_op.drop_constraint(op.f("ck_trials_task"), type_="check")
        batch_op.create_check_constraint(
            op.f("ck_trials_task"), "task IN (" + ", ".join(f"'{t}'" for t in tasks) + ")"
        )


def upgrade() -> None:
    _constrain(AFTER)


def downgrade() -> None:
    stored = op.get_bind().execute(
        sa.text("SELECT count(*) FROM trials WHERE task = 'leg_agility'")
    ).scalar_one()
    if stored:
        raise RuntimeError(
            f"{stored} leg agility trial(s) are stored; revision 0013 cannot hold them. Erase"
            " them first (or keep this revision)."
        )
    _constrain(BEFORE)

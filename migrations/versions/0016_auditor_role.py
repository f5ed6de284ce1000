"""A user may be an auditor: the audit trail and nothing of the patients' data.

Revision ID: 0016
Revises: 0015
Create Date: 2026-11-28

The named constraint ``ck_users_role`` is widened to ``app.models.ROLES``. Going back
refuses while an auditor account exists: the narrower constraint would not hold, and
turning the account into a clinician would give it every patient's data.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0016"
down_revision: str | Sequence[str] | None = "0015"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

BEFORE = ("clinician", "admin")
AFTER = (*BEFORE, "auditor")


def _constrain(roles: tuple[str, ...]) -> None:
    with op.batch_alter_table("users") as batch_op:
        batch_op.drop_constraint(op.f("ck_users_role"), type_="check")
        batch_op.create_check_constraint(
            op.f("ck_users_role"), "role IN (" + ", ".join(f"'{r}'" for r in roles) + ")"
        )


def upgrade() -> None:
    _constrain(AFTER)


def downgrade() -> None:
    stored = op.get_bind().execute(
        sa.text("SELECT count(*) FROM users WHERE role = 'auditor'")
    ).scalar_one()
    if stored:
        raise RuntimeError(
            f"{stored} auditor account(s) exist; revision 0015 cannot hold them. Deactivate"
            " and erase them, or set another role, first (or keep this revision)."
        )
    _constrain(BEFORE)

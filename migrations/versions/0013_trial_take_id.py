"""A trial remembers the capture page's id of its take, so a take sent again is not stored twice.

Revision ID: 0013
Revises: 0012
Create Date: 2026-11-24

``trials.take_id`` (nullable; the capture page sends a random id with each take)
and the unique index ``ix_trials_session_id_take_id`` on ``(session_id,
take_id)``: when the connection is lost after a take was sent, the page cannot
know whether the server stored it; sending it again with the same id answers
with the trial stored first instead of a second trial. Other uploads leave it
NULL (NULLs do not collide in a unique index, on SQLite as on PostgreSQL).
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0013"
down_revision: str | Sequence[str] | None = "0012"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("trials") as batch_op:
        batch_op.add_column(sa.Column("take_id", sa.String(64), nullable=True))
    op.create_index(
        "ix_trials_session_id_take_id", "trials", ["session_id", "take_id"], unique=True
    )


def downgrade() -> None:
    op.drop_index("ix_trials_session_id_take_id", table_name="trials")
    with op.batch_alter_table("trials") as batch_op:
        batch_op.drop_column("take_id")

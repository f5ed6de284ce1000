"""Each result revision's plots, drawn once and stored (``results.plots_path``).

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-24

The worker draws a revision's plots when it stores the revision (a correction
when it is made) and keeps them as a JSON file beside ``markers.csv``; pages
and reports read them instead of drawing them at every first view. Older rows
keep NULL and are drawn on demand, as before.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0012"
down_revision: str | Sequence[str] | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("results") as batch_op:
        batch_op.add_column(sa.Column("plots_path", sa.String(500), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("results") as batch_op:
        batch_op.drop_column("plots_path")

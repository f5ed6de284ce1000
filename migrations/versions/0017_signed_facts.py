"""A signature keeps what the signed report said beyond the results: ratings, session facts.

Revision ID: 0017
Revises: 0016
Create Date: 2026-11-28

``signatures.signed_facts`` (JSON, NULL for signatures made before): the patient code,
each session's medication and DBS state, last levodopa, more affected side, dominant
hand, time and clinician, and each trial's task, side, session, rating and rating
comment, as the signed report printed them. A later change to any of them makes an
amendment pending, as a newer result revision already did. The column is added
without rewriting the table, so the trigger that refuses UPDATEs of a signature
(0009) stays in place; signatures made before keep NULL and are compared by their
result revisions alone.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0017"
down_revision: str | Sequence[str] | None = "0016"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("signatures", sa.Column("signed_facts", sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column("signatures", "signed_facts")

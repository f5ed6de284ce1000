"""Per-frame capture times stored with a video (the capture page's timestamps files).

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-26

A trial upload may carry, for each video, a timestamps file (``frame,time_s``
CSV: each frame's capture time on that camera's clock; the capture page writes
them). It is stored beside the video and referenced by ``videos.times_path``
(relative to the data directory, like ``path``) with its ``times_sha256``.
``duration_s`` is the recording's length: from its capture times when a
timestamps file came with it, else ``frame_count / fps``; older rows keep NULL.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0008"
down_revision: str | Sequence[str] | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("videos") as batch_op:
        batch_op.add_column(sa.Column("times_path", sa.String(500), nullable=True))
        batch_op.add_column(sa.Column("times_sha256", sa.String(64), nullable=True))
        batch_op.add_column(sa.Column("duration_s", sa.Float(), nullable=True))
        batch_op.create_unique_constraint("uq_videos_times_path", ["times_path"])


def downgrade() -> None:
    with op.batch_alter_table("videos") as batch_op:
        batch_op.drop_constraint("uq_videos_times_path", type_="unique")
        batch_op.drop_column("duration_s")
        batch_op.drop_column("times_sha256")
        batch_op.drop_column("times_path")

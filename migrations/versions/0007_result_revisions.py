"""Result revisions, hidden trials with a reason, browser proxies of the videos.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-24

A trial's result is no longer replaced: every analysis or clinician's
correction adds a revision (``results.revision`` 1, 2...; UNIQUE per trial
instead of one result per trial) with who asked for it, why and what changed,
and the review view's overlay file. Existing results become revision 1 (an
analysis). Hidden (soft-deleted) trials keep why and by whom; videos keep the
path of their browser-playable proxy.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0007"
down_revision: str | Sequence[str] | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("results") as batch_op:
        batch_op.drop_constraint("uq_results_trial_id", type_="unique")
        batch_op.add_column(
            sa.Column("revision", sa.Integer(), nullable=False, server_default="1")
        )
        batch_op.add_column(
            sa.Column("kind", sa.String(length=16), nullable=False, server_default="analysis")
        )
        batch_op.add_column(sa.Column("base_revision", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("overlay_path", sa.String(length=500), nullable=True))
        batch_op.add_column(sa.Column("created_by", sa.String(length=320), nullable=True))
        batch_op.add_column(sa.Column("created_by_user_id", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("reason", sa.Text(), nullable=True))
        batch_op.add_column(sa.Column("change", sa.JSON(), nullable=True))
        batch_op.create_foreign_key(
            op.f("fk_results_created_by_user_id_users"), "users", ["created_by_user_id"], ["id"]
        )
        batch_op.create_unique_constraint("uq_results_trial_revision", ["trial_id", "revision"])
        batch_op.create_check_constraint(
            op.f("ck_results_kind"), "kind IN ('analysis', 'correction')"
        )
        batch_op.create_check_constraint(op.f("ck_results_revision"), "revision >= 1")
        batch_op.create_index(op.f("ix_results_trial_id"), ["trial_id"], unique=False)
    # The defaults served the existing rows only; the models give every new row its values.
    with op.batch_alter_table("results") as batch_op:
        batch_op.alter_column("revision", server_default=None)
        batch_op.alter_column("kind", server_default=None)
    with op.batch_alter_table("trials") as batch_op:
        batch_op.add_column(sa.Column("deleted_reason", sa.Text(), nullable=True))
        batch_op.add_column(sa.Column("deleted_by", sa.String(length=320), nullable=True))
    with op.batch_alter_table("videos") as batch_op:
        batch_op.add_column(sa.Column("proxy_path", sa.String(length=500), nullable=True))


def downgrade() -> None:
    # Back to one result per trial: the newest revision of each trial stays.
    op.execute(
        "DELETE FROM results WHERE revision < "
        "(SELECT max(r2.revision) FROM results r2 WHERE r2.trial_id = results.trial_id)"
    )
    with op.batch_alter_table("videos") as batch_op:
        batch_op.drop_column("proxy_path")
    with op.batch_alter_table("trials") as batch_op:
        batch_op.drop_column("deleted_by")
        batch_op.drop_column("deleted_reason")
    with op.batch_alter_table("results") as batch_op:
        batch_op.drop_index(op.f("ix_results_trial_id"))
        batch_op.drop_constraint(op.f("ck_results_revision"), type_="check")
        batch_op.drop_constraint(op.f("ck_results_kind"), type_="check")
        batch_op.drop_constraint("uq_results_trial_revision", type_="unique")
        batch_op.drop_constraint(op.f("fk_results_created_by_user_id_users"), type_="foreignkey")
        batch_op.drop_column("change")
        batch_op.drop_column("reason")
        batch_op.drop_column("created_by_user_id")
        batch_op.drop_column("created_by")
        batch_op.drop_column("overlay_path")
        batch_op.drop_column("base_revision")
        batch_op.drop_column("kind")
        batch_op.drop_column("revision")
        batch_op.create_unique_constraint(op.f("uq_results_trial_id"), ["trial_id"])

"""Login throttling by failure streaks; API keys get an owner and an expiry date.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-24

``login_attempts`` (one row per attempt, counted after the password check,
which concurrent attempts could race past) gives way to ``login_throttles``:
one row per account and per (address, account) pair, whose count is taken by
a compare-and-set before the password is checked (``app.throttle``). The old
rows only fed the throttle's window and are not carried over: at worst a
streak that was running at the upgrade starts again.

``api_clients`` gains ``owner_user_id`` (the person answerable for the key;
the key stops working when they are deactivated) and ``expires_at``. Keys
made before this revision keep no expiry date (NULL) until they are replaced.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0005"
down_revision: str | Sequence[str] | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "login_throttles",
        sa.Column("key", sa.String(length=64), nullable=False),
        sa.Column("email_hash", sa.String(length=64), nullable=False),
        sa.Column("ip", sa.String(length=45), nullable=True),
        sa.Column("failures", sa.Integer(), nullable=False),
        sa.Column("blocked_until", sa.DateTime(timezone=True), nullable=True),
        sa.Column("last_attempt_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("key", name=op.f("pk_login_throttles")),
    )
    with op.batch_alter_table("login_throttles") as batch_op:
        batch_op.create_index(
            batch_op.f("ix_login_throttles_email_hash"), ["email_hash"], unique=False
        )
        batch_op.create_index(
            batch_op.f("ix_login_throttles_last_attempt_at"), ["last_attempt_at"], unique=False
        )
    with op.batch_alter_table("login_attempts") as batch_op:
        batch_op.drop_index("ix_login_attempts_ip_at")
        batch_op.drop_index("ix_login_attempts_email_hash_at")
    op.drop_table("login_attempts")

    with op.batch_alter_table("api_clients") as batch_op:
        batch_op.add_column(sa.Column("owner_user_id", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("expires_at", sa.DateTime(timezone=True), nullable=True))
        batch_op.create_foreign_key(
            batch_op.f("fk_api_clients_owner_user_id_users"), "users", ["owner_user_id"], ["id"]
        )


def downgrade() -> None:
    with op.batch_alter_table("api_clients") as batch_op:
        batch_op.drop_constraint(
            batch_op.f("fk_api_clients_owner_user_id_users"), type_="foreignkey"
        )
        batch_op.drop_column("expires_at")
        batch_op.drop_column("owner_user_id")

    op.create_table(
        "login_attempts",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("email_hash", sa.String(length=64), nullable=False),
        sa.Column("ip", sa.String(length=45), nullable=True),
        sa.Column("success", sa.Boolean(), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_login_attempts")),
    )
    with op.batch_alter_table("login_attempts") as batch_op:
        batch_op.create_index("ix_login_attempts_email_hash_at", ["email_hash", "at"], unique=False)
        batch_op.create_index("ix_login_attempts_ip_at", ["ip", "at"], unique=False)
    with op.batch_alter_table("login_throttles") as batch_op:
        batch_op.drop_index(batch_op.f("ix_login_throttles_last_attempt_at"))
        batch_op.drop_index(batch_op.f("ix_login_throttles_email_hash"))
    op.drop_table("login_throttles")

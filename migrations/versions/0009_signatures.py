"""Signed visit reports: ``signatures``, never updated.

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-24

A clinician's signature of a visit: who, when, the SHA-256 of the signed PDF
(stored as a file, served byte for byte) and the result revision of each
signed trial. A trigger refuses every UPDATE of a signature (a signed report
cannot be altered, not even by a bug); rows go only with a patient's erasure.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0009"
down_revision: str | Sequence[str] | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

MESSAGE = "signatures cannot be changed"


def upgrade() -> None:
    op.create_table(
        "signatures",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("patient_id", sa.Integer(), nullable=False),
        sa.Column("session_id", sa.Integer(), nullable=False),
        sa.Column("visit_date", sa.String(length=10), nullable=False),
        sa.Column("number", sa.Integer(), nullable=False),
        sa.Column("amends_number", sa.Integer(), nullable=True),
        sa.Column("signed_by", sa.String(length=320), nullable=False),
        sa.Column("signed_by_user_id", sa.Integer(), nullable=False),
        sa.Column("signed_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("sha256", sa.String(length=64), nullable=False),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        sa.Column("pdf_path", sa.String(length=500), nullable=False),
        sa.Column("trial_revisions", sa.JSON(), nullable=False),
        sa.ForeignKeyConstraint(
            ["patient_id"], ["patients.id"], name=op.f("fk_signatures_patient_id_patients")
        ),
        sa.ForeignKeyConstraint(
            ["session_id"], ["sessions.id"], name=op.f("fk_signatures_session_id_sessions")
        ),
        sa.ForeignKeyConstraint(
            ["signed_by_user_id"], ["users.id"], name=op.f("fk_signatures_signed_by_user_id_users")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_signatures")),
        sa.UniqueConstraint("patient_id", "visit_date", "number", name="uq_signatures_visit_number"),
        sa.UniqueConstraint("pdf_path", name=op.f("uq_signatures_pdf_path")),
    )
    op.create_index("ix_signatures_session_id", "signatures", ["session_id"], unique=False)
    if op.get_bind().dialect.name == "postgresql":
        op.execute(
            "CREATE FUNCTION bradyscope_signatures_unchanged() RETURNS trigger "
            "LANGUAGE plpgsql AS $$ BEGIN "
            f"RAISE EXCEPTION '{MESSAGE}'; "
            "END $$"
        )
        op.execute(
            "CREATE TRIGGER signatures_no_update BEFORE UPDATE ON signatures "
            "FOR EACH ROW EXECUTE FUNCTION bradyscope_signatures_unchanged()"
        )
    else:
        op.execute(
            "CREATE TRIGGER signatures_no_update BEFORE UPDATE ON signatures "
            f"BEGIN SELECT RAISE(ABORT, '{MESSAGE}'); END"
        )


def downgrade() -> None:
    if op.get_bind().dialect.name == "postgresql":
        op.execute("DROP TRIGGER IF EXISTS signatures_no_update ON signatures")
        op.execute("DROP FUNCTION IF EXISTS bradyscope_signatures_unchanged()")
    else:
        op.execute("DROP TRIGGER IF EXISTS signatures_no_update")
    op.drop_index("ix_signatures_session_id", table_name="signatures")
    op.drop_table("signatures")

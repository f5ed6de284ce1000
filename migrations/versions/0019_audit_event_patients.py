"""The patients a list returned, where the trail's patient filter finds them.

Revision ID: 0019
Revises: 0018
Create Date: 2026-11-28

A list of patients (``GET /patients``, the patient list page) is one audit event whose
``details`` name the patients returned (sealed into the chain); ``audit_event_patients``
holds a row per (event, patient), indexed by patient, so that a patient's trail shows
the lists that returned their data. No foreign keys, as the trail's own table.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0019"
down_revision: str | Sequence[str] | None = "0018"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "audit_event_patients",
        sa.Column("event_id", sa.Integer(), nullable=False),
        sa.Column("patient_id", sa.Integer(), nullable=False),
        sa.PrimaryKeyConstraint("event_id", "patient_id", name=op.f("pk_audit_event_patients")),
    )
    op.create_index(
        op.f("ix_audit_event_patients_patient_id"), "audit_event_patients", ["patient_id"]
    )


def downgrade() -> None:
    op.drop_index(op.f("ix_audit_event_patients_patient_id"), table_name="audit_event_patients")
    op.drop_table("audit_event_patients")

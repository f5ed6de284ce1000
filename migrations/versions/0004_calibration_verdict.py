"""Calibrations keep their quality verdict (good / acceptable / poor) and its reasons.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-23

The verdict was computed again wherever a calibration was shown (rig pages,
reports). It is now judged once, when a calibration becomes ready, and stored
in ``calibrations.verdict`` and ``calibrations.verdict_reasons``. Ready
calibrations of an existing database are judged here from their stored quality
figures (``core.calibration.quality_verdict``, as the service judges new ones).
"""

import json
from collections.abc import Sequence
from typing import Any

import sqlalchemy as sa
from alembic import op

from core.calibration import quality_verdict

# revision identifiers, used by Alembic.
revision: str = "0004"
down_revision: str | Sequence[str] | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

VERDICTS = "'good', 'acceptable', 'poor'"


def _quality(value: Any) -> dict[str, Any]:
    if isinstance(value, str):  # SQLite returns JSON columns as text here
        value = json.loads(value)
    return dict(value) if isinstance(value, dict) else {}


def upgrade() -> None:
    with op.batch_alter_table("calibrations") as batch_op:
        batch_op.add_column(sa.Column("verdict", sa.String(length=16), nullable=True))
        batch_op.add_column(sa.Column("verdict_reasons", sa.JSON(), nullable=True))
        batch_op.create_check_constraint(
            op.f("ck_calibrations_verdict"), f"verdict IS NULL OR verdict IN ({VERDICTS})"
        )
    calibrations = sa.table(
        "calibrations",
        sa.column("id", sa.Integer),
        sa.column("status", sa.String),
        sa.column("rms_px", sa.Float),
        sa.column("quality", sa.JSON),
        sa.column("verdict", sa.String),
        sa.column("verdict_reasons", sa.JSON),
    )
    bind = op.get_bind()
    rows = bind.execute(
        sa.select(calibrations.c.id, calibrations.c.rms_px, calibrations.c.quality).where(
            calibrations.c.status == "ready"
        )
    ).all()
    for cal_id, rms_px, quality in rows:
        figures = _quality(quality)
        if rms_px is not None:
            figures.setdefault("rms_px", rms_px)
        verdict, reasons = quality_verdict(figures)
        bind.execute(
            calibrations.update()
            .where(calibrations.c.id == cal_id)
            .values(verdict=verdict, verdict_reasons=list(reasons))
        )
    with op.batch_alter_table("calibrations") as batch_op:
        batch_op.create_check_constraint(
            op.f("ck_calibrations_ready_has_verdict"), "status != 'ready' OR verdict IS NOT NULL"
        )


def downgrade() -> None:
    with op.batch_alter_table("calibrations") as batch_op:
        batch_op.drop_constraint(op.f("ck_calibrations_ready_has_verdict"), type_="check")
        batch_op.drop_constraint(op.f("ck_calibrations_verdict"), type_="check")
        batch_op.drop_column("verdict_reasons")
        batch_op.drop_column("verdict")

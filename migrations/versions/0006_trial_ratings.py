"""Per-trial clinician ratings; structured session fields (levodopa, sides).

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-24

The MDS-UPDRS 3.4 item is rated per hand, but the rating was stored once per
session (``sessions.updrs_34_rating``), so a left-hand result showed the
right hand's rating. Each trial now holds its own ``clinician_rating`` (0–4),
``rating_comment``, ``rated_at`` and ``rated_by_user_id``.

The session rating is carried over to every trial of that session (both
hands: which hand it described was never recorded), with a comment that says
so. A session that has a rating but no trial keeps it in its notes, so that
nothing stored is lost. The session also gains the structured fields that
clinicians record with tapping: ``time_since_levodopa_min``,
``more_affected_side`` and ``dominant_hand``.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0006"
down_revision: str | Sequence[str] | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

CARRIED_OVER = (
    "Carried over from the session's single 3.4 rating, given before ratings were per hand;"
    " the hand it described was not recorded."
)
NOTE_PREFIX = "MDS-UPDRS 3.4 rating given for the whole session (no trial to carry it): "

sessions = sa.table(
    "sessions",
    sa.column("id", sa.Integer),
    sa.column("clinician_user_id", sa.Integer),
    sa.column("created_at", sa.DateTime),
    sa.column("notes", sa.Text),
    sa.column("updrs_34_rating", sa.Integer),
)
trials = sa.table(
    "trials",
    sa.column("id", sa.Integer),
    sa.column("session_id", sa.Integer),
    sa.column("clinician_rating", sa.Integer),
    sa.column("rating_comment", sa.Text),
    sa.column("rated_at", sa.DateTime),
    sa.column("rated_by_user_id", sa.Integer),
)


def upgrade() -> None:
    with op.batch_alter_table("trials") as batch_op:
        batch_op.add_column(sa.Column("clinician_rating", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("rating_comment", sa.Text(), nullable=True))
        batch_op.add_column(sa.Column("rated_at", sa.DateTime(timezone=True), nullable=True))
        batch_op.add_column(sa.Column("rated_by_user_id", sa.Integer(), nullable=True))
        batch_op.create_foreign_key(
            op.f("fk_trials_rated_by_user_id_users"), "users", ["rated_by_user_id"], ["id"]
        )
        batch_op.create_check_constraint(
            op.f("ck_trials_clinician_rating"),
            "clinician_rating IS NULL OR (clinician_rating >= 0 AND clinician_rating <= 4)",
        )

    bind = op.get_bind()
    rated = bind.execute(
        sa.select(
            sessions.c.id,
            sessions.c.updrs_34_rating,
            sessions.c.clinician_user_id,
            sessions.c.created_at,
            sessions.c.notes,
        ).where(sessions.c.updrs_34_rating.is_not(None))
    ).all()
    for session_id, rating, user_id, created_at, notes in rated:
        n = bind.execute(
            trials.update()
            .where(trials.c.session_id == session_id)
            .values(
                clinician_rating=rating,
                rating_comment=CARRIED_OVER,
                rated_at=created_at,
                rated_by_user_id=user_id,
            )
        ).rowcount
        if not n:
            note = NOTE_PREFIX + str(rating) + "."
            bind.execute(
                sessions.update()
                .where(sessions.c.id == session_id)
                .values(notes=f"{notes}\n{note}" if notes else note)
            )

    with op.batch_alter_table("sessions") as batch_op:
        batch_op.drop_constraint(op.f("ck_sessions_updrs_34_rating"), type_="check")
        batch_op.drop_column("updrs_34_rating")
        batch_op.add_column(sa.Column("time_since_levodopa_min", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("more_affected_side", sa.String(length=8), nullable=True))
        batch_op.add_column(sa.Column("dominant_hand", sa.String(length=8), nullable=True))
        batch_op.create_check_constraint(
            op.f("ck_sessions_time_since_levodopa_min"),
            "time_since_levodopa_min IS NULL OR time_since_levodopa_min >= 0",
        )
        batch_op.create_check_constraint(
            op.f("ck_sessions_more_affected_side"),
            "more_affected_side IS NULL OR more_affected_side IN ('left', 'right', 'equal')",
        )
        batch_op.create_check_constraint(
            op.f("ck_sessions_dominant_hand"),
            "dominant_hand IS NULL OR dominant_hand IN ('left', 'right', 'both')",
        )


def downgrade() -> None:
    with op.batch_alter_table("sessions") as batch_op:
        batch_op.drop_constraint(op.f("ck_sessions_dominant_hand"), type_="check")
        batch_op.drop_constraint(op.f("ck_sessions_more_affected_side"), type_="check")
        batch_op.drop_constraint(op.f("ck_sessions_time_since_levodopa_min"), type_="check")
        batch_op.drop_column("dominant_hand")
        batch_op.drop_column("more_affected_side")
        batch_op.drop_column("time_since_levodopa_min")
        batch_op.add_column(sa.Column("updrs_34_rating", sa.Integer(), nullable=True))
        batch_op.create_check_constraint(
            op.f("ck_sessions_updrs_34_rating"),
            "updrs_34_rating IS NULL OR (updrs_34_rating >= 0 AND updrs_34_rating <= 4)",
        )
    # A session keeps one rating: the highest of its trials (per-hand ratings cannot
    # be told apart in the old schema; the worse hand is the cautious choice).
    bind = op.get_bind()
    rows = bind.execute(
        sa.select(trials.c.session_id, sa.func.max(trials.c.clinician_rating))
        .where(trials.c.clinician_rating.is_not(None))
        .group_by(trials.c.session_id)
    ).all()
    for session_id, rating in rows:
        bind.execute(
            sessions.update().where(sessions.c.id == session_id).values(updrs_34_rating=rating)
        )
    with op.batch_alter_table("trials") as batch_op:
        batch_op.drop_constraint(op.f("ck_trials_clinician_rating"), type_="check")
        batch_op.drop_constraint(op.f("fk_trials_rated_by_user_id_users"), type_="foreignkey")
        batch_op.drop_column("rated_by_user_id")
        batch_op.drop_column("rated_at")
        batch_op.drop_column("rating_comment")
        batch_op.drop_column("clinician_rating")

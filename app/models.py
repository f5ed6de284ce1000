"""The database model of the bradyscope service (SQLAlchemy 2.0, typed).

One recording travels through these tables::

    Patient ─< RecordingSession ─< Trial ─< Video (left, right; each with a browser proxy)
                     │                 └── Job (kind "analyze_trial") ──> Result (revisions 1, 2...)
                     └── Rig ─< Calibration ─< Video (board recordings)
                                      └── Job (kind "calibrate")

Conventions that every caller must keep
---------------------------------------
- **Timestamps are timezone-aware UTC** (:class:`UTCDateTime`). Binding a naive
  ``datetime`` raises ``ValueError``; use :func:`utcnow` or convert with
  ``dt.astimezone(UTC)``. Values read back are always aware UTC, on SQLite too.
- **Enumerated columns are plain strings** checked by a named CHECK constraint;
  the allowed values are the module constants (``ROLES``, ``JOB_STATUSES``...).
- **Files are stored under the data directory** (see :mod:`app.storage`);
  ``Video.path`` and ``Result.markers_path`` are *relative* to it.
- The model class for a clinical session is :class:`RecordingSession` (table
  ``sessions``), so that it is never confused with SQLAlchemy's ``Session``.
- Soft deletion: patients and sessions have ``deleted_at``; rows are kept so
  that audit history stays meaningful. :class:`AuditEvent` has no foreign keys
  on purpose (it outlives what it describes) and holds no clinical values
  (the values an update changed are in :class:`FieldChange`, erased with the patient).
- Every schema change goes through an Alembic migration in ``migrations/``;
  ``tests/app/test_migrations.py`` fails on any drift.

One module on purpose (more than 500 lines): the schema is read as a whole, and
its relationships refer to each other. Queries live in the services
(``app.services``); the one here,
:func:`next_calibration_version`, guards a UNIQUE constraint of these tables.
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any, ClassVar, Final

import sqlalchemy as sa
from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    CheckConstraint,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Text,
    UniqueConstraint,
    event,
    select,
)
from sqlalchemy.engine import Connection, Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, Mapper, mapped_column, relationship
from sqlalchemy.orm import Session as DbSession
from sqlalchemy.types import TypeDecorator

from core.tasks import TASKS

# Allowed values of the enumerated string columns.
ROLES = ("clinician", "admin", "auditor")
SEXES = ("female", "male", "other", "unknown")
MEDICATION_STATES = ("on", "off", "unknown")
DBS_STATES = ("on", "off", "none", "unknown")
HANDS = ("left", "right")
"""The side of a trial: the hand, or the foot for toe tapping."""
MORE_AFFECTED_SIDES = ("left", "right", "equal")
DOMINANT_HANDS = ("left", "right", "both")
CLINICIAN_RATINGS = (0, 1, 2, 3, 4)
SIDES = ("left", "right")
CALIBRATION_SOURCES = ("rig_file", "board_videos")
CALIBRATION_STATUSES = ("pending", "ready", "failed")
CALIBRATION_VERDICTS = ("good", "acceptable", "poor")
TRIAL_STATUSES = ("queued", "running", "succeeded", "failed")
JOB_KINDS = ("analyze_trial", "calibrate", "report_pdf")
JOB_STATUSES = ("queued", "running", "succeeded", "failed")
RESULT_KINDS = ("analysis", "correction")
"""A result revision measured from the videos (``analysis``) or a clinician's correction of one."""
ACTOR_TYPES = ("user", "api_client", "system", "anonymous")
ACTOR_ANONYMOUS: Final = "anonymous"
"""Actor type of a request by nobody known yet, e.g. a failed login (no ``actor_id``)."""

# Stable constraint names, so that batch migrations on SQLite can address them.
NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utcnow() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """A timestamp stored as UTC and always read back timezone-aware (UTC).

    PostgreSQL stores ``timestamp with time zone``; SQLite stores the UTC
    wall-clock time as text (which sorts and compares correctly).
    """

    impl = sa.DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if not isinstance(value, datetime):
            raise ValueError(f"expected a datetime, got {type(value).__name__}")
        if value.tzinfo is None or value.utcoffset() is None:
            raise ValueError(
                f"naive datetime {value.isoformat()} given; timestamps must be timezone-aware "
                "(use app.models.utcnow() or dt.astimezone(UTC))"
            )
        value = value.astimezone(UTC)
        if dialect.name == "sqlite":
            return value.replace(tzinfo=None)
        return value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value.astimezone(UTC)


def _in(column: str, values: tuple[str, ...]) -> str:
    quoted = ", ".join(f"'{v}'" for v in values)
    return f"{column} IN ({quoted})"


class Base(DeclarativeBase):
    """Declarative base with the constraint naming convention."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map: ClassVar[dict[Any, Any]] = {
        datetime: UTCDateTime(),
        dict[str, Any]: JSON(),
        list[str]: JSON(),
    }


# --------------------------------------------------------------------------- people


class User(Base):
    """A person who logs in to the web interface: a clinician or an admin."""

    __tablename__ = "users"
    __table_args__ = (CheckConstraint(_in("role", ROLES), name="role"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    email: Mapped[str] = mapped_column(String(320), unique=True)
    """Stored lower-cased; unique."""
    password_hash: Mapped[str] = mapped_column(String(255))
    """argon2 hash from :func:`app.passwords.hash_password`."""
    role: Mapped[str] = mapped_column(String(16), default="clinician")
    display_name: Mapped[str | None] = mapped_column(String(200))
    is_active: Mapped[bool] = mapped_column(Boolean, default=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    last_login_at: Mapped[datetime | None]
    oidc_subject: Mapped[str | None] = mapped_column(String(255), unique=True, index=True)
    """The identity provider's ``sub`` (single sign-on), bound at the first such login."""


class ApiClient(Base):
    """A hospital system calling the REST API with a Bearer key (see :mod:`app.apikeys`)."""

    __tablename__ = "api_clients"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(100), unique=True)
    key_prefix: Mapped[str] = mapped_column(String(32), unique=True)
    """The public lookup part of the key (``bsk_<prefix>_<secret>``)."""
    key_hash: Mapped[str] = mapped_column(String(128))
    """SHA-256 (hex) of the whole key; see :func:`app.apikeys.hash_api_key`."""
    scopes: Mapped[list[str]] = mapped_column(JSON, default=list)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    revoked_at: Mapped[datetime | None]
    last_used_at: Mapped[datetime | None]
    created_by_user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id"))
    owner_user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id"))
    """The person answerable for the key; the key stops working when they are deactivated."""
    expires_at: Mapped[datetime | None]
    """The key is refused from this time on (NULL: keys made before expiry dates existed)."""


class BrowserSession(Base):
    """A logged-in browser. ``id`` is the SHA-256 (hex) of the cookie token, never the token."""

    __tablename__ = "browser_sessions"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    csrf_token: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(index=True)
    last_seen_at: Mapped[datetime] = mapped_column(default=utcnow)
    ip: Mapped[str | None] = mapped_column(String(45))
    user_agent: Mapped[str | None] = mapped_column(String(300))

    user: Mapped[User] = relationship()


class LoginThrottle(Base):
    """The failure streak of one account, or of one (address, account) pair (see ``app.throttle``).

    ``key`` is the SHA-256 (hex) of ``"account|<email_hash>"`` or of
    ``"pair|<ip>|<email_hash>"``; ``email_hash`` is the SHA-256 (hex) of the
    lower-cased e-mail address (so ``admin unlock`` finds every row of an
    account, and unknown addresses are throttled like known ones).
    ``failures`` counts the attempts admitted since the last success; an
    attempt is counted when it is admitted, before its password is checked,
    so that concurrent attempts cannot all pass the limit.
    """

    __tablename__ = "login_throttles"

    key: Mapped[str] = mapped_column(String(64), primary_key=True)
    email_hash: Mapped[str] = mapped_column(String(64), index=True)
    ip: Mapped[str | None] = mapped_column(String(45))
    """The address of a pair's row; NULL for the account's own row."""
    failures: Mapped[int] = mapped_column(Integer, default=0)
    blocked_until: Mapped[datetime | None]
    """No attempt is admitted before this time (the growing delay)."""
    last_attempt_at: Mapped[datetime] = mapped_column(default=utcnow, index=True)


# --------------------------------------------------------------------------- patients


class Patient(Base):
    """A patient, known to bradyscope only by a pseudonymous code (e.g. ``PD-0042``)."""

    __tablename__ = "patients"
    __table_args__ = (CheckConstraint(f"sex IS NULL OR {_in('sex', SEXES)}", name="sex"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    code: Mapped[str] = mapped_column(String(64), unique=True)
    birth_year: Mapped[int | None] = mapped_column(Integer)
    sex: Mapped[str | None] = mapped_column(String(16))
    notes: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    deleted_at: Mapped[datetime | None]
    erased_at: Mapped[datetime | None]
    """When the patient's data was erased (``app.services.erasure``): the row is then a
    tombstone whose ``code`` is a keyed hash of the real one, kept for the audit trail."""

    sessions: Mapped[list[RecordingSession]] = relationship(
        back_populates="patient", order_by="RecordingSession.recorded_at"
    )


# --------------------------------------------------------------------------- rigs


class Rig(Base):
    """A physical two-camera set-up in a clinic."""

    __tablename__ = "rigs"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(100), unique=True)
    description: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    calibrations: Mapped[list[Calibration]] = relationship(
        back_populates="rig", order_by="Calibration.version"
    )


class Calibration(Base):
    """One version of a rig's calibration, valid from ``valid_from`` on.

    ``rig_json`` is the rig file document (INTERFACES.md, ``bradyscope.rig/1``);
    it is NULL while a board-video calibration is ``pending`` and stays NULL
    when it ``failed`` (the job's ``error`` says why).
    """

    __tablename__ = "calibrations"
    __table_args__ = (
        UniqueConstraint("rig_id", "version", name="uq_calibrations_rig_id_version"),
        CheckConstraint(_in("source", CALIBRATION_SOURCES), name="source"),
        CheckConstraint(_in("status", CALIBRATION_STATUSES), name="status"),
        CheckConstraint("status != 'ready' OR rig_json IS NOT NULL", name="ready_has_rig"),
        CheckConstraint(
            f"verdict IS NULL OR {_in('verdict', CALIBRATION_VERDICTS)}", name="verdict"
        ),
        CheckConstraint("status != 'ready' OR verdict IS NOT NULL", name="ready_has_verdict"),
        Index("ix_calibrations_rig_id_valid_from", "rig_id", "valid_from"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    rig_id: Mapped[int] = mapped_column(ForeignKey("rigs.id"))
    version: Mapped[int] = mapped_column(Integer)
    """1, 2, 3... per rig; see :func:`next_calibration_version`."""
    valid_from: Mapped[datetime]
    rig_json: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    rms_px: Mapped[float | None] = mapped_column(Float)
    quality: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    verdict: Mapped[str | None] = mapped_column(String(16))
    """``good``, ``acceptable`` or ``poor``, judged once when the calibration became ready
    (``core.calibration.quality_verdict``); NULL while pending or failed."""
    verdict_reasons: Mapped[list[str] | None] = mapped_column(JSON)
    """One sentence per quality figure that is not good (empty when all are)."""
    source: Mapped[str] = mapped_column(String(16))
    status: Mapped[str] = mapped_column(String(16), default="pending")
    board: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    """Board description for ``board_videos`` (board, cols, rows, square_mm, marker_mm, dictionary)."""
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    created_by_user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id"))

    rig: Mapped[Rig] = relationship(back_populates="calibrations")
    videos: Mapped[list[Video]] = relationship(back_populates="calibration")

    def judge(self) -> None:
        """Judge the quality figures (:func:`calibration_verdict`) into ``verdict`` and its reasons.

        Runs by itself when a ``ready`` calibration without a verdict is
        inserted or updated through the session (see :func:`_judge_when_ready`).
        """
        self.verdict, self.verdict_reasons = calibration_verdict(self.quality, self.rms_px)


def calibration_verdict(
    quality: Mapping[str, Any] | None, rms_px: float | None = None
) -> tuple[str, list[str]]:
    """``(verdict, reasons)`` of a calibration's quality figures (``core.calibration``'s rule).

    ``rms_px`` (the calibration's column) counts when the figures lack it. The
    one place the service judges a calibration; the result is stored in
    ``Calibration.verdict`` and ``Calibration.verdict_reasons``.
    """
    from core.calibration import quality_verdict  # OpenCV and SciPy: not at start-up

    figures = dict(quality or {})
    if rms_px is not None:
        figures.setdefault("rms_px", rms_px)
    verdict, reasons = quality_verdict(figures)
    return str(verdict), [str(r) for r in reasons]


@event.listens_for(Calibration, "before_insert")
@event.listens_for(Calibration, "before_update")
def _judge_when_ready(
    mapper: Mapper[Calibration], connection: Connection, target: Calibration
) -> None:
    """A calibration is judged once, when it is stored ready without a verdict."""
    if target.status == "ready" and target.verdict is None:
        target.judge()


# --------------------------------------------------------------------------- recordings


class RecordingSession(Base):
    """A clinical session: one patient, one rig, one time, usually two trials (hands)."""

    __tablename__ = "sessions"
    __table_args__ = (
        CheckConstraint(_in("medication_state", MEDICATION_STATES), name="medication_state"),
        CheckConstraint(_in("dbs_state", DBS_STATES), name="dbs_state"),
        CheckConstraint(
            f"more_affected_side IS NULL OR {_in('more_affected_side', MORE_AFFECTED_SIDES)}",
            name="more_affected_side",
        ),
        CheckConstraint(
            f"dominant_hand IS NULL OR {_in('dominant_hand', DOMINANT_HANDS)}",
            name="dominant_hand",
        ),
        CheckConstraint(
            "time_since_levodopa_min IS NULL OR time_since_levodopa_min >= 0",
            name="time_since_levodopa_min",
        ),
        Index("ix_sessions_patient_id_recorded_at", "patient_id", "recorded_at"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    patient_id: Mapped[int] = mapped_column(ForeignKey("patients.id"))
    rig_id: Mapped[int] = mapped_column(ForeignKey("rigs.id"))
    calibration_id: Mapped[int | None] = mapped_column(ForeignKey("calibrations.id"))
    """Override of the calibration lookup; NULL = newest valid one (:func:`calibration_for`)."""
    recorded_at: Mapped[datetime]
    clinician_user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id"))
    medication_state: Mapped[str] = mapped_column(String(16), default="unknown")
    dbs_state: Mapped[str] = mapped_column(String(16), default="unknown")
    notes: Mapped[str | None] = mapped_column(Text)
    time_since_levodopa_min: Mapped[int | None] = mapped_column(Integer)
    """Minutes from the last levodopa dose to the recording; NULL when not recorded."""
    more_affected_side: Mapped[str | None] = mapped_column(String(8))
    """The more affected side as the clinician judges it: left, right or equal."""
    dominant_hand: Mapped[str | None] = mapped_column(String(8))
    """left, right or both (ambidextrous)."""
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    deleted_at: Mapped[datetime | None]

    patient: Mapped[Patient] = relationship(back_populates="sessions")
    rig: Mapped[Rig] = relationship()
    calibration: Mapped[Calibration | None] = relationship()
    trials: Mapped[list[Trial]] = relationship(back_populates="session", order_by="Trial.id")


class Trial(Base):
    """One recording of one task (finger tapping by default) on one side: two videos, one
    analysis job, one result."""

    __tablename__ = "trials"
    __table_args__ = (
        CheckConstraint(_in("hand", HANDS), name="hand"),
        CheckConstraint(_in("task", TASKS), name="task"),
        CheckConstraint(_in("status", TRIAL_STATUSES), name="status"),
        CheckConstraint(
            "clinician_rating IS NULL OR (clinician_rating >= 0 AND clinician_rating <= 4)",
            name="clinician_rating",
        ),
        Index("ix_trials_session_id_take_id", "session_id", "take_id", unique=True),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    session_id: Mapped[int] = mapped_column(ForeignKey("sessions.id"), index=True)
    take_id: Mapped[str | None] = mapped_column(String(64))
    """The capture page's id of the take (unique in the session): a take sent again after
    a lost connection is not stored twice. NULL for other uploads."""
    hand: Mapped[str] = mapped_column(String(8))
    """The side: left or right hand (or foot, for toe tapping; leg, for leg agility)."""
    rig_id: Mapped[int | None] = mapped_column(ForeignKey("rigs.id"))
    """The rig that recorded this trial when it is not the session's: toe tapping and leg
    agility film the foot and leg from another placement of the cameras, calibrated as a
    rig of its own (docs/protocols.md). NULL: the session's rig."""
    task: Mapped[str] = mapped_column(
        String(32), default="finger_tapping", server_default="finger_tapping"
    )
    """The MDS-UPDRS item recorded (``core.tasks.Task``): finger_tapping, hand_movements,
    pronation_supination, toe_tapping or leg_agility."""
    status: Mapped[str] = mapped_column(String(16), default="queued")
    """Mirrors the analysis job: queued, running, succeeded, failed."""
    offset_frames: Mapped[float | None] = mapped_column(Float)
    """Known camera offset (right frame j ~ left frame j + K); NULL = estimate it."""
    clinician_rating: Mapped[int | None] = mapped_column(Integer)
    """The clinician's own MDS-UPDRS rating of this side's item (3.4–3.8 by the task), 0–4."""
    rating_comment: Mapped[str | None] = mapped_column(Text)
    rated_at: Mapped[datetime | None]
    rated_by_user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id"))
    """The user who rated (NULL when an API client set the rating)."""
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    deleted_at: Mapped[datetime | None]
    """Set when the trial is hidden (soft-deleted); an admin can restore it."""
    deleted_reason: Mapped[str | None] = mapped_column(Text)
    """Why it was hidden (required when hiding from the pages or the API)."""
    deleted_by: Mapped[str | None] = mapped_column(String(320))
    """Who hid it (user e-mail or API client name)."""

    session: Mapped[RecordingSession] = relationship(back_populates="trials")
    rig: Mapped[Rig | None] = relationship()
    """The trial's own rig (None: the session's)."""
    rated_by: Mapped[User | None] = relationship()
    videos: Mapped[list[Video]] = relationship(back_populates="trial", order_by="Video.side")
    results: Mapped[list[Result]] = relationship(back_populates="trial", order_by="Result.revision")
    """Every revision of the trial's result, oldest first (none kept is ever changed)."""

    @property
    def result(self) -> Result | None:
        """The current (newest) revision of the result, None before the first analysis."""
        return self.results[-1] if self.results else None

    def revision(self, number: int) -> Result | None:
        """Revision ``number`` (1 = the first analysis), None if there is none."""
        return next((r for r in self.results if r.revision == number), None)


class Video(Base):
    """A stored video file of a trial or of a calibration (exactly one of the two)."""

    __tablename__ = "videos"
    __table_args__ = (
        CheckConstraint(_in("side", SIDES), name="side"),
        CheckConstraint(
            "(trial_id IS NULL) != (calibration_id IS NULL)", name="trial_xor_calibration"
        ),
        UniqueConstraint("trial_id", "side", name="uq_videos_trial_id_side"),
        UniqueConstraint("calibration_id", "side", name="uq_videos_calibration_id_side"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    trial_id: Mapped[int | None] = mapped_column(ForeignKey("trials.id"))
    calibration_id: Mapped[int | None] = mapped_column(ForeignKey("calibrations.id"))
    side: Mapped[str] = mapped_column(String(8))
    path: Mapped[str] = mapped_column(String(500), unique=True)
    """Relative to the data directory (``app.storage.Storage.absolute(path)``)."""
    original_filename: Mapped[str | None] = mapped_column(String(255))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64))
    fps: Mapped[float] = mapped_column(Float)
    frame_count: Mapped[int] = mapped_column(Integer)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    codec: Mapped[str | None] = mapped_column(String(16))
    """FOURCC as probed."""
    proxy_path: Mapped[str | None] = mapped_column(String(500))
    """A browser-playable H.264 copy (``core.video.write_proxy``), relative to the data
    directory; made at the trial's first analysis. The original is never changed."""
    times_path: Mapped[str | None] = mapped_column(String(500), unique=True)
    """The timestamps file uploaded with the video (``frame,time_s`` CSV, each frame's
    capture time on that camera's clock), relative to the data directory; NULL: none."""
    times_sha256: Mapped[str | None] = mapped_column(String(64))
    duration_s: Mapped[float | None] = mapped_column(Float)
    """Length of the recording (s): from its capture times when a timestamps file came
    with it (then ``fps`` is the measured rate too), else ``frame_count / fps``."""
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    trial: Mapped[Trial | None] = relationship(back_populates="videos")
    calibration: Mapped[Calibration | None] = relationship(back_populates="videos")

    @property
    def has_times(self) -> bool:
        """Whether a timestamps file is stored with the video."""
        return self.times_path is not None


# --------------------------------------------------------------------------- jobs, results


class Job(Base):
    """A unit of long work for the worker (see :mod:`app.jobs` for the life cycle)."""

    __tablename__ = "jobs"
    __table_args__ = (
        CheckConstraint(_in("status", JOB_STATUSES), name="status"),
        CheckConstraint("progress >= 0 AND progress <= 1", name="progress"),
        Index("ix_jobs_status_run_after", "status", "run_after"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    kind: Mapped[str] = mapped_column(String(32))
    """``analyze_trial``, ``calibrate`` or ``report_pdf`` (``JOB_KINDS``)."""
    status: Mapped[str] = mapped_column(String(16), default="queued")
    trial_id: Mapped[int | None] = mapped_column(ForeignKey("trials.id"), index=True)
    calibration_id: Mapped[int | None] = mapped_column(ForeignKey("calibrations.id"), index=True)
    payload: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    """Fraction 0–1 of the current attempt."""
    stage: Mapped[str | None] = mapped_column(String(64))
    error: Mapped[str | None] = mapped_column(Text)
    """User-facing sentence of the last failure (tracebacks go to the log only)."""
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer, default=3)
    run_after: Mapped[datetime] = mapped_column(default=utcnow)
    """Not claimed before this time (retry back-off)."""
    lease_owner: Mapped[str | None] = mapped_column(String(100))
    """Unique token of the claim currently holding the job (worker name + random)."""
    lease_expires_at: Mapped[datetime | None]
    heartbeat_at: Mapped[datetime | None]
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]

    trial: Mapped[Trial | None] = relationship()
    calibration: Mapped[Calibration | None] = relationship()


class Result(Base):
    """One revision of a trial's measurement: the full ``result.json`` and its files.

    Revisions are numbered 1, 2... per trial (UNIQUE ``(trial_id, revision)``);
    the newest is current and none is ever changed or removed. An ``analysis``
    revision is measured from the videos by the worker (the first one, or a
    re-analysis with a given offset or swapped cameras), inserted in the
    transaction that marks its job succeeded; a ``correction`` revision is a
    clinician's correction of the newest analysis (``base_revision``), measured
    again from its stored trajectories. ``created_by``, ``reason`` and ``change``
    say who asked for a revision after the first, why, and what changed.
    """

    __tablename__ = "results"
    __table_args__ = (
        UniqueConstraint("trial_id", "revision", name="uq_results_trial_revision"),
        CheckConstraint(_in("kind", RESULT_KINDS), name="kind"),
        CheckConstraint("revision >= 1", name="revision"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    trial_id: Mapped[int] = mapped_column(ForeignKey("trials.id"), index=True)
    revision: Mapped[int] = mapped_column(Integer, default=1)
    kind: Mapped[str] = mapped_column(String(16), default="analysis")
    base_revision: Mapped[int | None] = mapped_column(Integer)
    """For a correction: the analysis revision whose trajectories were measured again."""
    job_id: Mapped[int | None] = mapped_column(ForeignKey("jobs.id"))
    calibration_id: Mapped[int | None] = mapped_column(ForeignKey("calibrations.id"))
    document: Mapped[dict[str, Any]] = mapped_column(JSON)
    """``result.json`` (INTERFACES.md, ``bradyscope.result/1``), with ``revision`` and ``edits``."""
    markers_path: Mapped[str | None] = mapped_column(String(500))
    """``markers.csv``, relative to the data directory (shared by revisions that keep it)."""
    overlay_path: Mapped[str | None] = mapped_column(String(500))
    """The review view's overlay (``core.overlay``, JSON), relative to the data directory."""
    plots_path: Mapped[str | None] = mapped_column(String(500))
    """The revision's plots drawn once (``app.reports.figures.plots_document``, JSON)."""
    created_by: Mapped[str | None] = mapped_column(String(320))
    """Who asked for this revision (user e-mail or API client name); None for the first."""
    created_by_user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id"))
    reason: Mapped[str | None] = mapped_column(Text)
    change: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    """What this revision changed (the request), e.g. ``{"exclude_taps": [3]}``."""
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    trial: Mapped[Trial] = relationship(back_populates="results")
    calibration: Mapped[Calibration | None] = relationship()


class Signature(Base):
    """A clinician's signature of a visit report: who, when, and the signed PDF's SHA-256.

    A visit is the patient's sessions on one day (``visit_date``, in the clinic's
    time zone); signatures are numbered 1, 2... per visit, a later one amending
    the one before. ``pdf_path`` holds the signed bytes, served unchanged;
    ``trial_revisions`` maps each signed trial (id as text) to its result
    revision, ``signed_facts`` the ratings and session facts it printed. The
    database refuses any UPDATE of a signature (migration 0009);
    rows go only with the erasure of the patient.
    """

    __tablename__ = "signatures"
    __table_args__ = (
        UniqueConstraint("patient_id", "visit_date", "number", name="uq_signatures_visit_number"),
        Index("ix_signatures_session_id", "session_id"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    patient_id: Mapped[int] = mapped_column(ForeignKey("patients.id"))
    session_id: Mapped[int] = mapped_column(ForeignKey("sessions.id"))
    """The session the visit was signed through (any session of that day)."""
    visit_date: Mapped[str] = mapped_column(String(10))
    """ISO date of the visit in the clinic's time zone."""
    number: Mapped[int] = mapped_column(Integer)
    amends_number: Mapped[int | None] = mapped_column(Integer)
    signed_by: Mapped[str] = mapped_column(String(320))
    signed_by_user_id: Mapped[int] = mapped_column(ForeignKey("users.id"))
    signed_at: Mapped[datetime]
    sha256: Mapped[str] = mapped_column(String(64))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    pdf_path: Mapped[str] = mapped_column(String(500), unique=True)
    """The signed PDF, relative to the data directory."""
    trial_revisions: Mapped[dict[str, Any]] = mapped_column(JSON)
    signed_facts: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    """What the signed report printed beyond the results (``app.services.signatures``):
    None for signatures made before migration 0017."""


# --------------------------------------------------------------------------- audit


class AuditEvent(Base):
    """Who did what to which patient's data, when, with what outcome. Append-only.

    No foreign keys (the trail outlives deleted rows) and no clinical values.
    ``actor_id`` is the user or API-client id as text (NULL for ``system``
    and ``anonymous``).
    """

    __tablename__ = "audit_events"
    __table_args__ = (
        CheckConstraint(_in("actor_type", ACTOR_TYPES), name="actor_type"),
        Index("ix_audit_events_patient_id_at", "patient_id", "at"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    actor_type: Mapped[str] = mapped_column(String(16))
    actor_id: Mapped[str | None] = mapped_column(String(64))
    action: Mapped[str] = mapped_column(String(64))
    """A verb such as ``read``, ``create``, ``update``, ``delete``, ``export``, ``login``."""
    resource_type: Mapped[str] = mapped_column(String(32))
    resource_id: Mapped[str | None] = mapped_column(String(64))
    patient_id: Mapped[int | None] = mapped_column(Integer)
    outcome: Mapped[str] = mapped_column(String(16), default="success")
    """``success``, ``denied``, ``not_found``, ``error``..."""
    ip: Mapped[str | None] = mapped_column(String(45))
    request_id: Mapped[str | None] = mapped_column(String(64))
    seq: Mapped[int | None] = mapped_column(BigInteger, unique=True, index=True)
    """The event's number in the hash chain (``app.chain``); NULL for events older than it."""
    hash: Mapped[str | None] = mapped_column(String(64))
    """HMAC-SHA256 of the previous event's hash and this event's fields."""
    details: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    """Sealed with the rest (``app.chain``): identifiers and field names only, e.g. an
    update's ``{"fields": [...], "values_sha256": ...}`` (:class:`FieldChange`)."""


class FieldChange(Base):
    """The previous and new values of the fields one update changed, beside its audit event.

    The event names the fields and seals ``values_sha256``, the SHA-256 of ``nonce`` and
    ``changes`` (:mod:`app.services.changes`), so an altered row shows; the values are
    the patient's data, so the row refers to the patient and is erased with them (the
    nonce with it: the digest left in the trail then tells nothing).
    """

    __tablename__ = "field_changes"

    id: Mapped[int] = mapped_column(primary_key=True)
    event_id: Mapped[int] = mapped_column(Integer, index=True)
    """The :class:`AuditEvent`'s id; no foreign key, as nothing holds the trail's rows
    (a TRUNCATE of it is refused by its own trigger, not by another table)."""
    patient_id: Mapped[int] = mapped_column(ForeignKey("patients.id"), index=True)
    changes: Mapped[dict[str, Any]] = mapped_column(JSON)
    """``{field: [previous, new]}``, values as the API shows them."""
    nonce: Mapped[str] = mapped_column(String(32))

    event: Mapped[AuditEvent] = relationship(
        primaryjoin="foreign(FieldChange.event_id) == AuditEvent.id"
    )


class AuditEventPatient(Base):
    """A patient whose data one event returned beyond its own ``patient_id``: a patient a
    list returned (``list``, e.g. the patient list), or one whose previous and new values
    a read of the audit trail showed (``read`` ``field_changes``,
    :func:`app.audit.audit_values_shown`). The index the trail's patient filter looks
    into; the event's ``details`` hold the same ids (``patient_ids``), sealed, and
    ``verify-audit`` checks the two agree. No foreign keys (the trail outlives what it
    describes)."""

    __tablename__ = "audit_event_patients"

    event_id: Mapped[int] = mapped_column(Integer, primary_key=True)
    patient_id: Mapped[int] = mapped_column(Integer, primary_key=True, index=True)

    event: Mapped[AuditEvent] = relationship(
        primaryjoin="foreign(AuditEventPatient.event_id) == AuditEvent.id"
    )


class AuditHead(Base):
    """The newest number and hash of the audit chain: one row, updated with every event."""

    __tablename__ = "audit_head"
    __table_args__ = (CheckConstraint("id = 1", name="one_row"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    seq: Mapped[int] = mapped_column(BigInteger)
    hash: Mapped[str] = mapped_column(String(64))


# --------------------------------------------------------------------------- services


def next_calibration_version(db: DbSession, rig_id: int) -> int:
    """The version number for a new calibration of ``rig_id`` (1 for the first).

    Two concurrent inserts of the same version collide on the UNIQUE
    ``(rig_id, version)`` constraint rather than silently sharing a number.
    """
    current = db.scalar(
        select(sa.func.max(Calibration.version)).where(Calibration.rig_id == rig_id)
    )
    return int(current or 0) + 1


__all__ = [
    "ACTOR_ANONYMOUS",
    "ACTOR_TYPES",
    "CALIBRATION_SOURCES",
    "CALIBRATION_STATUSES",
    "CALIBRATION_VERDICTS",
    "CLINICIAN_RATINGS",
    "DBS_STATES",
    "DOMINANT_HANDS",
    "HANDS",
    "JOB_KINDS",
    "JOB_STATUSES",
    "MEDICATION_STATES",
    "MORE_AFFECTED_SIDES",
    "RESULT_KINDS",
    "ROLES",
    "SEXES",
    "SIDES",
    "TRIAL_STATUSES",
    "ApiClient",
    "AuditEvent",
    "AuditEventPatient",
    "AuditHead",
    "Base",
    "BrowserSession",
    "Calibration",
    "FieldChange",
    "Job",
    "LoginThrottle",
    "Patient",
    "RecordingSession",
    "Result",
    "Rig",
    "Signature",
    "Trial",
    "UTCDateTime",
    "User",
    "Video",
    "calibration_verdict",
    "next_calibration_version",
    "utcnow",
]

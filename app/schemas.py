"""Request and response bodies of the REST API (pydantic 2): ``XCreate``, ``XRead``, ``XUpdate``.

Field names carry their units (``size_bytes``, ``fps``, ``rms_px``) like the
database columns and ``result.json``. Timestamps are ISO 8601; a timestamp
sent without a time zone is taken as UTC, and every timestamp returned is UTC.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any, Generic, Literal, TypeVar

from fastapi import Path
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    StringConstraints,
    model_validator,
)

T = TypeVar("T")

MedicationState = Literal["on", "off", "unknown"]
DbsState = Literal["on", "off", "none", "unknown"]
Hand = Literal["left", "right"]
MoreAffectedSide = Literal["left", "right", "equal"]
DominantHand = Literal["left", "right", "both"]
Sex = Literal["female", "male", "other", "unknown"]
JobStatus = Literal["queued", "running", "succeeded", "failed"]


MAX_ID = 2**31 - 1  # ids are 32-bit integers in PostgreSQL


def _as_utc(value: datetime) -> datetime:
    if not 1900 <= value.year <= 2200:
        raise ValueError("the date must lie between the years 1900 and 2200")
    if value.tzinfo is None or value.utcoffset() is None:
        return value.replace(tzinfo=UTC)
    return value.astimezone(UTC)


def _no_nul(value: str) -> str:
    if "\x00" in value:
        raise ValueError("text must not contain NUL characters")
    return value


UtcDateTime = Annotated[datetime, AfterValidator(_as_utc)]
PatientCode = Annotated[
    str,
    StringConstraints(
        strip_whitespace=True, min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$"
    ),
    Field(
        description="Pseudonymous patient code (letters, digits, '.', '_', '-'), e.g. PD-0042;"
        " never a name or a hospital number.",
        examples=["PD-0042"],
    ),
]
ShortText = Annotated[
    str, StringConstraints(strip_whitespace=True, max_length=2000), AfterValidator(_no_nul)
]
Name = Annotated[
    str,
    StringConstraints(strip_whitespace=True, min_length=1, max_length=100),
    AfterValidator(_no_nul),
]
# Numbers of request bodies are strict: JSON true, "2" or 2.0 is not a rating, a tap or an id
# (pydantic would read them as 1 and 2).
Id = Annotated[int, Strict(), Field(ge=1, le=MAX_ID)]
IdPath = Annotated[int, Path(ge=1, le=MAX_ID, description="Numeric id.")]
"""An id in a path, API or page: larger ones do not exist (and would overflow the database)."""


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid")


class _Out(BaseModel):
    model_config = ConfigDict(from_attributes=True)


# --------------------------------------------------------------------------- common


class ErrorIssue(BaseModel):
    """One problem of an invalid request (location, message, kind)."""

    loc: list[str]
    msg: str
    type: str


class ErrorResponse(BaseModel):
    """Every error: one sentence saying what was wrong and what to do."""

    detail: str = Field(examples=["The patient 17 does not exist."])
    errors: list[ErrorIssue] | None = Field(
        default=None, description="For 422 validation errors: each invalid field."
    )


class Created(BaseModel):
    """The id of a newly created resource."""

    id: int


class Page(BaseModel, Generic[T]):
    """One page of a list; ask for the next with ``offset + limit``."""

    items: list[T]
    total: int = Field(description="Number of matching items in all pages.")
    limit: int
    offset: int


# --------------------------------------------------------------------------- patients


class PatientCreate(_In):
    code: PatientCode
    birth_year: Annotated[int, Strict()] | None = Field(default=None, ge=1900, le=2100)
    sex: Sex | None = None
    notes: ShortText | None = None


class PatientUpdate(_In):
    """Fields to change; omitted fields stay as they are."""

    code: PatientCode | None = None
    birth_year: Annotated[int, Strict()] | None = Field(default=None, ge=1900, le=2100)
    sex: Sex | None = None
    notes: ShortText | None = None


class PatientRead(_Out):
    id: int
    code: str
    birth_year: int | None
    sex: str | None
    notes: str | None
    created_at: datetime


# --------------------------------------------------------------------------- rigs, calibrations


class RigCreate(_In):
    name: Name = Field(examples=["clinic-A"])
    description: ShortText | None = None


class RigRead(_Out):
    id: int
    name: str
    description: str | None
    created_at: datetime


class CalibrationCreated(BaseModel):
    """A new calibration; ``job_id`` is set when board videos have to be computed first."""

    id: int
    job_id: int | None = None
    status: Literal["pending", "ready", "failed"]


class CalibrationRead(_Out):
    id: int
    rig_id: int
    version: int = Field(description="1, 2, 3... per rig.")
    valid_from: datetime = Field(description="Sessions recorded from this time on use it.")
    status: Literal["pending", "ready", "failed"]
    source: Literal["rig_file", "board_videos"]
    rms_px: float | None = Field(description="Reprojection RMS of the calibration, pixels.")
    quality: dict[str, Any] | None
    board: dict[str, Any] | None
    created_at: datetime
    job_id: int | None = None
    error: str | None = Field(default=None, description="Why a board calibration failed.")


# --------------------------------------------------------------------------- sessions


RATING_MOVED = (
    "updrs_34_rating is no longer a session field: the MDS-UPDRS rating is given per trial"
    " (per hand); send it as clinician_rating with PATCH /api/v1/trials/{trial_id}."
)


def _no_session_rating(data: Any) -> Any:
    if isinstance(data, dict) and "updrs_34_rating" in data:
        raise ValueError(RATING_MOVED)
    return data


LevodopaMinutes = Annotated[
    int,
    Strict(),
    Field(
        ge=0,
        le=7 * 24 * 60,
        description="Minutes from the last levodopa dose to the recording.",
    ),
]


class _SessionFields(_In):
    notes: ShortText | None = None
    time_since_levodopa_min: LevodopaMinutes | None = None
    more_affected_side: MoreAffectedSide | None = Field(
        default=None, description="The more affected side, as the clinician judges it."
    )
    dominant_hand: DominantHand | None = None

    @model_validator(mode="before")
    @classmethod
    def _rating_moved(cls, data: Any) -> Any:
        return _no_session_rating(data)


class SessionCreate(_SessionFields):
    patient_id: Id
    rig_id: Id
    recorded_at: UtcDateTime = Field(description="When the recording was made (UTC if no zone).")
    medication_state: MedicationState = "unknown"
    dbs_state: DbsState = "unknown"
    calibration_id: Id | None = Field(
        default=None, description="Use this calibration instead of the newest valid one."
    )


class SessionUpdate(_SessionFields):
    """Fields to change; omitted fields stay as they are."""

    medication_state: MedicationState | None = None
    dbs_state: DbsState | None = None
    calibration_id: Id | None = None


class SessionRead(_Out):
    id: int
    patient_id: int
    rig_id: int
    calibration_id: int | None
    recorded_at: datetime
    medication_state: str
    dbs_state: str
    notes: str | None
    time_since_levodopa_min: int | None
    more_affected_side: str | None
    dominant_hand: str | None
    created_at: datetime


# --------------------------------------------------------------------------- trials, jobs


class VideoRead(_Out):
    side: Literal["left", "right"]
    original_filename: str | None
    size_bytes: int
    sha256: str
    fps: float
    frame_count: int
    width: int = Field(description="Pixels.")
    height: int = Field(description="Pixels.")
    codec: str | None
    duration_s: float | None = Field(
        default=None,
        description="Seconds, from the capture times when a timestamps file came with the"
        " video (fps is then the measured rate), else frame_count / fps.",
    )
    has_times: bool = Field(
        default=False, description="A timestamps file (frame,time_s) is stored with the video."
    )


class TakeRead(BaseModel):
    """The quick check of one camera's recording, known before the analysis."""

    frame_count: int
    duration_s: float = Field(description="Seconds.")
    fps: float = Field(description="Frame rate reached (Hz): from the capture times if given.")
    dropped_frames: int | None = Field(
        description="Frames lost (gaps in the capture times); null when the video's"
        " timestamps cannot tell."
    )
    time_source: Literal["file", "container", "fps"] = Field(
        description="The frame times: the timestamps file's, the video's own (container), i / fps."
    )


class TrialCreated(BaseModel):
    """The accepted trial and the analysis job measuring it."""

    id: int
    job_id: int
    warnings: list[str] = Field(default_factory=list, description="About the recording, if any.")
    take: dict[Literal["left", "right"], TakeRead] = Field(
        default_factory=dict, description="The quick check of each camera's recording."
    )
    stored_before: bool = Field(
        default=False,
        description="The take_id sent was stored before: this is that trial, nothing new"
        " was stored (a retry after a lost answer).",
    )


class TrialRead(_Out):
    id: int
    session_id: int
    hand: Literal["left", "right"] = Field(
        description="The side: hand, or foot for toe tapping, or leg for leg agility."
    )
    task: Literal[
        "finger_tapping", "hand_movements", "pronation_supination", "toe_tapping", "leg_agility"
    ] = Field(default="finger_tapping", description="The MDS-UPDRS item recorded (3.4-3.8).")
    rig_id: int = Field(
        description="The rig that recorded it: the session's, or the one named at upload"
        " (another placement of the cameras, e.g. for toe tapping or leg agility)."
    )
    status: JobStatus
    offset_frames: float | None
    created_at: datetime
    job_id: int | None = None
    has_result: bool = False
    videos: list[VideoRead] = Field(default_factory=list)
    clinician_rating: int | None = Field(
        default=None, description="The clinician's own MDS-UPDRS rating of this trial (0-4)."
    )
    comment: str | None = Field(default=None, description="The clinician's comment.")
    rated_at: datetime | None = None
    rated_by_user_id: int | None = Field(
        default=None, description="Who rated (null when an API client set the rating)."
    )


class TrialRatingUpdate(_In):
    """The clinician's rating of one trial (one hand); omitted fields stay as they are."""

    clinician_rating: Annotated[int, Strict()] | None = Field(
        default=None,
        ge=0,
        le=4,
        description="MDS-UPDRS rating of the trial's item (3.4-3.8 by its task), 0-4;"
        " null clears it.",
    )
    comment: ShortText | None = None


class JobRead(_Out):
    id: int
    kind: str
    status: JobStatus
    progress: float = Field(ge=0.0, le=1.0, description="Fraction 0-1 of the current attempt.")
    stage: str | None
    error: str | None = Field(description="Why the job failed, in plain words.")
    trial_id: int | None
    calibration_id: int | None
    created_at: datetime
    finished_at: datetime | None


# --------------------------------------------------------------------------- revisions

TapNumber = Annotated[int, Strict(), Field(ge=0, le=100_000)]
Reason = Annotated[
    str,
    StringConstraints(strip_whitespace=True, min_length=3, max_length=2000),
    AfterValidator(_no_nul),
    Field(description="Why the result is revised (kept with the revision; required)."),
]


class RevisionCreate(_In):
    """A correction (stored at once) or a re-analysis (a job) of a trial's result.

    Corrections not given stay as the current revision has them; tap numbers
    are 0-based (``taps[].index`` of the newest analysis).
    """

    reason: Reason
    exclude_taps: list[TapNumber] | None = Field(
        default=None, max_length=10_000, description="Taps that do not count (all of them)."
    )
    dismiss_pauses: list[TapNumber] | None = Field(
        default=None,
        max_length=10_000,
        description="Taps whose hesitation or halt is not one (e.g. the patient was talking).",
    )
    window_s: tuple[Annotated[float, Strict()], Annotated[float, Strict()]] | None = Field(
        default=None,
        description="Only taps wholly inside [start, end] (s) count; null: the whole recording.",
    )
    swap_labels: Annotated[bool, Strict()] | None = Field(
        default=None, description="The thumb and index labels are the wrong way round."
    )
    offset_frames: Annotated[float, Strict()] | None = Field(
        default=None,
        ge=-10_000,
        le=10_000,
        description="Measure the videos again with this offset (right frame j = left j + K).",
    )
    swap_cameras: Annotated[bool, Strict()] | None = Field(
        default=None, description="Measure again with the left and right videos exchanged."
    )


class RevisionCreated(BaseModel):
    """The new revision (a correction), or the job that will store it (a re-analysis)."""

    trial_id: int
    revision: int | None = Field(description="The new revision; null while a re-analysis runs.")
    job_id: int | None = Field(description="The re-analysis job; null for a correction.")


class RevisionRead(BaseModel):
    revision: int
    kind: Literal["analysis", "correction"]
    created_at: datetime
    created_by: str | None
    reason: str | None
    change: dict[str, Any]
    current: bool


# --------------------------------------------------------------------------- signatures


class SignRequest(_In):
    """The signing clinician's password, asked again."""

    password: Annotated[str, StringConstraints(min_length=1, max_length=1024)]


class SignatureRead(_Out):
    number: int = Field(description="1, 2... per visit; a later one amends the one before.")
    amends_number: int | None
    signed_by: str
    signed_at: datetime
    sha256: str = Field(description="SHA-256 (hex) of the signed PDF's bytes.")
    size_bytes: int
    visit_date: str
    trial_revisions: dict[str, int] = Field(description="Result revision of each signed trial.")


class VisitSignaturesRead(BaseModel):
    status: Literal["unsigned", "signed", "amendment_pending"]
    changes: list[str] = Field(description="What changed since the newest signature.")
    signatures: list[SignatureRead]


# --------------------------------------------------------------------------- auth


class LoginRequest(_In):
    email: Annotated[
        str,
        StringConstraints(strip_whitespace=True, min_length=3, max_length=320),
        AfterValidator(_no_nul),
    ]
    password: Annotated[str, StringConstraints(min_length=1, max_length=1024)]


class LoginResponse(BaseModel):
    """The session cookie is set; send ``csrf_token`` as ``X-CSRF-Token`` on changes."""

    user_id: int
    email: str
    role: str
    csrf_token: str


# --------------------------------------------------------------------------- audit


class AuditEventRead(_Out):
    """One audit event: who did what to which patient's data, when, with what outcome."""

    id: int
    seq: int | None = Field(description="Number in the hash chain (null before the chain).")
    at: datetime
    actor_type: str = Field(description="user, api_client, system or anonymous.")
    actor_id: str | None
    action: str
    resource_type: str
    resource_id: str | None
    patient_id: int | None
    outcome: str
    ip: str | None
    request_id: str | None
    hash: str | None = Field(description="HMAC-SHA256 seal chaining it to the event before.")

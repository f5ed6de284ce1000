"""What the visit report shows: :class:`VisitData` and its task groups.

A *visit* is what a patient does in clinic on one day: the sessions of one
patient on one calendar day in the clinic's time zone (typically one off
medication and one on, an hour or two apart), each with trials of a task on
one side. Page 1 of the visit report summarises every trial in one table per
task (finger tapping first): the summary block of each trial (hand ×
medication state), the right–left asymmetry and the medication response of
the key metrics, and the clinician's ratings and comments. The per-trial
detail follows.

Plain data, no database (``app.services.visits`` fills it), so that rendering
is a pure function of a :class:`VisitData` and a signed copy can be stored
and reproduced.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, date, datetime

from app.reports.data import ReportData, summary_column
from app.reports.summary import (
    TASK_ORDER,
    TASK_TITLES,
    Comparison,
    SummaryColumn,
    SummaryRow,
    asymmetry_rows,
    medication_rows,
    short_taps_note,
    summary_rows,
)
from app.timezones import to_zone
from core.tasks import parse_task

MEDICATION_ORDER = ("off", "on", "unknown")
HAND_ORDER = ("right", "left")


@dataclass(frozen=True)
class SessionFacts:
    """One session of the visit, as the report header lists it."""

    id: int
    recorded_at: datetime
    medication_state: str
    dbs_state: str
    time_since_levodopa_min: int | None = None
    more_affected_side: str | None = None
    dominant_hand: str | None = None
    notes: str | None = None
    clinician: str | None = None


@dataclass(frozen=True)
class SignatureLine:
    """The signature a signed visit report carries (filled in when it is signed).

    ``revisions`` are ``(trial id, result revision)`` pairs of what was signed;
    ``amends`` the number of the signature this one amends, if any.
    """

    signed_by: str
    signed_at: datetime
    number: int
    amends: int | None = None
    revisions: tuple[tuple[int, int], ...] = ()


@dataclass(frozen=True)
class HiddenTrial:
    """A trial of the visit that was hidden: not reported, but named with who hid it and why
    (a signature then tells what it left out, not only what it signed)."""

    trial_id: int
    task: str
    hand: str
    medication_state: str
    recorded_at: datetime
    hidden_at: datetime
    hidden_by: str | None = None
    reason: str | None = None
    uploaded_at: datetime | None = None

    def when(self, timezone: str) -> str:
        """The trial's own time (:func:`trial_time`), with its day."""
        return trial_time(self.uploaded_at, self.recorded_at, timezone, with_day=True)


@dataclass(frozen=True)
class UnmeasuredTrial:
    """A visible trial of the visit without a result: its analysis ``failed`` (``why``: the
    error the session page shows) or was still ``measuring`` when the report was made.
    Listed, so that a signature shows every take of the visit, not only those measured."""

    trial_id: int
    task: str
    hand: str
    medication_state: str
    recorded_at: datetime
    status: str
    why: str | None = None
    uploaded_at: datetime | None = None

    def when(self, timezone: str) -> str:
        """The trial's own time (:func:`trial_time`), with its day."""
        return trial_time(self.uploaded_at, self.recorded_at, timezone, with_day=True)


@dataclass(frozen=True)
class VisitData:
    """Everything the visit report shows.

    Attributes
    ----------
    patient_code : str
        The pseudonymous code; the report holds no other identifying data.
    session_id : int
        The session the report was asked for (its visit is reported).
    visit_date : date
        The day, in the clinic's time zone.
    timezone : str
        The clinic's time zone (IANA name).
    sessions : tuple of SessionFacts
        The visit's sessions in time order.
    trials : tuple of ReportData
        Every trial of the visit with a result.
    software_version : str
        The software that rendered the report (each trial names what measured it).
    generated_at : datetime (UTC)
    signature : SignatureLine or None
        Who signed this report, when, and which revisions (None: not signed).
    signatures_on_record : tuple of SignatureLine
        The visit's signatures (oldest first) when this copy is not a signed one: a
        copy made later says that it is not the signed record and where that is.
    hidden : tuple of HiddenTrial
        The visit's hidden trials, listed with who hid them, when and why.
    unmeasured : tuple of UnmeasuredTrial
        The visit's trials without a result (failed, or still being measured).
    """

    patient_code: str
    session_id: int
    visit_date: date
    timezone: str
    sessions: tuple[SessionFacts, ...]
    trials: tuple[ReportData, ...]
    software_version: str
    generated_at: datetime = field(default_factory=lambda: datetime.now(UTC))
    signature: SignatureLine | None = None
    signatures_on_record: tuple[SignatureLine, ...] = ()
    hidden: tuple[HiddenTrial, ...] = ()
    unmeasured: tuple[UnmeasuredTrial, ...] = ()

    def signed(self, line: SignatureLine) -> VisitData:
        """This visit as signed by ``line`` (the report's signature box filled in)."""
        return replace(self, signature=line, generated_at=line.signed_at)


@dataclass(frozen=True)
class TaskGroup:
    """One task's part of the visit summary (a row group of page 1)."""

    task: str
    title: str
    columns: tuple[SummaryColumn, ...]
    rows: tuple[SummaryRow, ...]
    asymmetry: tuple[tuple[str, tuple[Comparison, ...]], ...]
    """Per medication state with both hands: right − left, % of their mean."""
    medication: tuple[tuple[str, tuple[Comparison, ...]], ...]
    """Per hand with both states: on − off, % of off."""
    notes: tuple[str, ...]
    pairs: tuple[str, ...] = ()
    """Which trials the asymmetry and the medication response compare, where a side has
    several trials in one medication state (the newest of each is compared)."""


def _order(column: SummaryColumn) -> tuple[int, int, int]:
    med = (
        MEDICATION_ORDER.index(column.medication_state)
        if column.medication_state in MEDICATION_ORDER
        else 9
    )
    hand = HAND_ORDER.index(column.hand) if column.hand in HAND_ORDER else 9
    return med, hand, column.trial_id


def _newest(columns: Sequence[SummaryColumn], hand: str, med: str) -> SummaryColumn | None:
    found = [c for c in columns if c.hand == hand and c.medication_state == med]
    return max(found, key=lambda c: c.trial_id) if found else None


def trial_time(
    uploaded_at: datetime | None, session_at: datetime, timezone: str, *, with_day: bool = False
) -> str:
    """A trial's own time in the clinic's zone, as the visit report names it: ``"uploaded
    10:42 CET"`` (``with_day``: ``"uploaded 2026-03-01 10:42 CET"``), the day added when it
    is not the session's (recordings uploaded later); the session's time when the upload
    time is not known."""
    session_local = to_zone(session_at, timezone)
    if uploaded_at is None:
        return f"{session_local:%Y-%m-%d %H:%M %Z}" if with_day else f"{session_local:%H:%M %Z}"
    local = to_zone(uploaded_at, timezone)
    day = with_day or local.date() != session_local.date()
    return f"uploaded {local:%Y-%m-%d %H:%M %Z}" if day else f"uploaded {local:%H:%M %Z}"


def distinct_labels(
    columns: Sequence[SummaryColumn], trials: Sequence[ReportData]
) -> list[SummaryColumn]:
    """``columns`` with the trial number and its own time added to each label that two of
    them share (two trials of the same side and medication state): ``"Right hand,
    medication off — trial #13, uploaded 10:42 CET"`` (:func:`trial_time`)."""
    shared = Counter(c.base_label for c in columns)
    when = {t.trial_id: trial_time(t.uploaded_at, t.recorded_at, t.timezone) for t in trials}
    return [
        replace(c, label_detail=f"trial #{c.trial_id}, {when[c.trial_id]}")
        if shared[c.base_label] > 1 and c.trial_id in when
        else c
        for c in columns
    ]


def _pair_note(
    what: str, compared: Sequence[SummaryColumn], of: Sequence[SummaryColumn], by: str
) -> str:
    """Which two trials a comparison uses (each named by its ``by`` attribute: ``hand`` or
    ``medication_state``), and which of the same sides and states it leaves out."""
    ids = {c.trial_id for c in compared}
    used = " against ".join(f"trial #{c.trial_id} ({getattr(c, by)})" for c in compared)
    left_out = ", ".join(f"#{c.trial_id}" for c in of if c.trial_id not in ids)
    return f"{what}: {used}, the newest of each; not compared: trial {left_out}."


Compared = tuple[str, tuple[Comparison, ...]]


def _comparisons(
    cols: Sequence[SummaryColumn],
) -> tuple[list[Compared], list[Compared], list[str]]:
    """The asymmetry per medication state, the medication response per side, and which
    trials they use where a side and state has several."""
    limb = parse_task(cols[0].task).limb if cols else "hand"
    asymmetry: list[Compared] = []
    medication: list[Compared] = []
    pairs: list[str] = []
    for med in MEDICATION_ORDER:
        right, left = _newest(cols, "right", med), _newest(cols, "left", med)
        if right is not None and left is not None:
            asymmetry.append((med, tuple(asymmetry_rows(right, left))))
            of = [c for c in cols if c.medication_state == med]
            if len(of) > 2:
                pairs.append(
                    _pair_note(f"Right–left asymmetry, medication {med}", (right, left), of, "hand")
                )
    for hand in HAND_ORDER:
        on, off = _newest(cols, hand, "on"), _newest(cols, hand, "off")
        if on is not None and off is not None:
            medication.append((hand, tuple(medication_rows(on, off))))
            of = [c for c in cols if c.hand == hand and c.medication_state in ("on", "off")]
            if len(of) > 2:
                pairs.append(
                    _pair_note(
                        f"Medication response, {hand} {limb}", (on, off), of, "medication_state"
                    )
                )
    return asymmetry, medication, pairs


def task_groups(trials: Sequence[ReportData]) -> list[TaskGroup]:
    """The visit's trials grouped by task (finger tapping first), columns off→on, right→left;
    a label two trials share gets their trial numbers and times (:func:`distinct_labels`)."""
    columns = [summary_column(t) for t in trials]
    tasks = sorted(
        {c.task for c in columns},
        key=lambda t: (TASK_ORDER.index(t) if t in TASK_ORDER else len(TASK_ORDER), t),
    )
    groups = []
    for task in tasks:
        cols = distinct_labels(sorted((c for c in columns if c.task == task), key=_order), trials)
        asymmetry, medication, pairs = _comparisons(cols)
        notes = tuple(
            f"{c.label}: {note}" for c in cols if (note := short_taps_note(c)) is not None
        )
        groups.append(
            TaskGroup(
                task=task,
                title=TASK_TITLES.get(task, task.replace("_", " ").capitalize()),
                columns=tuple(cols),
                rows=tuple(summary_rows(cols)),
                asymmetry=tuple(asymmetry),
                medication=tuple(medication),
                notes=notes,
                pairs=tuple(pairs),
            )
        )
    return groups

"""What a trial's report shows: :class:`ReportData` and the lines derived from it.

Plain data, no database: ``app.services.results`` fills a :class:`ReportData`
from the database, the renderers (:mod:`app.reports.rendering`) and exports
read it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import UTC, datetime
from functools import cached_property
from typing import Any

from app.reports.result import SyncSummary, TrialResult, read_result
from app.reports.summary import SummaryColumn
from core.clock import LARGE_DRIFT_PPM, LARGE_DROPS, MIN_CONFIDENCE
from core.markers_csv import MarkerTable
from core.timing import describe_lost_frames

#: How each ``sync.time_source`` reads in the quality panel.
TIME_SOURCES = {
    "container": "container timestamps",
    "fps": "frame rate (frame number / fps)",
    "file": "timestamps file",
}


@dataclass(frozen=True)
class CalibrationInfo:
    """The calibration a trial was measured with, for the quality panel."""

    rig_name: str
    version: int | None
    valid_from: datetime | None
    rms_px: float | None
    verdict: str | None = None
    reasons: tuple[str, ...] = ()
    id: int | None = None


@dataclass(frozen=True)
class ReportData:
    """Everything the report of one trial shows.

    Attributes
    ----------
    trial_id : int
    patient_code : str
        The pseudonymous code; the report holds no other identifying data.
    hand : ``"left"`` or ``"right"``
    recorded_at : datetime (UTC)
        The session's time (a visit is the sessions of one day).
    uploaded_at : datetime (UTC) or None
        When this trial's recordings were uploaded (the trial row's ``created_at``): the
        capture page sends a take as it ends, so two takes of a visit are told apart by
        it. None: not known (the session's time is shown).
    medication_state, dbs_state : str
    clinician_rating : int or None
        The clinician's own MDS-UPDRS rating of this trial (3.4 for finger tapping), 0–4.
    rating_comment : str or None
    rated_by : str or None
        Who gave the rating (a user's name; None for an API client or no rating).
    rated_at : datetime (UTC) or None
    clinician : str or None
    notes : str or None
    task : str
        ``finger_tapping`` (the tasks of MDS-UPDRS 3.4–3.8, INTERFACES.md).
    time_since_levodopa_min : int or None
    more_affected_side, dominant_hand : str or None
    timezone : str
        The clinic's time zone (IANA name): dates are shown in it.
    beside : tuple of SummaryColumn
        The other hand (same medication state) and the same hand in the other
        medication state, from the same visit, where they exist: shown beside
        this trial's summary block.
    result : dict
        ``result.json`` as stored (docs/interfaces.md); :attr:`analysis` reads it, typed.
    markers : MarkerTable or None
        Trajectories from ``markers.csv`` (None when the file is gone, or not
        read because ``plots`` were stored and nothing else needs them).
    plots : dict or None
        The revision's stored plots (inline SVG by name, ``app.reports.figures``);
        None: drawn from ``markers`` when needed.
    calibration : CalibrationInfo or None
    generated_at : datetime (UTC)
    revision : int
        The result revision shown (1 = the first analysis).
    edits : tuple of dict
        Every correction or re-analysis up to that revision: ``revision``,
        ``kind``, ``by``, ``at``, ``reason``, ``change`` (empty: not edited).
    """

    trial_id: int
    patient_code: str
    hand: str
    recorded_at: datetime
    medication_state: str
    result: dict[str, Any]
    dbs_state: str = "unknown"
    clinician_rating: int | None = None
    rating_comment: str | None = None
    rated_by: str | None = None
    rated_at: datetime | None = None
    clinician: str | None = None
    notes: str | None = None
    task: str = "finger_tapping"
    time_since_levodopa_min: int | None = None
    more_affected_side: str | None = None
    dominant_hand: str | None = None
    timezone: str = "UTC"
    beside: tuple[SummaryColumn, ...] = ()
    session_id: int | None = None
    patient_id: int | None = None
    markers: MarkerTable | None = None
    calibration: CalibrationInfo | None = None
    generated_at: datetime = field(default_factory=lambda: datetime.now(UTC))
    revision: int = 1
    edits: tuple[dict[str, Any], ...] = ()
    plots: dict[str, str] | None = None
    uploaded_at: datetime | None = None

    @property
    def edited(self) -> bool:
        """The result shown was corrected or measured again after the first analysis."""
        return bool(self.edits)

    @property
    def edit_lines(self) -> list[str]:
        """One line per edit, for the report: revision, who, when, what and why."""
        return [edit_line(e) for e in self.edits]

    @cached_property
    def analysis(self) -> TrialResult:
        """:attr:`result` read as a :class:`~app.reports.result.TrialResult` (once)."""
        return read_result(self.result)


@dataclass(frozen=True)
class QualityRow:
    label: str
    value: str
    warn: bool = False


def quality_rows(data: ReportData) -> list[QualityRow]:
    """Lines of the quality panel: calibration, reprojection, tracking, sync."""
    rows = _calibration_rows(data.calibration)
    result = data.analysis
    q = result.quality
    if q.reprojection_px_median is not None:
        value = q.reprojection_px_median
        rows.append(
            QualityRow("Marker reprojection error (median)", f"{value:.2f} px", value > 1.0)
        )
    if q.reprojection_px_p95 is not None:
        value = q.reprojection_px_p95
        rows.append(
            QualityRow(
                "Marker reprojection error (95th percentile)", f"{value:.2f} px", value > 2.0
            )
        )
    # measured, interpolated and missing apart: an interpolated frame is no measurement
    if q.measured_fraction is not None:
        value = q.measured_fraction
        rows.append(QualityRow("Frames measured", f"{100 * value:.1f} %", value < 0.9))
    if q.tracked_fraction is not None:
        value = 1.0 - q.tracked_fraction
        rows.append(QualityRow("Frames missing", f"{100 * value:.1f} %", value > 0.05))
    if q.interpolated_fraction is not None:
        value = q.interpolated_fraction
        rows.append(QualityRow("Frames interpolated", f"{100 * value:.1f} %", value > 0.05))
    if q.set_aside_frames is not None:
        n = q.set_aside_frames
        rows.append(
            QualityRow(
                "Marker images set aside (partly hidden or merged; camera frames)",
                str(n),
                q.frames is not None and n > 0.05 * 2 * q.frames,
            )
        )
    if q.overlap_frames is not None:
        n = q.overlap_frames
        rows.append(
            QualityRow(
                "Frames with the two markers overlapping in a camera (not measured there)",
                str(n),
                q.frames is not None and n > 0.05 * q.frames,
            )
        )
    if q.merged_measured_frames:
        rows.append(
            QualityRow(
                "Touching marker images measured as two discs (camera frames)",
                str(q.merged_measured_frames),
                False,  # measured along the other camera's rays (0.04 px RMS, docs/markers.md)
            )
        )
    rows.extend(sync_rows(result.sync, result.fps))
    return rows


def sync_rows(sync: SyncSummary, fps: float | None) -> list[QualityRow]:
    """The quality panel's lines on the two cameras' timing (docs/sync.md): the offset in
    frames and ms, the clocks' drift, the frame rates, where the frame times came from, the
    frames lost and the rolling shutter compensated; a line is marked when core warns of it.
    Figures a result does not carry (older results) are left out."""
    rows: list[QualityRow] = []
    if sync.offset_frames is not None:
        text = f"{sync.offset_frames:+.2f} frames"
        offset_s = sync.offset_s
        if offset_s is None and fps:
            offset_s = sync.offset_frames / fps
        if offset_s is not None:
            text += f" ({1000 * offset_s:+.1f} ms)"
        guess = False
        if sync.method:
            text += f", {'estimated' if sync.method == 'auto' else 'given'}"
            if sync.method == "auto" and sync.confidence is not None:
                text += f" (confidence {sync.confidence:.2f})"
                guess = sync.confidence < MIN_CONFIDENCE
        rows.append(QualityRow("Camera synchronisation offset", text, guess))
    if sync.drift_ppm is not None:
        rows.append(
            QualityRow(
                "Camera clock drift (right against left)",
                f"{sync.drift_ppm:+.0f} ppm",
                abs(sync.drift_ppm) > LARGE_DRIFT_PPM,
            )
        )
    if fps:
        text = f"{fps:.1f} Hz"
        if sync.fps_right and abs(sync.fps_right - fps) > 1e-3 * fps:
            text = f"left {fps:.2f} Hz, right {sync.fps_right:.2f} Hz"
        rows.append(QualityRow("Frame rate", text))
    if len(sync.time_source) == 2:
        left, right = (TIME_SOURCES.get(s, s) for s in sync.time_source)
        text = left if left == right else f"left: {left}; right: {right}"
        rows.append(QualityRow("Frame times from", text))
    if sync.offset_s is not None:  # results of the time model report their lost frames
        lost = [  # grouped by gap, a long list summed up (core.timing)
            f"{name} {len(frames)}"
            + (f" ({describe_lost_frames(frames, fps=rate)})" if frames else "")
            for name, frames, rate in (
                ("left", sync.dropped_frames_left, fps),
                ("right", sync.dropped_frames_right, sync.fps_right or fps),
            )
        ]
        n = len(sync.dropped_frames_left) + len(sync.dropped_frames_right)
        rows.append(QualityRow("Lost frames found", ", ".join(lost), n > LARGE_DROPS))
    if len(sync.readout_ms) == 2:
        left_ms, right_ms = sync.readout_ms
        rows.append(
            QualityRow(
                "Rolling-shutter readout compensated",
                f"left {left_ms:g} ms, right {right_ms:g} ms",
            )
        )
    return rows


def _calibration_rows(cal: CalibrationInfo | None) -> list[QualityRow]:
    if cal is None:
        return []
    name = cal.rig_name + (f", calibration v{cal.version}" if cal.version else "")
    if cal.valid_from is not None and cal.valid_from.year > 1980:
        name += f" (valid from {cal.valid_from:%Y-%m-%d})"
    rms = "not reported" if cal.rms_px is None else f"{cal.rms_px:.2f} px"
    if cal.verdict:
        rms += f" — {cal.verdict}"
    return [
        QualityRow("Calibration used", name),
        QualityRow("Calibration RMS error", rms, warn=cal.verdict == "poor"),
    ]


def summary_column(data: ReportData) -> SummaryColumn:
    """The summary block's column of one trial."""
    return SummaryColumn(
        trial_id=data.trial_id,
        task=data.task,
        hand=data.hand,
        medication_state=data.medication_state,
        result=data.analysis,
        clinician_rating=data.clinician_rating,
        rating_comment=data.rating_comment,
    )


def edit_line(edit: dict[str, Any]) -> str:
    """``Revision 2 (correction) by Dr X, 2026-01-02 10:00 UTC: exclude taps 3; reason: ...``.

    Tap numbers are shown 1-based, as on every page and report.
    """
    change = edit.get("change") or {}
    parts = []
    for key, value in change.items():
        if key in ("exclude_taps", "dismiss_pauses"):
            taps = ", ".join(str(int(i) + 1) for i in value) or "none"
            parts.append(
                ("excluded taps " if key == "exclude_taps" else "dismissed pauses of taps ") + taps
            )
        elif key == "window_s":
            parts.append(
                "whole recording" if value is None else f"window {value[0]:g}–{value[1]:g} s"
            )
        elif key == "swap_labels":
            parts.append("thumb and index labels swapped" if value else "labels as tracked")
        elif key == "swap_cameras":
            parts.append(
                "measured again with the cameras swapped" if value else "cameras as uploaded"
            )
        elif key == "offset_frames":
            parts.append(f"measured again with a camera offset of {value:g} frames")
    at = str(edit.get("at") or "")[:16].replace("T", " ")
    what = "; ".join(parts) or "changed"
    return (
        f"Revision {edit.get('revision')} ({edit.get('kind', 'correction')}) by {edit.get('by') or '–'},"
        f" {at} UTC: {what}. Reason: {edit.get('reason') or '–'}"
    )

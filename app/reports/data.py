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

from app.reports.result import TrialResult, read_result
from core.markers_csv import MarkerTable


@dataclass(frozen=True)
class CalibrationInfo:
    """The calibration a trial was measured with, for the quality panel."""

    rig_name: str
    version: int | None
    valid_from: datetime | None
    rms_px: float | None
    verdict: str | None = None
    reasons: tuple[str, ...] = ()


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
    medication_state, dbs_state : str
    updrs_34_rating : int or None
        The clinician's own MDS-UPDRS 3.4 rating, if given.
    clinician : str or None
    notes : str or None
    result : dict
        ``result.json`` as stored (docs/interfaces.md); :attr:`analysis` reads it, typed.
    markers : MarkerTable or None
        Trajectories from ``markers.csv`` (None when the file is gone).
    calibration : CalibrationInfo or None
    generated_at : datetime (UTC)
    """

    trial_id: int
    patient_code: str
    hand: str
    recorded_at: datetime
    medication_state: str
    result: dict[str, Any]
    dbs_state: str = "unknown"
    updrs_34_rating: int | None = None
    clinician: str | None = None
    notes: str | None = None
    session_id: int | None = None
    patient_id: int | None = None
    markers: MarkerTable | None = None
    calibration: CalibrationInfo | None = None
    generated_at: datetime = field(default_factory=lambda: datetime.now(UTC))

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
    if q.tracked_fraction is not None:
        value = q.tracked_fraction
        rows.append(QualityRow("Frames measured", f"{100 * value:.1f} %", value < 0.9))
    if q.interpolated_fraction is not None:
        value = q.interpolated_fraction
        rows.append(QualityRow("Frames interpolated", f"{100 * value:.1f} %", value > 0.05))
    offset = result.sync.offset_frames
    if offset is not None:
        text = f"{offset:+.2f} frames"
        if result.fps:
            text += f" ({1000 * offset / result.fps:+.1f} ms)"
        if result.sync.method:
            text += f", {'estimated' if result.sync.method == 'auto' else 'given'}"
        rows.append(QualityRow("Camera synchronisation offset", text))
    if result.fps:
        rows.append(QualityRow("Frame rate", f"{result.fps:.1f} Hz"))
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

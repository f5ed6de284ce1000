"""The trial result page (plots, metrics, quality, comparison) and its downloads.

Downloads: ``pdf`` and ``html`` (the report), ``csv`` (markers.csv),
``c3d`` and ``trc`` (trajectories for motion-capture tools), ``json``
(result.json) and ``fhir`` (a FHIR R4 Bundle). Each is one ``export`` audit
event; the page itself one ``read`` event.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse, Response

from app.audit import audit
from app.auth import SessionDep
from app.errors import AppError
from app.models import Trial
from app.reports import (
    ReportData,
    build_report_data,
    comparison_plots,
    format_metric,
    metric_rows,
    report_context,
)
from app.services.common import visible_trial
from app.web.common import (
    PageUser,
    error_page,
    missing_page,
    render,
    settings_of,
    status_of,
)
from app.web.patients import trials_of_patient

router = APIRouter()

DOWNLOADS: dict[str, tuple[str, str, str]] = {
    # kind: (label, media type, file suffix)
    "pdf": ("PDF report", "application/pdf", ".pdf"),
    "html": ("HTML report", "text/html; charset=utf-8", ".html"),
    "csv": ("Markers CSV", "text/csv; charset=utf-8", "-markers.csv"),
    "c3d": ("C3D", "application/octet-stream", ".c3d"),
    "trc": ("TRC", "text/plain; charset=utf-8", ".trc"),
    "json": ("Result JSON", "application/json", "-result.json"),
    "fhir": ("FHIR R4 Bundle", "application/fhir+json", "-fhir.json"),
}


def trial_label(trial: Trial) -> str:
    s = trial.session
    return f"{s.recorded_at:%Y-%m-%d}, {trial.hand} hand, medication {s.medication_state}"


def _comparison(db: Any, data: ReportData, other: ReportData) -> dict[str, Any]:
    rows_a = {r.key: r for r in metric_rows(data.result)}
    rows_b = {r.key: r for r in metric_rows(other.result)}
    metrics_a = data.result.get("metrics") or {}
    metrics_b = other.result.get("metrics") or {}
    rows = []
    for key in [k for k in rows_a if k in rows_b]:
        a, b = metrics_a.get(key), metrics_b.get(key)
        diff = "–"
        if isinstance(a, int | float) and isinstance(b, int | float):
            diff = format_metric(key, float(b) - float(a))
            if not diff.startswith(("-", "+", "–")):
                diff = "+" + diff
        rows.append(
            {
                "label": rows_a[key].label,
                "a": rows_a[key].value,
                "b": rows_b[key].value,
                "diff": diff,
                "unit": rows_a[key].unit,
            }
        )
    plots_a, plots_b = comparison_plots(data, other)
    return {"rows": rows, "plots_a": plots_a, "plots_b": plots_b}


def _suggested(trial: Trial, candidates: list[Trial]) -> list[tuple[Trial, str]]:
    """Candidates for comparison, the most useful first (other hand, same session; other medication)."""

    def rank(t: Trial) -> tuple[int, float]:
        same_session = t.session_id == trial.session_id
        other_hand = t.hand != trial.hand
        other_med = t.session.medication_state != trial.session.medication_state
        if same_session and other_hand:
            score = 0
        elif t.hand == trial.hand and other_med:
            score = 1
        elif t.hand == trial.hand:
            score = 2
        else:
            score = 3
        return score, -t.session.recorded_at.timestamp()

    hints = {
        0: "other hand, same session",
        1: "same hand, other medication state",
        2: "same hand, other session",
        3: "",
    }
    out = []
    for t in sorted((c for c in candidates if c.id != trial.id), key=rank):
        hint = hints[rank(t)[0]]
        out.append((t, trial_label(t) + (f" ({hint})" if hint else "")))
    return out


@router.get("/trials/{trial_id}", response_class=HTMLResponse)
def trial_page(
    request: Request, db: SessionDep, user: PageUser, trial_id: int, compare: int | None = None
) -> Response:
    trial = visible_trial(db, trial_id)
    if trial is None:
        return missing_page(request, db, user, "read", "trial", trial_id)
    patient = trial.session.patient
    if trial.result is None:
        from app.web.recordings import _latest_job

        job = _latest_job(db, trial.id)
        audit(db, user, "read", "trial", trial.id, patient.id)
        db.commit()
        return render(
            request,
            "trial_pending.html",
            user,
            active="patients",
            title=f"Trial {trial.id} — {patient.code}",
            trial=trial,
            patient=patient,
            job=job,
        )
    settings = settings_of(request)
    data = build_report_data(db, trial.id, settings=settings)
    context = report_context(data)
    candidates = _suggested(trial, trials_of_patient(db, patient))
    comparison = None
    compare_error = None
    if compare is not None:
        other = visible_trial(db, compare)
        if other is None or other.result is None or other.session.patient_id != patient.id:
            compare_error = "That trial cannot be compared: it does not exist, has no result, or belongs to another patient."
        else:
            other_data = build_report_data(db, other.id, settings=settings)
            comparison = _comparison(db, data, other_data)
            comparison["label"] = trial_label(other)
            comparison["trial"] = other
    audit(db, user, "read", "result", trial.id, patient.id)
    db.commit()
    return render(
        request,
        "trial.html",
        user,
        active="patients",
        title=f"{patient.code}: {trial_label(trial)}",
        trial=trial,
        patient=patient,
        label=trial_label(trial),
        candidates=candidates,
        comparison=comparison,
        compare_id=compare,
        compare_error=compare_error,
        downloads=DOWNLOADS,
        **context,
    )


def _attachment(name: str) -> dict[str, str]:
    return {"Content-Disposition": f'attachment; filename="{name}"'}


@router.get("/trials/{trial_id}/download/{kind}")
def trial_download(
    request: Request, db: SessionDep, user: PageUser, trial_id: int, kind: str
) -> Response:
    from app.services import results as svc

    if kind not in DOWNLOADS:
        return error_page(request, user, status_code=404, message=f"There is no {kind!r} download.")
    trial = visible_trial(db, trial_id)
    if trial is None:
        return missing_page(request, db, user, "export", "trial", trial_id)
    _, media_type, suffix = DOWNLOADS[kind]
    filename = f"{trial.session.patient.code}-trial{trial.id}-{trial.hand}{suffix}"
    settings = settings_of(request)
    try:
        if kind == "pdf":
            body: bytes | str = svc.report_pdf(db, user, trial.id, settings)
        elif kind == "html":
            body = svc.report_html(db, user, trial.id, settings)
        elif kind == "fhir":
            body = json.dumps(svc.fhir_bundle(db, user, trial.id, settings), indent=1)
        elif kind == "json":
            body = json.dumps(svc.get_result(db, user, trial.id), indent=1)
        elif kind == "csv":
            from app.storage import Storage

            path = svc.markers_csv_path(db, user, trial.id, Storage.from_settings(settings))
            body = path.read_bytes()
        else:
            body = _trajectory_file(db, user, trial, kind, settings)
    except AppError as exc:
        db.rollback()
        return error_page(request, user, status_code=status_of(exc), message=str(exc))
    return Response(content=body, media_type=media_type, headers=_attachment(filename))


def _trajectory_file(db: Any, user: Any, trial: Trial, kind: str, settings: Any) -> bytes:
    from app.errors import ConflictError, NotFoundError
    from app.exports import write_c3d, write_trc

    if trial.result is None:
        raise ConflictError(f"The trial {trial.id} has no result yet; wait for its analysis.")
    data = build_report_data(db, trial.id, settings=settings)
    if data.markers is None:
        raise NotFoundError(f"The markers file of trial {trial.id} is missing from storage.")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"trial.{kind}"
        (write_c3d if kind == "c3d" else write_trc)(path, data.markers)
        body = path.read_bytes()
    audit(db, user, "export", f"{kind}_file", trial.id, trial.session.patient_id)
    db.commit()
    return body

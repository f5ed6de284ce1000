"""Results of a trial and their exports: result.json, markers.csv, report (HTML/PDF), FHIR.

Each export is generated first and audited (``export``) only when it could be
produced, in the same commit. The report and FHIR renderers live in
``app.reports`` / ``app.exports`` and are imported lazily: while they are
missing the routes answer 503 instead of inventing content.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any, TypeVar

from sqlalchemy.orm import Session

from app.actors import Actor
from app.audit import audit
from app.errors import ConflictError, NotFoundError, ServiceUnavailableError
from app.models import Job, Result, Trial
from app.services.common import load_trial
from app.storage import Storage

T = TypeVar("T")


def _result_of(db: Session, actor: Actor, trial_id: int, action: str) -> tuple[Trial, Result]:
    trial = load_trial(db, actor, trial_id, action)
    result = trial.result
    if result is None:
        if trial.status == "failed":
            job = db.query(Job).filter(Job.trial_id == trial.id).order_by(Job.id.desc()).first()
            reason = f": {job.error}" if job is not None and job.error else "."
            raise ConflictError(f"The analysis of trial {trial.id} failed{reason}")
        raise ConflictError(
            f"The trial {trial.id} has no result yet (status {trial.status}); poll its job and"
            " retry when it has succeeded."
        )
    return trial, result


def _exported(db: Session, actor: Actor, trial: Trial, resource_type: str, value: T) -> T:
    """Audit the export of ``trial``'s ``resource_type`` (committed); returns ``value``."""
    audit(db, actor, "export", resource_type, trial.id, trial.session.patient_id)
    db.commit()
    return value


def _renderer(module: str, name: str) -> Any:
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as exc:
        raise ServiceUnavailableError(
            f"{module}.{name} is not available yet in this installation; the export cannot be made."
        ) from exc


def get_result(db: Session, actor: Actor, trial_id: int) -> dict[str, Any]:
    """The trial's ``result.json`` document (409 until the analysis has succeeded)."""
    trial, result = _result_of(db, actor, trial_id, "read")
    document = dict(result.document)
    audit(db, actor, "read", "result", trial.id, trial.session.patient_id)
    db.commit()
    return document


def markers_csv_path(db: Session, actor: Actor, trial_id: int, storage: Storage) -> Path:
    """The stored ``markers.csv`` of the trial."""
    trial, result = _result_of(db, actor, trial_id, "export")
    path = storage.absolute(result.markers_path) if result.markers_path else None
    if path is None or not path.is_file():
        raise NotFoundError(f"The markers file of trial {trial.id} is missing from storage.")
    return _exported(db, actor, trial, "markers_csv", path)


def _report_data(db: Session, actor: Actor, trial_id: int, settings: Any) -> tuple[Trial, Any]:
    trial, _ = _result_of(db, actor, trial_id, "export")
    build = _renderer("app.reports", "build_report_data")
    return trial, build(db, trial.id, settings=settings)


def report_html(db: Session, actor: Actor, trial_id: int, settings: Any) -> str:
    render = _renderer("app.reports", "render_report_html")
    trial, data = _report_data(db, actor, trial_id, settings)
    return _exported(db, actor, trial, "report_html", str(render(data)))


def report_pdf(db: Session, actor: Actor, trial_id: int, settings: Any) -> bytes:
    render = _renderer("app.reports", "render_report_pdf")
    trial, data = _report_data(db, actor, trial_id, settings)
    return _exported(db, actor, trial, "report_pdf", bytes(render(data)))


def fhir_bundle(db: Session, actor: Actor, trial_id: int, settings: Any) -> dict[str, Any]:
    """A FHIR R4 Bundle (DiagnosticReport + Observations, the PDF attached)."""
    make_bundle = _renderer("app.exports", "fhir_bundle")
    render_pdf = _renderer("app.reports", "render_report_pdf")
    trial, data = _report_data(db, actor, trial_id, settings)
    bundle = dict(make_bundle(data, bytes(render_pdf(data))))
    return _exported(db, actor, trial, "fhir_bundle", bundle)

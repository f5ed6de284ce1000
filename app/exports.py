"""Exports of one trial for other systems: a FHIR R4 Bundle.

- ``markers.csv`` itself is :mod:`core.markers_csv`'s (header, writer, reader).
- C3D and TRC, the marker trajectories for motion-capture tools, are
  :mod:`app.trajectories`'.
- :func:`fhir_bundle` builds a FHIR R4 Bundle (a DiagnosticReport, one
  Observation per metric with UCUM units, the clinician's rating, the Patient by
  its pseudonymous code and the PDF report as ``presentedForm``), validated with
  the R4B models of ``fhir.resources`` (R4B 4.3 is wire-compatible with R4 4.0.1
  for these resources). Every Observation carries the session's medication and
  DBS states (:mod:`app.fhir_state`); identifiers and versions, by which a
  receiver matches what it holds, are :mod:`app.fhir_versions`'.
"""

from __future__ import annotations

import base64
import math
import uuid
from datetime import UTC, datetime
from typing import Any

from fhir.resources.R4B.bundle import Bundle

from app.fhir_state import UCUM_SYSTEM, state_components
from app.fhir_versions import (
    bundle_identifier,
    finish_versions,
    measured_identity,
    rating_identity,
)
from app.reports.catalogue import ALIAS_KEYS, display_value, metric_spec
from app.reports.data import ReportData
from app.reports.rendering import report_key
from core.tasks import Task, parse_task, task_key

# Identifier systems of bradyscope's own codes (URNs: valid URIs that need no web server).
PATIENT_CODE_SYSTEM = "urn:bradyscope:patient-code"
METRIC_CODE_SYSTEM = "urn:bradyscope:finger-tapping-metric"
EXAM_CATEGORY = {
    "system": "http://terminology.hl7.org/CodeSystem/observation-category",
    "code": "exam",
    "display": "Exam",
}
"""The FHIR Observation category of every measurement and of the clinician's rating."""
REPORT_CODE_SYSTEM = "urn:bradyscope:report"


def metric_code_system(task: Task) -> str:
    """The code system of a task's metrics: ``urn:bradyscope:finger-tapping-metric``,
    ``urn:bradyscope:hand-movements-metric``..."""
    return f"urn:bradyscope:{task.value.replace('_', '-')}-metric"


def _body_site(task: Task, side: str) -> str:
    if task is Task.FINGER_TAPPING:
        return f"{side} hand, thumb and index finger"
    return f"{side} {task.limb}"


def _method(task: Task) -> str:
    return f"Stereo-video {task.label.lower()} (MDS-UPDRS {task.updrs_item} task), bradyscope"


LOINC_SYSTEM = "http://loinc.org"


# --------------------------------------------------------------------------- FHIR


FIRST_10_SUFFIX = "_first_10"
"""The code of a metric over the first 10 taps or cycles: its key with this suffix."""


def _observation(
    key: str,
    value: float,
    *,
    patient_ref: str,
    effective: str,
    hand: str,
    task: Task = Task.FINGER_TAPPING,
    trial_id: int = 0,
    revision: int = 1,
    first_10: bool = False,
    components: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    spec = metric_spec(key, task.value)
    label, ucum, unit = spec.label, spec.ucum, spec.unit
    if first_10:  # the value the pages, the trends and the summary show (the item's 10 taps)
        key, label = f"{key}{FIRST_10_SUFFIX}", f"{label}, first 10 {task.cycle_word}s"
    obs: dict[str, Any] = {
        "resourceType": "Observation",
        **measured_identity(trial_id, key, revision),
        "category": [{"coding": [dict(EXAM_CATEGORY)]}],
        "code": {
            "coding": [{"system": metric_code_system(task), "code": key, "display": label}],
            "text": f"{label} ({hand} {task.limb})",
        },
        "subject": {"reference": patient_ref},
        "effectiveDateTime": effective,
        "bodySite": {"text": _body_site(task, hand)},
        "method": {"text": _method(task)},
    }
    if math.isfinite(value):
        obs["valueQuantity"] = {
            "value": float(value),  # as result.json has it
            "unit": unit or ucum,
            "system": UCUM_SYSTEM,
            "code": ucum,
        }
    else:
        obs["dataAbsentReason"] = {
            "coding": [
                {
                    "system": "http://terminology.hl7.org/CodeSystem/data-absent-reason",
                    "code": "not-applicable",
                    "display": "Not Applicable",
                }
            ]
        }
    if spec.definition:
        obs["note"] = [{"text": spec.definition}]
    if components:
        obs["component"] = components
    return obs


def _iso(value: datetime) -> str:
    if value.tzinfo is None:
        value = value.replace(tzinfo=UTC)
    return value.isoformat(timespec="seconds")


def fhir_bundle(
    data: ReportData, pdf_bytes: bytes | None, *, report_content: str | None = None
) -> dict[str, Any]:
    """A FHIR R4 ``collection`` Bundle for one trial.

    Contents: the Patient (only its pseudonymous code as identifier), one
    Observation per numeric metric (UCUM units, code system
    ``urn:bradyscope:finger-tapping-metric``), and a DiagnosticReport that
    references them and carries the PDF report as ``presentedForm``. The
    result is validated with ``fhir.resources.R4B`` before it is returned.
    ``report_content``: what the PDF shows (``app.reports.rendering.report_key(data)``,
    made here when not given), which the report's version follows.

    Returns
    -------
    dict
        JSON-ready Bundle.
    """
    patient_url = _urn()
    effective = _iso(data.recorded_at)
    issued = _iso(data.generated_at)
    entries: list[dict[str, Any]] = [
        {
            "fullUrl": patient_url,
            "resource": {
                "resourceType": "Patient",
                "identifier": [{"system": PATIENT_CODE_SYSTEM, "value": data.patient_code}],
            },
        }
    ]
    metric_entries = _observation_entries(data, patient_url, effective)
    group = {
        "fullUrl": _urn(),
        "resource": _task_group(
            data, patient_url, effective, [e["fullUrl"] for e in metric_entries]
        ),
    }
    entries += [*metric_entries, group]
    measured_urls = [str(e["fullUrl"]) for e in entries[1:]]
    if (rating := _rating_observation(data, patient_url)) is not None:
        entries.append({"fullUrl": _urn(), "resource": rating})
    report = _diagnostic_report(
        data,
        patient_url,
        effective=effective,
        issued=issued,
        observation_urls=measured_urls,
        pdf_bytes=pdf_bytes,
    )
    entries.append({"fullUrl": _urn(), "resource": report})
    resources = [e["resource"] for e in entries]
    if pdf_bytes is not None and report_content is None:
        report_content = report_key(data)  # what the PDF shows (the caller may have it)
    finish_versions(resources, report_content=report_content if pdf_bytes is not None else None)
    doc: dict[str, Any] = {
        "resourceType": "Bundle",
        "type": "collection",  # no server-side processing asked for; a set of resources
        "timestamp": issued,
        "identifier": bundle_identifier(data.trial_id, data.revision, resources),
        "entry": entries,
    }
    Bundle.model_validate(doc)  # raises pydantic.ValidationError if the bundle is malformed
    return doc


def _task_group(
    data: ReportData, patient_ref: str, effective: str, member_urls: list[str]
) -> dict[str, Any]:
    """The task's Observation group: a panel whose members are the trial's metric
    Observations (one group per task; a visit's bundles keep the tasks apart)."""
    task = parse_task(data.task)
    return {
        "resourceType": "Observation",
        **measured_identity(data.trial_id, "panel", data.revision),
        "category": [{"coding": [dict(EXAM_CATEGORY)]}],
        "code": {
            "coding": [
                {
                    "system": REPORT_CODE_SYSTEM,
                    "code": task.value.replace("_", "-"),
                    "display": f"Instrumented {task.heading[0].lower()}{task.heading[1:]}",
                }
            ],
            "text": f"{task.heading}, {data.hand} {task.limb}: measured",
        },
        "subject": {"reference": patient_ref},
        "effectiveDateTime": effective,
        "bodySite": {"text": _body_site(task, data.hand)},
        "method": {"text": _method(task)},
        "hasMember": [{"reference": u} for u in member_urls],
        "component": _state(data),
    }


RATING_CODE_SYSTEM = "urn:bradyscope:clinician-rating"


def _rating_observation(data: ReportData, patient_ref: str) -> dict[str, Any] | None:
    """The clinician's own MDS-UPDRS rating of the trial: an Observation of its own.

    Distinct from the measured Observations: its own code system
    (``urn:bradyscope:clinician-rating``), category ``exam`` with the text
    "Clinician's rating", the clinician as ``performer``, an integer value
    0–4, and the comment as ``note``. The DiagnosticReport (the instrument's
    measurement) does not list it among its results.

    A rating cleared after it was given (no rating, but a time it was changed) comes
    back with the same identifier, no value and status ``entered-in-error`` (R4:
    "withdrawn following previous final release"), so that a receiver that holds it
    withdraws it; None when the trial was never rated.
    """
    withdrawn = data.clinician_rating is None
    if withdrawn and data.rated_at is None:
        return None
    task = parse_task(data.task)
    item = task.updrs_item
    obs: dict[str, Any] = {
        "resourceType": "Observation",
        **rating_identity(data.trial_id, item, data.rated_at),
        "status": "entered-in-error" if withdrawn else "final",
        "category": [{"coding": [dict(EXAM_CATEGORY)], "text": "Clinician's rating"}],
        "code": {
            "coding": [
                {
                    "system": RATING_CODE_SYSTEM,
                    "code": f"mds-updrs-{item}",
                    "display": f"MDS-UPDRS {item} {task.label.lower()}, clinician's rating (0-4)",
                }
            ],
            "text": f"Clinician's MDS-UPDRS {item} rating ({data.hand} {task.limb})",
        },
        "subject": {"reference": patient_ref},
        "effectiveDateTime": _iso(data.recorded_at),
        "bodySite": {"text": f"{data.hand} {task.limb}"},
        "method": {"text": "Rated by the clinician on the MDS-UPDRS wording; not measured"},
        "component": _state(data),
    }
    if data.rated_at is not None:
        obs["issued"] = _iso(data.rated_at)
    if withdrawn:
        obs["note"] = [{"text": "The clinician withdrew this rating (cleared it in bradyscope)."}]
        return obs
    obs["valueInteger"] = int(data.clinician_rating or 0)
    if data.rated_by:
        obs["performer"] = [{"display": data.rated_by}]
    if data.rating_comment:
        obs["note"] = [{"text": data.rating_comment}]
    return obs


def _state(data: ReportData) -> list[dict[str, Any]]:
    """The medication and DBS states of the session (and the time since levodopa), as a
    ``component`` of every Observation (:mod:`app.fhir_state`)."""
    return state_components(data.medication_state, data.dbs_state, data.time_since_levodopa_min)


def _urn() -> str:
    return f"urn:uuid:{uuid.uuid4()}"


def _observation_entries(
    data: ReportData, patient_url: str, effective: str
) -> list[dict[str, Any]]:
    """One Observation entry per numeric metric of the result (an undefined one: data absent),
    over all taps (``metrics``) and over the first 10 (``metrics_first_10``, codes with
    :data:`FIRST_10_SUFFIX`: the values the pages and trends show); the common keys that
    repeat one of the task's own metrics are given once, by its name."""
    task = parse_task(data.task)
    aliases = ALIAS_KEYS | ({"cycle_count"} if task is Task.FINGER_TAPPING else set())
    entries = []
    both = [(k, v, False) for k, v in data.analysis.metrics.items()] + [
        (k, v, True) for k, v in data.analysis.metrics_first_10.items()
    ]
    for key, value, first_10 in both:
        if key in aliases:
            continue
        # Tap numbers are counted from 1, as the definition in the note says.
        number = math.nan if value is None else display_value(key, float(value))
        entries.append(
            {
                "fullUrl": _urn(),
                "resource": _observation(
                    key,
                    number,
                    patient_ref=patient_url,
                    effective=effective,
                    hand=data.hand,
                    task=task,
                    trial_id=data.trial_id,
                    revision=data.revision,
                    first_10=first_10,
                    components=_state(data),
                ),
            }
        )
    return entries


def _diagnostic_report(
    data: ReportData,
    patient_url: str,
    *,
    effective: str,
    issued: str,
    observation_urls: list[str],
    pdf_bytes: bytes | None,
) -> dict[str, Any]:
    task = parse_task(data.task)
    report: dict[str, Any] = {
        "resourceType": "DiagnosticReport",
        **measured_identity(data.trial_id, "report", data.revision),
        "category": [
            {
                "coding": [
                    {
                        "system": "http://terminology.hl7.org/CodeSystem/v2-0074",
                        # v2-0074 has no section for an instrumented neurological
                        # examination; "Nursing Service Measures" (NRS) it is not
                        "code": "OTH",
                        "display": "Other",
                    }
                ],
                "text": "Movement analysis",
            }
        ],
        "code": {
            "coding": [
                {
                    "system": REPORT_CODE_SYSTEM,
                    "code": task.value.replace("_", "-"),
                    "display": f"Instrumented {task.heading[0].lower()}{task.heading[1:]}",
                }
            ],
            "text": f"Instrumented {task.label.lower()}, {data.hand} {task.limb}",
        },
        "subject": {"reference": patient_url},
        "effectiveDateTime": effective,
        "issued": issued,
        "result": [{"reference": u} for u in observation_urls],
        "conclusion": _conclusion(data),
    }
    if pdf_bytes is not None:
        report["presentedForm"] = [
            {
                "contentType": "application/pdf",
                "language": "en",
                "data": base64.b64encode(pdf_bytes).decode("ascii"),
                "title": f"bradyscope {task.label.lower()} report {data.patient_code}",
                "creation": issued,
            }
        ]
    return report


def _conclusion(data: ReportData) -> str:
    """One sentence per count of taps: over all of them, and over the first 10 (what the
    pages and the trends show): ``Right hand, medication off. All 12 taps: 2.18 Hz, mean
    amplitude 26.7 mm, decrement -1.12 mm/tap. First 10 taps: ...``."""
    task = parse_task(data.task)
    unit, word = task.amplitude_unit, task.cycle_word
    m = data.analysis

    def summary(values: dict[str, Any], lead: str) -> str | None:
        taps = values.get(task_key("tap_count", task))
        if taps is None:
            return None
        parts = []
        if (frequency := values.get("frequency_hz")) is not None:
            parts.append(f"{frequency:.2f} Hz")
        if (amplitude := values.get(task_key("amplitude_mm_mean", task))) is not None:
            parts.append(f"mean amplitude {amplitude:.1f} {unit}")
        decrement = values.get(task_key("amplitude_decrement_mm_per_tap", task))
        if decrement is not None:
            parts.append(f"decrement {decrement:+.2f} {unit}/{word}")
        head = lead.format(n=int(taps), word=word if int(taps) == 1 else f"{word}s")
        return f"{head}: {', '.join(parts)}." if parts else f"{head}."

    sentences = [f"{data.hand.capitalize()} {task.limb}, medication {data.medication_state}."]
    for values, lead in ((m.metrics, "All {n} {word}"), (m.metrics_first_10, "First {n} {word}")):
        if (text := summary(dict(values), lead)) is not None:
            sentences.append(text)
    return " ".join(sentences)

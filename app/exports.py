"""Exports of one trial for other systems: C3D, TRC and a FHIR R4 Bundle.

- ``markers.csv`` itself is :mod:`core.markers_csv`'s (header, writer, reader).
- C3D (through ezc3d) and TRC carry the same marker trajectories for motion
  capture tools (Vicon Nexus, Mokka, OpenSim...). Coordinates are in mm in the
  rig's world frame (the left camera's frame: x right, y down, z away from the
  camera); missing samples are marked invalid (C3D residual -1, empty TRC cells),
  interpolated ones residual 0 in C3D (its "not a measured point").
- :func:`fhir_bundle` builds a FHIR R4 Bundle (a DiagnosticReport, one
  Observation per metric with UCUM units, the Patient by its pseudonymous
  code and the PDF report as ``presentedForm``), validated with the R4B models
  of ``fhir.resources`` (R4B 4.3 is wire-compatible with R4 4.0.1 for these
  resources).
"""

from __future__ import annotations

import base64
import math
import struct
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import ezc3d
import numpy as np
from fhir.resources.R4B.bundle import Bundle
from numpy.typing import NDArray

from app.reports.catalogue import ALIAS_KEYS, display_value, metric_spec
from app.reports.data import ReportData
from core.markers_csv import MarkerTable
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


UCUM_SYSTEM = "http://unitsofmeasure.org"
LOINC_SYSTEM = "http://loinc.org"


def _num(value: float, digits: int) -> str:
    return "" if not math.isfinite(value) else f"{value:.{digits}f}"


def write_c3d(path: str | Path, table: MarkerTable, *, focal_px: float | None = None) -> Path:
    """Write the trajectories as a C3D file (ezc3d), in mm, frame rate ``table.fps``.

    Each sample's fourth word says what it is, as the C3D format defines it (its
    camera mask in the high byte, its residual in ``POINT:SCALE`` steps in the low
    byte):

    - measured (stereo): the cameras 1 and 2 (left, right) and a positive residual,
      the reprojection error brought to mm at the marker's depth
      (``reprojection_px * z / focal_px``, ``focal_px`` the left camera's focal length;
      one step where either is unknown), 1 to 255 steps;
    - interpolated: 0, C3D's "filtered, interpolated or otherwise modified, not a
      measured point";
    - missing: -1 (C3D's "invalid") and zero coordinates.

    ``POINT:SCALE`` is -(largest coordinate / 32000) as the format asks (negative:
    float storage). The first frame number in the header is the first left-video
    frame + 1.
    """
    path = Path(path)
    c3d = ezc3d.c3d()
    t, m = table.frames.size, len(table.labels)
    pts = np.zeros((4, m, t))
    pts[:3] = np.transpose(table.positions_mm, (2, 1, 0))
    pts[3] = 1.0
    invalid = ~np.isfinite(table.positions_mm).all(axis=2)  # (T, M)
    pts[:3, invalid.T] = 0.0
    step = max(float(np.abs(pts[:3]).max()) if pts.size else 0.0, 1.0) / 32000.0  # mm
    measured = (table.status == "measured") & ~invalid
    steps = np.ones((t, m))
    if focal_px is not None and focal_px > 0:
        with np.errstate(invalid="ignore"):
            res_mm = np.abs(table.reprojection_px) * table.positions_mm[:, :, 2] / focal_px
        steps = np.where(np.isfinite(res_mm), np.rint(res_mm / step), 1.0)
    words = np.where(measured, (3 << 8) + np.clip(steps, 1, 255), 0.0)
    words[invalid] = -1.0
    c3d["parameters"]["POINT"]["RATE"]["value"] = [float(table.fps)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = list(table.labels)
    c3d["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c3d["parameters"]["POINT"]["SCALE"]["value"] = [-step]
    c3d["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = [
        f"{name} marker, bradyscope rig frame (left camera)" for name in table.labels
    ]
    c3d["data"]["points"] = pts
    c3d.add_parameter("MANUFACTURER", "COMPANY", "bradyscope")
    c3d.write(str(path))
    _finish_c3d(path, -step, words.astype(np.float32))
    return path


def _finish_c3d(path: Path, scale: float, words: NDArray[np.float32]) -> None:
    """Write what ezc3d does not into the file it wrote: the header's scale factor
    (words 7-8, which it leaves at -1 whatever ``POINT:SCALE`` says, and readers check
    that the two agree) and each sample's fourth word ``words`` (T, M) (ezc3d puts the
    camera mask and the residual in each other's byte in float files: its issue 386).

    ezc3d writes Intel (little-endian) float files of points only: both are checked.
    """
    t, m = words.shape
    with open(path, "r+b") as fh:
        header = fh.read(512)
        param_block, n_points, n_analog = header[0], *struct.unpack("<HH", header[2:6])
        data_block = struct.unpack("<H", header[16:18])[0]
        fh.seek(512 * (param_block - 1))
        processor = fh.read(4)[3]
        if processor != 84 or n_points != m or n_analog != 0:  # 84: Intel
            raise ValueError(
                f"unexpected C3D layout in {path.name}: processor {processor}, "
                f"{n_points} points, {n_analog} analog values"
            )
        fh.seek(12)
        fh.write(struct.pack("<f", scale))
        fh.seek(512 * (data_block - 1))
        data = np.frombuffer(fh.read(t * m * 16), dtype="<f4").reshape(t, m, 4).copy()
        data[:, :, 3] = words
        fh.seek(512 * (data_block - 1))
        fh.write(data.tobytes())


def write_trc(path: str | Path, table: MarkerTable) -> Path:
    """Write the trajectories as an OpenSim TRC file (tab separated, mm).

    Frame numbers start at 1 as the format expects; ``Time`` is the left-video
    time in s. Missing samples are empty cells.
    """
    path = Path(path)
    t, m = table.frames.size, len(table.labels)
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
        "OrigDataStartFrame\tOrigNumFrames",
        f"{table.fps:.6g}\t{table.fps:.6g}\t{t}\t{m}\tmm\t{table.fps:.6g}\t"
        f"{int(table.frames[0]) + 1 if t else 1}\t{t}",
        "Frame#\tTime\t" + "\t".join(f"{name}\t\t" for name in table.labels).rstrip("\t"),
        "\t\t" + "\t".join(f"X{k}\tY{k}\tZ{k}" for k in range(1, m + 1)),
        "",
    ]
    time_s = table.time_s
    for i in range(t):
        cells = [str(i + 1), f"{time_s[i]:.6f}"]
        for j in range(m):
            cells.extend(_num(float(v), 4) for v in table.positions_mm[i, j])
        lines.append("\t".join(cells))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def read_trc(path: str | Path) -> tuple[float, tuple[str, ...], NDArray[np.float64]]:
    """Read a TRC file written by :func:`write_trc`: ``(fps, labels, positions_mm (T, M, 3))``."""
    lines = Path(path).read_text(encoding="utf-8").splitlines()
    fps = float(lines[2].split("\t")[0])
    labels = tuple(c for c in lines[3].split("\t")[2:] if c)
    rows = [ln.split("\t") for ln in lines[6:] if ln.strip()]
    m = len(labels)
    pos = np.full((len(rows), m, 3), np.nan)
    for i, cells in enumerate(rows):
        values = [float(c) if c != "" else np.nan for c in cells[2 : 2 + 3 * m]]
        values += [np.nan] * (3 * m - len(values))
        pos[i] = np.asarray(values).reshape(m, 3)
    return fps, labels, pos


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
) -> dict[str, Any]:
    spec = metric_spec(key, task.value)
    label, ucum, unit = spec.label, spec.ucum, spec.unit
    if first_10:  # the value the pages, the trends and the summary show (the item's 10 taps)
        key, label = f"{key}{FIRST_10_SUFFIX}", f"{label}, first 10 {task.cycle_word}s"
    obs: dict[str, Any] = {
        "resourceType": "Observation",
        **_version(trial_id, key, revision),
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
    return obs


OBSERVATION_ID_SYSTEM = "urn:bradyscope:trial-observation"
REPORT_ID_SYSTEM = "urn:bradyscope:trial-report"


def _version(trial_id: int, what: str, revision: int) -> dict[str, Any]:
    """A measured resource's identifier, the same in every revision of the trial (so that
    a receiving system replaces the values it holds), its version (the revision) and its
    status: ``final``, or ``amended`` once a correction or a re-analysis has changed the
    first result."""
    system = REPORT_ID_SYSTEM if what == "report" else OBSERVATION_ID_SYSTEM
    value = str(trial_id) if what == "report" else f"{trial_id}/{what}"
    return {
        "meta": {"versionId": str(revision)},
        "identifier": [{"system": system, "value": value}],
        "status": "final" if revision <= 1 else "amended",
    }


def _iso(value: datetime) -> str:
    if value.tzinfo is None:
        value = value.replace(tzinfo=UTC)
    return value.isoformat(timespec="seconds")


def fhir_bundle(data: ReportData, pdf_bytes: bytes | None) -> dict[str, Any]:
    """A FHIR R4 ``collection`` Bundle for one trial.

    Contents: the Patient (only its pseudonymous code as identifier), one
    Observation per numeric metric (UCUM units, code system
    ``urn:bradyscope:finger-tapping-metric``), and a DiagnosticReport that
    references them and carries the PDF report as ``presentedForm``. The
    result is validated with ``fhir.resources.R4B`` before it is returned.

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
    if data.clinician_rating is not None:
        entries.append({"fullUrl": _urn(), "resource": _rating_observation(data, patient_url)})
    report = _diagnostic_report(
        data,
        patient_url,
        effective=effective,
        issued=issued,
        observation_urls=measured_urls,
        pdf_bytes=pdf_bytes,
    )
    entries.append({"fullUrl": _urn(), "resource": report})
    doc: dict[str, Any] = {
        "resourceType": "Bundle",
        "type": "collection",  # no server-side processing asked for; a set of resources
        "timestamp": issued,
        "identifier": {"system": "urn:bradyscope:trial", "value": str(data.trial_id)},
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
        **_version(data.trial_id, "panel", data.revision),
        "category": [
            {
                "coding": [
                    {
                        "system": "http://terminology.hl7.org/CodeSystem/observation-category",
                        "code": "exam",
                        "display": "Exam",
                    }
                ]
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
            "text": f"{task.heading}, {data.hand} {task.limb}: measured",
        },
        "subject": {"reference": patient_ref},
        "effectiveDateTime": effective,
        "bodySite": {"text": _body_site(task, data.hand)},
        "method": {"text": _method(task)},
        "hasMember": [{"reference": u} for u in member_urls],
    }


RATING_CODE_SYSTEM = "urn:bradyscope:clinician-rating"


def _rating_observation(data: ReportData, patient_ref: str) -> dict[str, Any]:
    """The clinician's own MDS-UPDRS rating of the trial: an Observation of its own.

    Distinct from the measured Observations: its own code system
    (``urn:bradyscope:clinician-rating``), category ``exam`` with the text
    "Clinician's rating", the clinician as ``performer``, an integer value
    0–4, and the comment as ``note``. The DiagnosticReport (the instrument's
    measurement) does not list it among its results.
    """
    task = parse_task(data.task)
    item = task.updrs_item
    obs: dict[str, Any] = {
        "resourceType": "Observation",
        "status": "final",
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
        "valueInteger": int(data.clinician_rating or 0),
    }
    if data.rated_at is not None:
        obs["issued"] = _iso(data.rated_at)
    if data.rated_by:
        obs["performer"] = [{"display": data.rated_by}]
    if data.rating_comment:
        obs["note"] = [{"text": data.rating_comment}]
    return obs


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
        **_version(data.trial_id, "report", data.revision),
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

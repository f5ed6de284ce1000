"""The patient's state at a session as FHIR: a ``component`` of every Observation.

The medication state (the MDS-UPDRS "clinical state", ON or OFF), the deep brain
stimulation state and the minutes since the last levodopa dose are what makes two
values of the same hand on the same day comparable; a receiver reads them on each
Observation, not from the DiagnosticReport's free text. Neither LOINC nor SNOMED CT
gives us a code we could check for them, so the codes are bradyscope's own URNs, stable
across versions (docs/reports.md, "FHIR details").
"""

from __future__ import annotations

from typing import Any

UCUM_SYSTEM = "http://unitsofmeasure.org"
SESSION_STATE_SYSTEM = "urn:bradyscope:session-state"
"""The codes of the components: ``medication-state``, ``dbs-state``, ``time-since-levodopa``."""
MEDICATION_STATE_SYSTEM = "urn:bradyscope:medication-state"
"""The medication state's values: ``on``, ``off``."""
DBS_STATE_SYSTEM = "urn:bradyscope:dbs-state"
"""The deep brain stimulation state's values: ``on``, ``off``, ``none`` (no device)."""
MEDICATION_STATES = {"on": "ON medication", "off": "OFF medication"}
DBS_STATES = {"on": "DBS on", "off": "DBS off", "none": "No DBS device"}
_UNKNOWN = {
    "coding": [
        {
            "system": "http://terminology.hl7.org/CodeSystem/data-absent-reason",
            "code": "unknown",
            "display": "Unknown",
        }
    ]
}


def _coded(
    code: str, display: str, system: str, value: str, names: dict[str, str]
) -> dict[str, Any]:
    component: dict[str, Any] = {
        "code": {"coding": [{"system": SESSION_STATE_SYSTEM, "code": code, "display": display}]}
    }
    if value in names:
        component["valueCodeableConcept"] = {
            "coding": [{"system": system, "code": value, "display": names[value]}],
            "text": names[value],
        }
    else:  # "unknown": not recorded for the session
        component["dataAbsentReason"] = _UNKNOWN
    return component


def state_components(
    medication_state: str, dbs_state: str, time_since_levodopa_min: int | None
) -> list[dict[str, Any]]:
    """The ``component`` list of an Observation made in this state.

    Parameters
    ----------
    medication_state : {"on", "off", "unknown"}
    dbs_state : {"on", "off", "none", "unknown"}
    time_since_levodopa_min : int or None
        Left out when not recorded.

    Returns
    -------
    list of dict
        The medication state and the DBS state (``dataAbsentReason`` ``unknown`` when
        unknown), then the time since levodopa in UCUM ``min``.
    """
    out = [
        _coded(
            "medication-state",
            "Medication state (MDS-UPDRS clinical state)",
            MEDICATION_STATE_SYSTEM,
            medication_state,
            MEDICATION_STATES,
        ),
        _coded(
            "dbs-state", "Deep brain stimulation state", DBS_STATE_SYSTEM, dbs_state, DBS_STATES
        ),
    ]
    if time_since_levodopa_min is not None:
        display = "Time since the last levodopa dose"
        out.append(
            {
                "code": {
                    "coding": [
                        {
                            "system": SESSION_STATE_SYSTEM,
                            "code": "time-since-levodopa",
                            "display": display,
                        }
                    ]
                },
                "valueQuantity": {
                    "value": int(time_since_levodopa_min),
                    "unit": "min",
                    "system": UCUM_SYSTEM,
                    "code": "min",
                },
            }
        )
    return out

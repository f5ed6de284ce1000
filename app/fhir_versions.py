"""How a receiving system matches the resources of our FHIR Bundles: identifiers and versions.

- Each measured resource keeps one ``identifier`` through every revision of its trial
  (:func:`measured_identity`), the clinician's rating one per trial
  (:func:`rating_identity`), so that a receiver replaces what it holds.
- Each has a ``meta.versionId``: a base (the revision, or when the rating was given)
  and the digest of its content (:func:`finish_versions`), so that any edit of what it
  says is a new version and the same content exported again the same one.
- ``Bundle.identifier`` names the content (:func:`bundle_identifier`), so that a
  receiver that drops a Bundle it has seen drops only the same content sent again.

docs/reports.md, "FHIR details".
"""

from __future__ import annotations

import hashlib
import json
from datetime import UTC, datetime
from typing import Any

OBSERVATION_ID_SYSTEM = "urn:bradyscope:trial-observation"
REPORT_ID_SYSTEM = "urn:bradyscope:trial-report"
RATING_ID_SYSTEM = "urn:bradyscope:trial-rating"
"""The system of the rating Observation's identifier, ``<trial id>/mds-updrs-<item>``."""
BUNDLE_ID_SYSTEM = "urn:bradyscope:trial-export"
"""The system of ``Bundle.identifier``: ``<trial id>/<revision>/<digest>``."""

# What a resource's version does not depend on: references to other entries (their
# fullUrls are new uuids in every export); for the DiagnosticReport also the time of the
# export and the PDF's bytes (made again from the same content, with another "generated
# on"): what the PDF shows counts instead (finish_versions' report_content).
_UNVERSIONED = frozenset({"meta", "subject", "hasMember", "result"})
_UNVERSIONED_REPORT = _UNVERSIONED | {"issued", "presentedForm"}


def measured_identity(trial_id: int, what: str, revision: int) -> dict[str, Any]:
    """A measured resource's identifier (``what``: a metric key, ``panel`` or ``report``),
    the same in every revision of the trial, the base of its version (the revision) and
    its status: ``final``, or ``amended`` once a correction or a re-analysis has changed
    the first result."""
    system = REPORT_ID_SYSTEM if what == "report" else OBSERVATION_ID_SYSTEM
    value = str(trial_id) if what == "report" else f"{trial_id}/{what}"
    return {
        "meta": {"versionId": str(revision)},
        "identifier": [{"system": system, "value": value}],
        "status": "final" if revision <= 1 else "amended",
    }


def rating_identity(trial_id: int, item: str, rated_at: datetime | None) -> dict[str, Any]:
    """The rating Observation's identifier (one per trial) and the base of its version:
    when it was rated or cleared (UTC, to the second; ``0`` when not known)."""
    if rated_at is None:
        base = "0"
    else:
        utc = rated_at.replace(tzinfo=UTC) if rated_at.tzinfo is None else rated_at
        base = utc.astimezone(UTC).strftime("%Y%m%dT%H%M%SZ")
    return {
        "meta": {"versionId": base},
        "identifier": [{"system": RATING_ID_SYSTEM, "value": f"{trial_id}/mds-updrs-{item}"}],
    }


def _digest(value: object, n: int) -> str:
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:n]


def finish_versions(resources: list[dict[str, Any]], *, report_content: str | None = None) -> None:
    """Complete the ``meta.versionId`` of every resource that has one (in place):
    ``<base>.<8 hex digits of its content>``. ``report_content`` stands for the attached
    PDF in the DiagnosticReport's content (``app.reports.rendering.report_key``: what
    the report shows, made at a fixed time): the PDF shows what no Observation carries
    (the session's notes, the clinician, the trials beside it)."""
    for res in resources:
        if "meta" not in res:
            continue
        report = res["resourceType"] == "DiagnosticReport"
        skip = _UNVERSIONED_REPORT if report else _UNVERSIONED
        content = {k: v for k, v in res.items() if k not in skip}
        if report and report_content is not None:
            content["presentedForm"] = report_content
        res["meta"] = {"versionId": f"{res['meta']['versionId']}.{_digest(content, 8)}"}


def bundle_identifier(
    trial_id: int, revision: int, resources: list[dict[str, Any]]
) -> dict[str, str]:
    """``Bundle.identifier`` of this content: the trial, the revision, and the digest of
    every resource's identifiers and version (the rating's among them, and the Patient's
    code). Two exports of the same content share it; any change gives another."""
    versions = sorted(
        (i["system"], i["value"], r.get("meta", {}).get("versionId", ""))
        for r in resources
        for i in r.get("identifier", [])
    )
    return {"system": BUNDLE_ID_SYSTEM, "value": f"{trial_id}/{revision}/{_digest(versions, 16)}"}

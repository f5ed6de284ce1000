# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""``?revision=N`` on every export of a trial's result, as on ``/result`` and the reports.

A hospital integrator asked ``/fhir?revision=1`` (and ``markers.csv``, ``.c3d``, ``.trc``)
and got the current revision without a word. Each revision keeps its own trajectories
(a label swap writes new ones) and calibration, so each export of it can be made again.
"""

from __future__ import annotations

import pytest
from api_support import Api, api, video_pair  # noqa: F401 - fixtures
from sqlalchemy import select
from test_revisions import _trial

from app.models import AuditEvent

EXPORTS = ("markers.csv", "markers.c3d", "markers.trc")


@pytest.fixture
def revised(api: Api, video_pair) -> int:
    """A trial with revision 1 (its analysis) and revision 2 (thumb and index swapped)."""
    trial_id = _trial(api, video_pair)
    swap = api.client.post(
        f"/api/v1/trials/{trial_id}/revisions",
        json={"swap_labels": True, "reason": "thumb and index were the wrong way round"},
        headers=api.headers,
    )
    assert swap.status_code == 201 and swap.json()["revision"] == 2, swap.text
    return trial_id


@pytest.mark.parametrize("name", EXPORTS)
def test_a_trajectory_export_serves_the_revision_asked_for(api: Api, revised: int, name) -> None:
    url = f"/api/v1/trials/{revised}/{name}"
    current = api.client.get(url, headers=api.headers)
    first = api.client.get(f"{url}?revision=1", headers=api.headers)
    second = api.client.get(f"{url}?revision=2", headers=api.headers)
    assert current.status_code == first.status_code == second.status_code == 200, first.text
    assert second.content == current.content
    assert first.content != current.content  # the labels of revision 1 are not swapped
    missing = api.client.get(f"{url}?revision=9", headers=api.headers)
    assert missing.status_code == 404 and "revisions are 1 to 2" in missing.json()["detail"]
    with api.sessions() as db:
        last = db.scalars(select(AuditEvent).order_by(AuditEvent.id.desc())).first()
    assert (last.action, last.resource_id, last.outcome) == ("export", str(revised), "not_found")


def test_the_fhir_bundle_of_a_revision_is_that_version(api: Api, revised: int) -> None:
    url = f"/api/v1/trials/{revised}/fhir"

    def report(answer) -> dict:  # type: ignore[no-untyped-def]
        assert answer.status_code == 200, answer.text
        entries = [e["resource"] for e in answer.json()["entry"]]
        return next(r for r in entries if r["resourceType"] == "DiagnosticReport")

    current = report(api.client.get(url, headers=api.headers))
    first = report(api.client.get(f"{url}?revision=1", headers=api.headers))
    # versionId: the revision (and what else app.exports puts after a dot)
    assert (current["meta"]["versionId"].split(".")[0], current["status"]) == ("2", "amended")
    assert (first["meta"]["versionId"].split(".")[0], first["status"]) == ("1", "final")
    assert first["identifier"] == current["identifier"]  # the same report, another version
    assert api.client.get(f"{url}?revision=3", headers=api.headers).status_code == 404

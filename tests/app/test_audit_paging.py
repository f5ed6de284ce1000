# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Paging the audit trail by sequence number: pages that do not move while it grows.

A hospital integrator paged ``GET /audit?limit=5&offset=0``, then ``offset=5``...: each
read of the trail adds an event at its top, so every offset page repeated the last
item of the page before. ``before_seq`` / ``after_seq`` and the answer's ``next`` page
by the events' numbers instead.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from api_support import Api, api, make_api_key  # noqa: F401 - fixtures
from fastapi.testclient import TestClient
from sqlalchemy import text

from app.db import dispose_engines, get_sessionmaker, migrate
from app.main import create_app


def _auditor(api: Api) -> dict[str, str]:
    key = make_api_key(api.sessions, name="auditor", scopes=("audit:read",))
    return {"Authorization": f"Bearer {key}"}


def _events(api: Api, n: int) -> None:
    """``n`` events about patients (a create and reads)."""
    pid = api.client.post("/api/v1/patients", json={"code": "PD-7"}, headers=api.headers).json()
    for _ in range(n - 1):
        assert api.client.get(f"/api/v1/patients/{pid['id']}", headers=api.headers).is_success


def test_offset_pages_shift_and_next_pages_do_not(api: Api) -> None:
    _events(api, 9)
    auditor = _auditor(api)
    # The problem: the read of page 1 is the newest event when page 2 is read.
    one = api.client.get("/api/v1/audit?limit=4", headers=auditor).json()
    two = api.client.get("/api/v1/audit?limit=4&offset=4", headers=auditor).json()
    assert one["items"][-1]["seq"] == two["items"][0]["seq"]  # repeated by offset paging
    # Following next: every event once, in sequence, however many reads are added.
    first = api.client.get("/api/v1/audit?limit=4", headers=auditor).json()
    top = first["items"][0]["seq"]
    seen, page = [e["seq"] for e in first["items"]], first
    while page["next"] is not None:
        assert page["next"].startswith("/api/v1/audit?") and "before_seq=" in page["next"]
        page = api.client.get(page["next"], headers=auditor).json()
        assert page["total"] <= first["total"]
        seen += [e["seq"] for e in page["items"]]
    assert seen == list(range(top, 0, -1))  # newest first, none repeated, none missed
    assert page["offset"] == 0 and len(page["items"]) <= 4


def test_after_seq_reads_what_was_added_oldest_first(api: Api) -> None:
    _events(api, 3)
    auditor = _auditor(api)
    top = api.client.get("/api/v1/audit?limit=1", headers=auditor).json()["items"][0]["seq"]
    _events_after = api.client.get("/api/v1/patients", headers=api.headers)
    assert _events_after.is_success
    new = api.client.get(f"/api/v1/audit?after_seq={top}&limit=1", headers=auditor).json()
    # the read that found top, then the list of patients: oldest first, one per page
    assert [e["seq"] for e in new["items"]] == [top + 1] and new["total"] == 2
    assert new["items"][0]["resource_type"] == "audit"
    assert new["next"] is not None and f"after_seq={top + 1}" in new["next"]
    rest = api.client.get(new["next"], headers=auditor).json()
    assert [(e["seq"], e["resource_type"]) for e in rest["items"]] == [(top + 2, "patient")]
    # the read of the page before is newer still: a feed read so never ends, nor repeats
    assert rest["total"] == 2 and f"after_seq={top + 2}" in rest["next"]
    last = api.client.get(f"/api/v1/audit?after_seq={top + 2}", headers=auditor).json()
    assert [e["seq"] for e in last["items"]] == [top + 3, top + 4] and last["next"] is None


def test_next_keeps_the_filters_and_both_cursors_are_refused(api: Api) -> None:
    _events(api, 5)
    auditor = _auditor(api)
    pid = api.client.get("/api/v1/patients", headers=api.headers).json()["items"][0]["id"]
    page = api.client.get(f"/api/v1/audit?patient_id={pid}&limit=2", headers=auditor).json()
    assert f"patient_id={pid}" in page["next"] and "limit=2" in page["next"]
    both = api.client.get("/api/v1/audit?before_seq=5&after_seq=1", headers=auditor)
    assert both.status_code == 422, both.text
    assert both.json()["errors"][0]["loc"] == ["query", "after_seq"]
    assert "not both" in both.json()["detail"]
    assert api.client.get("/api/v1/audit?before_seq=0", headers=auditor).status_code == 422


def test_events_older_than_the_chain_are_paged_too(tmp_path: Path, make_settings) -> None:
    """Events written before the chain (revision 0010) have no number: they come last,
    and next pages through them by an offset among them (none is ever added)."""
    settings = make_settings(tmp_path / "data")
    migrate(settings, revision="0009")
    engine = get_sessionmaker(settings).kw["bind"]
    with engine.begin() as conn:
        for i in range(1, 6):
            conn.execute(
                text(
                    "INSERT INTO audit_events (at, actor_type, action, resource_type, outcome)"
                    " VALUES (:at, 'system', 'read', 'patient', 'success')"
                ),
                {"at": f"2026-01-0{i} 10:00:00.000000"},
            )
    dispose_engines()
    migrate(settings)
    sessions = get_sessionmaker(settings)
    key = make_api_key(sessions, name="auditor", scopes=("audit:read",))
    try:
        with TestClient(create_app(settings)) as client:
            headers = {"Authorization": f"Bearer {key}"}
            page = client.get("/api/v1/audit?limit=2", headers=headers).json()
            ids = [e["id"] for e in page["items"]]
            while page["next"] is not None:
                page = client.get(page["next"], headers=headers).json()
                ids += [e["id"] for e in page["items"]]
            # the five unnumbered, newest first; the reads (numbered 1, 2...) are newer
            assert ids == [5, 4, 3, 2, 1]
            newer = client.get("/api/v1/audit?after_seq=0", headers=headers).json()
            assert [e["seq"] for e in newer["items"]] == [1, 2, 3]  # the three reads above
    finally:
        dispose_engines()


@pytest.mark.parametrize("cursor", ["before_seq", "after_seq"])
def test_the_cursors_are_in_the_openapi_document(api: Api, cursor: str) -> None:
    doc = api.client.get("/openapi.json").json()
    get = doc["paths"]["/api/v1/audit"]["get"]
    assert cursor in [p["name"] for p in get["parameters"]]
    page = get["responses"]["200"]["content"]["application/json"]["schema"]["$ref"]
    assert "next" in doc["components"]["schemas"][page.rsplit("/", 1)[1]]["properties"]


@pytest.mark.postgres
def test_next_pages_on_postgresql(pg_settings) -> None:
    sessions = get_sessionmaker(pg_settings)
    key = make_api_key(sessions)
    headers = {"Authorization": f"Bearer {key}"}
    try:
        with TestClient(create_app(pg_settings)) as client:
            pid = client.post("/api/v1/patients", json={"code": "PD-9"}, headers=headers).json()
            for _ in range(4):
                client.get(f"/api/v1/patients/{pid['id']}", headers=headers)
            page = client.get("/api/v1/audit?limit=2", headers=headers).json()
            seen = [e["seq"] for e in page["items"]]
            while page["next"] is not None:
                page = client.get(page["next"], headers=headers).json()
                seen += [e["seq"] for e in page["items"]]
            assert seen == list(range(seen[0], 0, -1)) and seen[0] >= 5
    finally:
        dispose_engines()

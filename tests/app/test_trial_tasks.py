# ruff: noqa: F811  (pytest fixtures imported from api_support / test_pages are parameters here)
"""A trial records one task: the upload's ``task``, the trial row, the API and the pages."""

from __future__ import annotations

import re

import pytest
from api_support import (  # noqa: F401 - fixtures
    Api,
    api,
    rig_document,
    seed_recording_target,
    trial_files,
    video_pair,
)
from sqlalchemy import select
from test_pages import client, login, seeded  # noqa: F401 - fixtures

from app.models import Job, Trial


@pytest.mark.parametrize(
    "task", ["hand_movements", "pronation_supination", "toe_tapping", "leg_agility"]
)
def test_the_upload_stores_the_task_and_the_api_reads_it_back(
    api: Api, video_pair, task: str
) -> None:
    seeded = seed_recording_target(api)
    left, right = video_pair
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "left", "task": task},
        files=trial_files(left, right),
        headers=api.headers,
    )
    assert r.status_code == 201, r.text
    trial_id = r.json()["id"]
    with api.sessions() as db:
        trial = db.get(Trial, trial_id)
        assert trial is not None and trial.task == task
    read = api.client.get(f"/api/v1/trials/{trial_id}", headers=api.headers)
    assert read.status_code == 200 and read.json()["task"] == task
    listed = api.client.get(f"/api/v1/sessions/{seeded.session_id}/trials", headers=api.headers)
    assert [t["task"] for t in listed.json()] == [task]


def test_a_trial_without_task_is_finger_tapping(api: Api, video_pair) -> None:
    seeded = seed_recording_target(api)
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "right"},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    assert r.status_code == 201, r.text
    read = api.client.get(f"/api/v1/trials/{r.json()['id']}", headers=api.headers)
    assert read.json()["task"] == "finger_tapping"


def test_an_unknown_task_is_refused_and_leaves_nothing(api: Api, video_pair) -> None:
    seeded = seed_recording_target(api)
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "right", "task": "gait"},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    assert r.status_code == 422, r.text
    assert "task must be one of finger_tapping" in r.json()["detail"]
    assert api.recording_rows() == (0, 0, 0)
    with api.sessions() as db:
        assert db.scalars(select(Job)).first() is None


def _second_rig(api: Api, name: str, *, calibrated: bool = True) -> int:
    """Another rig (another placement of the cameras), with a rig-file calibration."""
    import json

    rig = api.client.post("/api/v1/rigs", json={"name": name}, headers=api.headers).json()
    if calibrated:
        cal = api.client.post(
            f"/api/v1/rigs/{rig['id']}/calibrations",
            files={
                "rig_json": ("rig.json", json.dumps(rig_document()).encode(), "application/json")
            },
            headers=api.headers,
        )
        assert cal.status_code == 201, cal.text
    return int(rig["id"])


def test_a_trial_names_the_rig_that_recorded_it(api: Api, video_pair) -> None:
    """Toe tapping and leg agility film from another placement: a trial may name its rig;
    its analysis job is queued, and the API reads the rig back (the session's otherwise)."""
    seeded = seed_recording_target(api)
    legs = _second_rig(api, "clinic-A legs")
    made = {}
    for rig_id in (str(legs), str(seeded.rig_id), ""):
        r = api.client.post(
            f"/api/v1/sessions/{seeded.session_id}/trials",
            data={"hand": "left", "task": "leg_agility", "rig_id": rig_id},
            files=trial_files(*video_pair),
            headers=api.headers,
        )
        assert r.status_code == 201, r.text
        made[rig_id] = r.json()["id"]
    with api.sessions() as db:
        stored = {k: db.get(Trial, v).rig_id for k, v in made.items()}  # type: ignore[union-attr]
    assert stored == {str(legs): legs, str(seeded.rig_id): None, "": None}  # NULL: the session's
    read = {
        k: api.client.get(f"/api/v1/trials/{v}", headers=api.headers).json()["rig_id"]
        for k, v in made.items()
    }
    assert read == {str(legs): legs, str(seeded.rig_id): seeded.rig_id, "": seeded.rig_id}


@pytest.mark.parametrize(
    ("rig_id", "status", "words"),
    [
        ("9999", 422, "rig_id '9999' names no rig"),
        ("legs", 422, "rig_id must be a rig's id, a whole number"),
        ("²", 422, "a whole number"),  # a digit to str.isdigit, not to int()
        ("1.0", 422, "a whole number such as 3, not '1.0'"),
        ("99999999999999999999", 422, "names no rig"),  # beyond a PostgreSQL integer
        (None, 409, ""),
    ],
)
def test_a_rig_that_cannot_measure_the_trial_is_refused_and_leaves_nothing(
    api: Api, video_pair, rig_id: str | None, status: int, words: str
) -> None:
    seeded = seed_recording_target(api)
    if rig_id is None:  # a rig without any calibration
        uncalibrated = _second_rig(api, "clinic-A new placement", calibrated=False)
        rig_id, words = str(uncalibrated), f"rig {uncalibrated} has no ready calibration"
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "right", "task": "toe_tapping", "rig_id": rig_id},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    assert r.status_code == status, r.text
    assert words in r.json()["detail"]
    assert api.recording_rows() == (0, 0, 0)


def test_the_openapi_document_offers_the_tasks(api: Api) -> None:
    doc = api.client.get("/openapi.json").json()
    body = doc["paths"]["/api/v1/sessions/{session_id}/trials"]["post"]["requestBody"]
    schema = body["content"]["multipart/form-data"]["schema"]
    assert schema["properties"]["task"]["enum"] == [
        "finger_tapping",
        "hand_movements",
        "pronation_supination",
        "toe_tapping",
        "leg_agility",
    ]


def test_the_session_page_shows_every_task_by_side_and_offers_the_task(
    client, seeded, db_sessionmaker
) -> None:
    login(client)
    right_id = seeded["trials"][(1, "right")]
    with db_sessionmaker() as db:
        trial = db.get(Trial, right_id)
        session_id = trial.session_id
        trial.task = "toe_tapping"  # the left one stays finger tapping
        db.commit()
    page = client.get(f"/sessions/{session_id}").text
    for title in (
        "Finger tapping (MDS-UPDRS 3.4)",
        "Hand movements (MDS-UPDRS 3.5)",
        "Pronation–supination (MDS-UPDRS 3.6)",
        "Toe tapping (MDS-UPDRS 3.7)",
        "Leg agility (MDS-UPDRS 3.8)",
    ):
        assert title in page
    assert '<select id="task-left" name="task">' in page
    assert f'href="/trials/{right_id}" class="status status-succeeded">measured</a>' in page
    # one side per task: no right–left comparison is offered
    assert "data-compare-hands" not in page
    trial_page = client.get(f"/trials/{right_id}").text
    assert "Toe tapping (MDS-UPDRS 3.7)" in trial_page
    assert "Your MDS-UPDRS 3.7 rating of the right foot" in trial_page


def test_the_session_page_compares_the_two_sides_of_a_task(client, seeded) -> None:
    login(client)
    right_id = seeded["trials"][(1, "right")]
    left_id = seeded["trials"][(1, "left")]
    trial_page = client.get(f"/trials/{right_id}").text
    assert "Finger tapping (MDS-UPDRS 3.4)" in trial_page
    match = re.search(r'href="/sessions/(\d+)"', trial_page)
    assert match
    session_page = client.get(f"/sessions/{match.group(1)}").text
    assert f"/trials/{right_id}?compare={left_id}#compare" in session_page

# ruff: noqa: F811  (pytest fixtures imported from api_support / test_pages are parameters here)
"""A trial records one task: the upload's ``task``, the trial row, the API and the pages."""

from __future__ import annotations

import re

import pytest
from api_support import (  # noqa: F401 - fixtures
    Api,
    api,
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
    assert f'href="/trials/{right_id}">succeeded</a>' in page
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

# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Result revisions through the API: corrections measured by core, history, re-analysis jobs."""

from __future__ import annotations

import pytest
from api_support import Api, add_result, api, seed_recording_target, trial_files, video_pair  # noqa: F401 - pytest fixtures
from sqlalchemy import select

from app.models import AuditEvent, Job, Result, Trial
from app.reports.figures import read_plots_document
from app.storage import Storage
from core.cycles import common_metrics
from core.markers_csv import MEASURED, read_markers_csv
from core.metrics import compute_metrics, tapping_metrics

REASON = "tap 3 was the patient reaching for the glasses"


def _trial(api: Api, video_pair) -> int:
    seeded = seed_recording_target(api)
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "left"},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    assert r.status_code == 201, r.text
    trial_id = int(r.json()["id"])
    add_result(api, trial_id)
    with api.sessions() as db:  # no analysis job will run in these tests
        for job in db.scalars(select(Job).where(Job.trial_id == trial_id)):
            job.status = "succeeded"
        db.commit()
    return trial_id


def _core_metrics_without(
    api: Api, trial_id: int, drop: set[int], dismiss: frozenset[int] = frozenset()
):
    """What core computes on the stored trajectories without those taps (the oracle)."""
    with api.sessions() as db:
        path = db.scalar(select(Result.markers_path).where(Result.trial_id == trial_id))
    table = read_markers_csv(Storage.from_settings(api.settings).absolute(path), fps=100.0)
    full = compute_metrics(table.positions_mm, table.fps, measured=table.status == MEASURED)
    kept = [t for t in full.taps if t.index not in drop]
    idx = {t.index for t in kept}
    events = [
        e
        for e in full.events
        if e["kind"] == "gap" or (e["tap_index"] in idx and e["tap_index"] not in dismiss)
    ]
    metrics = tapping_metrics(kept, events)
    return full, {**metrics, **common_metrics(metrics, "mm")}  # with every task's common keys


def test_excluding_a_tap_is_a_new_revision_measured_by_core(api: Api, video_pair) -> None:
    trial_id = _trial(api, video_pair)
    h = api.headers
    original = api.client.get(f"/api/v1/trials/{trial_id}/result", headers=h).json()
    assert original["revision"] == 1 and original["edits"] == []

    r = api.client.post(
        f"/api/v1/trials/{trial_id}/revisions",
        json={"exclude_taps": [2], "reason": REASON},
        headers=h,
    )
    assert r.status_code == 201, r.text
    assert r.json() == {"trial_id": trial_id, "revision": 2, "job_id": None}

    current = api.client.get(f"/api/v1/trials/{trial_id}/result", headers=h).json()
    _, expected = _core_metrics_without(api, trial_id, {2})
    assert current["revision"] == 2
    assert current["metrics"] == pytest.approx(expected, abs=1e-12)  # JSON round trip only
    assert current["metrics"]["tap_count"] == original["metrics"]["tap_count"] - 1
    assert current["metrics"]["amplitude_mm_mean"] != original["metrics"]["amplitude_mm_mean"]
    assert [t["index"] for t in current["excluded_taps"]] == [2]
    assert 2 not in [t["index"] for t in current["taps"]]
    (edit,) = current["edits"]
    assert edit["reason"] == REASON and edit["change"] == {"exclude_taps": [2]}
    assert edit["by"] == "API client hospital" and edit["revision"] == 2
    # The measurement of the recording itself is kept.
    assert current["sync"] == original["sync"] and current["fps"] == original["fps"]

    # The original stays, unchanged, as revision 1.
    first = api.client.get(f"/api/v1/trials/{trial_id}/result?revision=1", headers=h)
    assert first.status_code == 200 and first.json() == original
    assert (
        api.client.get(f"/api/v1/trials/{trial_id}/result?revision=3", headers=h).status_code == 404
    )

    history = api.client.get(f"/api/v1/trials/{trial_id}/revisions", headers=h).json()
    assert [(v["revision"], v["kind"], v["current"]) for v in history] == [
        (2, "correction", True),
        (1, "analysis", False),
    ]
    assert history[0]["reason"] == REASON and history[0]["created_by"] == "API client hospital"


def test_corrections_accumulate_and_reports_state_the_revision(api: Api, video_pair) -> None:
    trial_id = _trial(api, video_pair)
    h = api.headers
    url = f"/api/v1/trials/{trial_id}/revisions"
    assert (
        api.client.post(url, json={"exclude_taps": [2], "reason": REASON}, headers=h).status_code
        == 201
    )
    doc = api.client.get(f"/api/v1/trials/{trial_id}/result", headers=h).json()
    pauses = [e for e in doc["events"] if e["kind"] in ("hesitation", "halt")]
    assert pauses, "the synthetic trial has a pause after tap 12"
    tap = pauses[0]["tap_index"]
    r = api.client.post(
        url, json={"dismiss_pauses": [tap], "reason": "the patient was talking"}, headers=h
    )
    assert r.status_code == 201 and r.json()["revision"] == 3
    doc = api.client.get(f"/api/v1/trials/{trial_id}/result", headers=h).json()
    _, expected = _core_metrics_without(api, trial_id, {2}, frozenset({tap}))
    assert doc["corrections"]["exclude_taps"] == [2]  # kept from revision 2
    assert doc["metrics"] == pytest.approx(expected, abs=1e-12)
    assert len(doc["edits"]) == 2

    html = api.client.get(f"/api/v1/trials/{trial_id}/report.html", headers=h).text
    assert "Result revision" in html and "3 — edited" in html
    assert "the patient was talking" in html and "excluded taps 3" in html  # 1-based on reports
    old = api.client.get(f"/api/v1/trials/{trial_id}/report.html?revision=1", headers=h).text
    assert "1 — as measured" in old and "edited after" not in old


def test_a_correction_stores_its_plots_and_the_report_reads_them(api: Api, video_pair) -> None:
    trial_id = _trial(api, video_pair)
    h = api.headers
    r = api.client.post(
        f"/api/v1/trials/{trial_id}/revisions",
        json={"exclude_taps": [2], "reason": REASON},
        headers=h,
    )
    assert r.status_code == 201, r.text
    storage = Storage.from_settings(api.settings)
    with api.sessions() as db:
        first, second = db.scalars(
            select(Result).where(Result.trial_id == trial_id).order_by(Result.revision)
        ).all()
        doc = second.document
        assert first.plots_path is None  # stored without plots (as before the migration)
        stored = read_plots_document(storage.absolute(second.plots_path).read_text())
    assert stored is not None
    # Drawn from the corrected revision: one tap fewer.
    assert f"Amplitude of {doc['metrics']['tap_count']} taps" in stored["amplitude"]
    html = api.client.get(f"/api/v1/trials/{trial_id}/report.html", headers=h).text
    # The stored drawing itself (its element ids are unique to that drawing).
    for svg in stored.values():
        assert svg in html
    # Revision 1 has none stored: drawn on demand, with its own taps.
    old = api.client.get(f"/api/v1/trials/{trial_id}/report.html?revision=1", headers=h).text
    assert f"Amplitude of {doc['metrics']['tap_count'] + 1} taps" in old
    assert stored["amplitude"] not in old


@pytest.mark.parametrize(
    ("body", "status", "text"),
    [
        ({"exclude_taps": [2]}, 422, "reason"),
        ({"exclude_taps": [2], "reason": "  "}, 422, "reason"),
        ({"reason": REASON}, 422, "Say what to change"),
        ({"exclude_taps": [999], "reason": REASON}, 422, "no tap 1000 (index 999)"),
        # numbers are strict: JSON true or "1" is not tap 1
        ({"exclude_taps": [True], "reason": REASON}, 422, "valid integer"),
        ({"exclude_taps": ["1"], "reason": REASON}, 422, "valid integer"),
        ({"swap_labels": 1, "reason": REASON}, 422, "valid boolean"),
        ({"exclude_taps": [1], "swap_cameras": True, "reason": REASON}, 422, "two revisions"),
        ({"window_s": [5.0, 1.0], "reason": REASON}, 422, "window_s"),
        ({"exclude_taps": [], "reason": REASON}, 422, "nothing would change"),
        # a re-analysis that asks for nothing is not one (it measured the same again)
        ({"swap_cameras": False, "reason": REASON}, 422, "nothing would change"),
        ({"swap_cameras": None, "reason": REASON}, 422, "Say what to change"),
        ({"offset_frames": None, "reason": REASON}, 422, "Say what to change"),
    ],
)
def test_bad_revisions_are_refused_and_store_nothing(api: Api, video_pair, body, status, text):
    trial_id = _trial(api, video_pair)
    r = api.client.post(f"/api/v1/trials/{trial_id}/revisions", json=body, headers=api.headers)
    assert r.status_code == status, r.text
    assert text in r.text
    assert api.count(Result) == 1


def test_swap_cameras_is_refused_when_the_analysis_measured_the_videos_so(
    api: Api, video_pair
) -> None:
    """swap_cameras says how the videos are measured: as the newest analysis did is no change
    (422, no job); the other way round is a re-analysis; false beside a correction is none."""
    trial_id = _trial(api, video_pair)
    url, h = f"/api/v1/trials/{trial_id}/revisions", api.headers
    mixed = api.client.post(
        url, json={"swap_cameras": False, "exclude_taps": [1], "reason": REASON}, headers=h
    )
    assert mixed.status_code == 201 and mixed.json()["revision"] == 2, mixed.text
    with api.sessions() as db:  # as if the newest analysis had measured them swapped
        result = db.get(Trial, trial_id).results[0]
        result.document = {**result.document, "cameras_swapped": True}
        db.commit()
    jobs = api.count(Job)
    same = api.client.post(url, json={"swap_cameras": True, "reason": REASON}, headers=h)
    assert same.status_code == 422 and "swapped already" in same.json()["detail"], same.text
    assert "swap_cameras: false" in same.json()["detail"] and api.count(Job) == jobs
    back = api.client.post(url, json={"swap_cameras": False, "reason": REASON}, headers=h)
    assert back.status_code == 201 and back.json()["job_id"] is not None, back.text
    with api.sessions() as db:
        payload = db.get(Job, back.json()["job_id"]).payload
    assert "swap_cameras" not in payload  # measured as stored
    assert payload["revision_request"]["change"] == {"swap_cameras": False}
    with api.sessions() as db:  # that job done: an offset alone keeps the videos swapped
        db.get(Job, back.json()["job_id"]).status = "succeeded"
        db.commit()
    offset = api.client.post(url, json={"offset_frames": 2, "reason": REASON}, headers=h)
    assert offset.status_code == 201, offset.text
    with api.sessions() as db:
        payload = db.get(Job, offset.json()["job_id"]).payload
    assert payload["swap_cameras"] is True and payload["offset_frames"] == 2.0
    assert payload["revision_request"]["change"] == {"offset_frames": 2}


def test_reanalysis_is_a_job_and_keeps_the_current_result(api: Api, video_pair) -> None:
    trial_id = _trial(api, video_pair)
    h = api.headers
    r = api.client.post(
        f"/api/v1/trials/{trial_id}/revisions",
        json={"offset_frames": 3, "reason": "the clapper shows a 3-frame offset"},
        headers=h,
    )
    assert r.status_code == 201, r.text
    assert r.json()["revision"] is None and r.json()["job_id"] is not None
    with api.sessions() as db:
        job = db.get(Job, r.json()["job_id"])
        assert job.status == "queued" and job.payload["offset_frames"] == 3.0
        assert job.payload["revision_request"]["reason"] == "the clapper shows a 3-frame offset"
        assert db.get(Trial, trial_id).status == "succeeded"  # the result stays current
    again = api.client.post(
        f"/api/v1/trials/{trial_id}/revisions",
        json={"swap_cameras": True, "reason": "second thoughts"},
        headers=h,
    )
    assert again.status_code == 409 and "already queued" in again.json()["detail"]
    assert api.client.get(f"/api/v1/trials/{trial_id}/result", headers=h).json()["revision"] == 1


def test_each_revision_is_one_audit_event(api: Api, video_pair) -> None:
    trial_id = _trial(api, video_pair)
    before = {e.id for e in api.audit_events()}
    r = api.client.post(
        f"/api/v1/trials/{trial_id}/revisions",
        json={"window_s": [0.5, 6.0], "reason": REASON},
        headers=api.headers,
    )
    assert r.status_code == 201
    new = [e for e in api.audit_events() if e.id not in before]
    assert [(e.action, e.resource_type, e.resource_id, e.outcome) for e in new] == [
        ("create", "revision", str(trial_id), "success")
    ]
    with api.sessions() as db:
        assert REASON not in " ".join(str(e.__dict__) for e in db.scalars(select(AuditEvent)))


def test_hide_and_restore_follow_the_roles(api: Api, video_pair) -> None:
    from api_support import make_api_key

    trial_id = _trial(api, video_pair)
    h = api.headers
    r = api.client.delete(
        f"/api/v1/trials/{trial_id}", params={"reason": "recorded the wrong hand"}, headers=h
    )
    assert r.status_code == 204
    assert api.client.get(f"/api/v1/trials/{trial_id}", headers=h).status_code == 404
    with api.sessions() as db:
        trial = db.get(Trial, trial_id)
        assert trial.deleted_reason == "recorded the wrong hand"
        assert trial.deleted_by == "API client hospital"

    before = {e.id for e in api.audit_events()}
    refused = api.client.post(f"/api/v1/trials/{trial_id}/restore", headers=h)
    assert refused.status_code == 403
    admin = {
        "Authorization": f"Bearer {make_api_key(api.sessions, name='admin', scopes=('admin',))}"
    }
    restored = api.client.post(f"/api/v1/trials/{trial_id}/restore", headers=admin)
    assert restored.status_code == 200 and restored.json()["id"] == trial_id
    again = api.client.post(f"/api/v1/trials/{trial_id}/restore", headers=admin)
    assert again.status_code == 404  # nothing hidden any more
    new = [e for e in api.audit_events() if e.id not in before]
    assert [(e.action, e.resource_type, e.outcome) for e in new] == [
        ("access", "route", "denied"),
        ("restore", "trial", "success"),
        ("restore", "trial", "not_found"),
    ]
    assert api.client.get(f"/api/v1/trials/{trial_id}", headers=h).status_code == 200
    # The result and its revisions came back with the trial.
    assert api.client.get(f"/api/v1/trials/{trial_id}/result", headers=h).json()["revision"] == 1


def test_a_trial_whose_analysis_failed_is_retried_as_stored(api: Api, video_pair) -> None:
    """No analysis yet (it failed, say for want of a calibration): swap_cameras false is the
    retry as stored, not 'measured as stored already' (nothing was measured)."""
    seeded = seed_recording_target(api)
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "left"},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    trial_id = int(r.json()["id"])
    with api.sessions() as db:
        for job in db.scalars(select(Job).where(Job.trial_id == trial_id)):
            job.status = "failed"
        db.get(Trial, trial_id).status = "failed"
        db.commit()
    retry = api.client.post(
        f"/api/v1/trials/{trial_id}/revisions",
        json={"swap_cameras": False, "reason": "the calibration is there now"},
        headers=api.headers,
    )
    assert retry.status_code == 201 and retry.json()["job_id"] is not None, retry.text
    with api.sessions() as db:
        payload = db.get(Job, retry.json()["job_id"]).payload
    assert "swap_cameras" not in payload

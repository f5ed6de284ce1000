"""Re-analysis revisions run by the real worker: swapped cameras, browser proxies, overlay."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from sqlalchemy import select
from test_worker import (  # noqa: F401 - a fixture
    _assert_own_proxies,
    _job,
    _trial_with_videos,
    small_recording,
)

from app.actors import ROLE_SCOPES, Actor
from app.models import Result, Trial, User, Video
from app.schemas import RevisionCreate
from app.services import revisions
from app.storage import file_sha256
from app.worker import run_worker
from core.video import probe_video

REASON = "the cables of the two cameras were plugged the other way round"


@pytest.mark.slow
def test_swapped_upload_fails_and_the_swapped_retry_measures_within_1_percent(
    app_settings,
    db_sessionmaker,
    storage,
    small_recording,  # noqa: F811 - the fixture imported above
):
    sm = db_sessionmaker
    rec = small_recording
    swapped = SimpleNamespace(
        left_video=rec.right_video, right_video=rec.left_video, rig_path=rec.rig_path
    )
    with sm() as db, db.begin():
        trial_id, job_id = _trial_with_videos(db, storage, swapped, calibrated=True)
        user = User(email="dr.swap@example.org", password_hash="x", display_name="Dr Swap")
        db.add(user)
        db.flush()
        actor = Actor(
            type="user",
            id=user.id,
            name=user.email,
            scopes=ROLE_SCOPES["clinician"],
            role="clinician",
        )
    # the analysis fails; the report job its failure queues finds no result to report
    assert run_worker(app_settings, once=True) == 2
    failed = _job(sm, job_id)
    assert failed.status == "failed" and "swapped" in failed.error  # the error suggests the retry
    with sm() as db:
        assert db.get(Trial, trial_id).status == "failed"
        originals = {v.side: (v.path, v.sha256) for v in db.scalars(select(Video))}

    with sm() as db:
        out = revisions.create_revision(
            db, actor, trial_id, RevisionCreate(reason=REASON, swap_cameras=True), storage
        )
    assert out.revision is None and out.job_id is not None
    assert run_worker(app_settings, once=True) == 2  # the re-analysis, then its PDF report
    assert _job(sm, out.job_id).status == "succeeded"

    truth = rec.truth
    with sm() as db:
        trial = db.get(Trial, trial_id)
        assert trial.status == "succeeded"
        result = db.scalars(select(Result).where(Result.trial_id == trial_id)).one()
        videos = {v.side: v for v in trial.videos}
        assert result.revision == 1 and result.kind == "analysis"
        assert result.created_by == "Dr Swap <dr.swap@example.org>" and result.reason == REASON
        doc = result.document
        overlay = json.loads(storage.absolute(result.overlay_path).read_text())
        proxies = {side: storage.absolute(v.proxy_path) for side, v in videos.items()}
        for side, (path, sha) in originals.items():  # the originals are untouched
            assert videos[side].path == path and file_sha256(storage.absolute(path)) == sha
    m = doc["metrics"]
    assert m["tap_count"] == truth["tap_count"]  # exact
    assert m["amplitude_mm_mean"] == pytest.approx(truth["amplitude_mm_mean"], rel=0.01)
    assert m["frequency_hz"] == pytest.approx(truth["frequency_hz"], rel=0.01)
    assert doc["cameras_swapped"] is True and doc["revision"] == 1
    assert doc["edits"][0]["change"] == {"swap_cameras": True}
    # The rig's left camera is the video stored as right, and its overlay says so.
    assert [(c["camera"], c["video"]) for c in overlay["cameras"]] == [
        ("left", "right"),
        ("right", "left"),
    ]
    for side, path in proxies.items():
        info = probe_video(path)
        assert info.fourcc == "h264" and info.frame_count == videos[side].frame_count
    # Written from the frames of the swapped analysis: each still shows its stored video.
    _assert_own_proxies(sm, storage, trial_id, swapped)
    # Tracked markers are drawn where the detector found them, in the right video.
    cam = overlay["cameras"][0]
    errors = [
        min(np.hypot(d[0] - p[0], d[1] - p[1]) for d in dets)
        for f, dets in enumerate(cam["detections"])
        for p in (cam["tracks"]["thumb"][f], cam["tracks"]["index"][f])
        if p is not None and dets
    ]
    assert len(errors) > len(cam["detections"]) and np.percentile(errors, 99) < 0.5  # px

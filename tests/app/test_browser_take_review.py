"""The review view of a browser take: proxies at the take's own frame times.

Chromium's MediaRecorder writes WebM with 1-ms timestamps and no frame rate; FFmpeg,
and so OpenCV, states 1000 fps for it. The camera's frames come at irregular
intervals and some are lost. The review proxies were written at 1000 fps (a 2.4-s take
lasted 0.07 s in the player, the overlay stuck on its first frames): here such a take is
measured by the real worker, and its proxies hold every frame at the take's time, the
overlay says those times, and the player's time-to-frame rule (``app/static/review.js``:
the last frame whose time is at or before the player's) finds each frame of the proxy.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from browser_takes import FPS, chromium_take, packet_times_s
from sqlalchemy import select
from test_worker import _trial_with_videos

from app.models import Job, Result, Trial
from app.worker import run_worker
from core.markers_csv import read_markers_csv
from core.video import probe_video

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def browser_take(simulated_session, tmp_path_factory):
    return chromium_take(simulated_session, tmp_path_factory.mktemp("chromium"))


def _trial(db, storage, sim, videos) -> tuple[int, int]:
    recording = SimpleNamespace(
        left_video=videos["left"], right_video=videos["right"], rig_path=sim.rig_path
    )
    return _trial_with_videos(db, storage, recording, calibrated=True)


def test_a_browser_take_is_probed_at_its_own_rate(browser_take):
    """OpenCV states 1000 fps for the take; probe_video gives its packets' rate."""
    _, videos = browser_take
    for path in videos.values():
        cap = cv2.VideoCapture(str(path))
        try:
            assert cap.get(cv2.CAP_PROP_FPS) == 1000.0  # what made the defect
        finally:
            cap.release()
        info = probe_video(path)
        assert info.fps == pytest.approx(FPS, rel=0.05)  # Hz: 1-ms rounding and jitter
        assert info.duration_s == pytest.approx(packet_times_s(path)[-1], abs=0.2)  # s


def test_review_proxies_and_overlay_keep_the_takes_frame_times(
    app_settings, db_sessionmaker, storage, browser_take
):
    sim, videos = browser_take
    with db_sessionmaker() as db, db.begin():
        trial_id, job_id = _trial(db, storage, sim, videos)
    run_worker(app_settings, once=True)
    with db_sessionmaker() as db:
        assert db.get(Job, job_id).status == "succeeded", db.get(Job, job_id).error
        trial = db.get(Trial, trial_id)
        proxies = {v.side: storage.absolute(v.proxy_path) for v in trial.videos}
        result = db.scalars(select(Result).where(Result.trial_id == trial_id)).one()
        overlay = json.loads(storage.absolute(result.overlay_path).read_text())
        table = read_markers_csv(storage.absolute(result.markers_path))
    cams = {cam["video"]: cam for cam in overlay["cameras"]}
    for side, take in videos.items():
        take_t = packet_times_s(take)
        proxy_t = packet_times_s(proxies[side])
        lost = np.flatnonzero(np.diff(take_t) > 1.5 / FPS)
        assert len(lost) >= 1, side  # the take has its gaps
        # Every frame at the take's time: the proxy lasts as long as the take.
        assert len(proxy_t) == len(take_t), side
        np.testing.assert_allclose(proxy_t, take_t, atol=2e-5)  # s: MP4's 1/90000 s ticks
        own = np.asarray(cams[side]["time_s"])
        np.testing.assert_allclose(own, take_t, atol=1e-6)  # s
        # The player's rule: the last frame whose time is at or before its time.
        half = 0.5 / FPS  # s
        for k, t in enumerate(proxy_t):
            for at in (t, t + 0.25 / FPS, t + 0.9 * np.diff(proxy_t, append=np.inf)[k]):
                assert np.searchsorted(own, min(at, t + half) + 1e-4, side="right") - 1 == k
    # The signal's times (the analysis's) and the left proxy's agree within half a frame.
    left_video = cams["left"]["video"] if cams["left"]["camera"] == "left" else "right"
    left_t = np.asarray(cams[left_video]["time_s"])
    assert np.max(np.abs(table.time_s - left_t[: len(table.time_s)])) < 0.5 / FPS  # s

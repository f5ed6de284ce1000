# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Raw elementary streams (H.264 without a container) uploaded with their timestamps files.

A raw stream states neither frame timestamps nor a frame rate; its timestamps
file (``frame,time_s``) gives both. Issue 11, section 5: only what truly cannot
be measured gets an error. So such a pair is accepted at upload (the file's rate
stands in for the missing one, as in ``bradyscope analyze --left-times``),
measured by the real worker (browser proxies included) and held to issue 11's
accuracy against the simulator's truth; the same stream without its timestamps
file is refused with the sentence that names the cause.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from api_support import Api, api, seed_recording_target  # noqa: F401 - fixtures
from sqlalchemy import select
from stream_support import raw_h264_from_mp4

from app.models import Result, Video
from app.storage import Storage
from app.worker import run_worker
from core.camera import ImageSize
from core.markers_csv import read_markers_csv
from core.simulation.kinematics import TappingScenario
from core.simulation.session import ImagingScenario, SimulatedSession, simulate_session
from core.simulation.timing import CameraTiming

pytestmark = pytest.mark.slow

SIZE = ImageSize(1280, 720)  # px
FPS = 60.0  # Hz
TAPPING = TappingScenario(duration_s=4.0, fps=FPS, hesitations=(4,))
LEFT = CameraTiming(jitter_s=0.0005, vfr=True)  # s: irregular capture times
RIGHT = CameraTiming(start_s=0.05, drift_ppm=200.0, jitter_s=0.0005, vfr=True)


def _simulated(out: Path) -> SimulatedSession:
    return simulate_session(
        out,
        seed=21,
        tapping=TAPPING,
        imaging=ImagingScenario(
            image_size=SIZE, codec="h264", left_timing=LEFT, right_timing=RIGHT
        ),
    )


def _times_csv(truth: dict[str, Any], side: str) -> bytes:
    """Each frame's capture time on its camera's own clock (what the capture page writes)."""
    stamps = 500.0 + np.asarray(truth["cameras"][side]["timestamps_s"])  # s
    lines = ["frame,time_s", *(f"{i},{t:.6f}" for i, t in enumerate(stamps))]
    return ("\n".join(lines) + "\n").encode()


def test_raw_h264_streams_with_timestamps_files_are_measured_by_the_service(
    api: Api, tmp_path: Path
) -> None:
    sim = _simulated(tmp_path / "sim")
    truth = sim.truth
    raw = {"left": tmp_path / "left.h264", "right": tmp_path / "right.h264"}
    for side, video in (("left", sim.left_video), ("right", sim.right_video)):
        n = raw_h264_from_mp4(video, raw[side])
        assert n == truth["cameras"][side]["frame_count"]
    session_id = seed_recording_target(
        api, rig_json=sim.rig_path.read_bytes(), patient_code="RAW-H264", rig_name="raw-streams"
    ).session_id

    def upload(with_times: bool):
        files = {f"{s}_video": (f"{s}.h264", raw[s].read_bytes(), "video/h264") for s in raw}
        if with_times:
            for s in raw:
                files[f"{s}_times"] = (f"{s}_times.csv", _times_csv(truth, s), "text/csv")
        return api.client.post(
            f"/api/v1/sessions/{session_id}/trials",
            data={"hand": "right"},
            files=files,
            headers=api.headers,
        )

    # Without its timestamps file a raw stream cannot be timed: one sentence naming the cause.
    refused = upload(with_times=False)
    assert refused.status_code == 415, refused.text
    detail = refused.json()["detail"]
    assert "neither frame timestamps nor a frame rate" in detail, detail
    assert "timestamps file" in detail and detail.endswith("."), detail
    assert api.recording_rows() == (0, 0, 0)  # no trial, video or job

    r = upload(with_times=True)
    assert r.status_code == 201, r.text
    body = r.json()
    for side in ("left", "right"):
        take = body["take"][side]
        assert take["time_source"] == "file", take
        assert take["frame_count"] == truth["cameras"][side]["frame_count"], take
        assert take["fps"] == pytest.approx(FPS, rel=0.01), take  # Hz

    assert run_worker(api.settings, once=True) == 2  # the analysis, then its PDF report
    storage = Storage.from_settings(api.settings)
    with api.sessions() as db:
        result = db.scalars(select(Result).where(Result.trial_id == body["id"])).one()
        doc, markers_path = result.document, result.markers_path
        videos = list(db.scalars(select(Video).where(Video.trial_id == body["id"])))
        proxies = {v.side: v.proxy_path for v in videos}
    assert doc["sync"]["time_source"] == ["file", "file"], doc["sync"]
    # The browser proxies were made too: the review view can show the raw streams.
    assert not [w for w in doc["quality"]["warnings"] if "review view" in w], doc["quality"]
    for side in ("left", "right"):
        assert proxies[side], proxies
        assert storage.absolute(proxies[side]).stat().st_size > 0

    # Positions: every left frame against the truth at its true capture time.
    table = read_markers_csv(storage.absolute(markers_path))
    names = list(truth["marker_names"])
    true_mm = np.asarray(truth["positions_mm"])[:, [names.index(x) for x in table.labels]]
    assert table.positions_mm.shape == true_mm.shape
    measured = table.status == "measured"
    err = np.linalg.norm(table.positions_mm - true_mm, axis=2)
    rms_mm = float(np.sqrt(np.mean(err[measured] ** 2)))
    assert rms_mm <= 0.08, rms_mm  # mm
    assert np.mean(measured.all(axis=1)) >= 0.95  # share of left frames (right starts 50 ms late)
    metrics = doc["metrics"]
    assert metrics["tap_count"] == truth["tap_count"]
    assert metrics["amplitude_mm_mean"] == pytest.approx(truth["amplitude_mm_mean"], rel=0.01)
    assert metrics["hesitation_count"] == len(truth["hesitations"])
    print(json.dumps({"rms_mm": rms_mm, "measured": float(np.mean(measured.all(axis=1)))}))

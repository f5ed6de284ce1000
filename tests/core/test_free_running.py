"""Acceptance of issue 11: free-running cameras measured to lab-rig accuracy, end to end.

1920x1080 60-fps H.264 recordings from the simulator (the truth is exact), each
simulated and measured by ``analyze_recording`` (as a user would) once per test
run, shared by the tests and the xdist workers (``run_once``). Bounds are the
issue's acceptance table. The issue's recordings last 10 s, as
``bench/bench_free_running.py``'s do; here the drift case (the drift is found
from the whole take) and the lost-frame case (its last loss, at 7.6 s, is not
found in an 8-s take) do, and the others last as long as their events need
(:data:`TEST_SECONDS`: the halt at tap 14 ends at 6.2 s), which keeps the suite
inside CI's 20 minutes on a slow machine.

The H.264 is x264's ``ultrafast`` preset at CRF 18: about 16 Mbit/s, a phone's rate.
The simulator's default, ``superfast``, keeps the simulated sensor noise at about
50 Mbit/s, and costs 2.6 times the CPU to simulate and measure (109 against 42 s for
the drift case on a 2-core machine; its 3D RMS 0.027 against 0.022 mm).
``bench/bench_free_running.py`` measures the default.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from detector_replay import RecordedDetector

from core.camera import ImageSize, StereoRig, read_rig
from core.metrics import compute_metrics
from core.pipeline import Analysis, analyze_recording
from core.simulation.kinematics import TappingScenario, simulate_tapping
from core.simulation.rig import default_rig
from core.simulation.session import ImagingScenario, SimulatedSession, simulate_session
from core.simulation.timing import CameraTiming

pytestmark = pytest.mark.slow

SIZE = ImageSize(1920, 1080)
TAPPING = TappingScenario(duration_s=10.0, fps=60.0, hesitations=(6,), halts=((14, 0.8),))


def _pitched_rig(degrees: float) -> StereoRig:
    """The default rig with the right camera tilted down about its own centre, so the
    markers are on rows ~f·tan(θ) apart in the two images."""
    rig = default_rig(image_size=SIZE)
    a = np.deg2rad(degrees)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    right = replace(
        rig.right,
        R_cam_from_world=rx @ rig.right.R_cam_from_world,
        t_cam_from_world_mm=rx @ rig.right.t_cam_from_world_mm,
    )
    return StereoRig(rig.left, right)


SCENARIOS: dict[str, dict[str, Any]] = {
    "drift": {"right": CameraTiming(start_s=0.237, drift_ppm=300.0)},
    "drops": {"right": CameraTiming(start_s=0.05, drop_after=(150, 310, 455))},
    "vfr": {
        "left": CameraTiming(jitter_s=0.0005, vfr=True, drop_after=(380,)),
        "right": CameraTiming(
            start_s=0.1, drift_ppm=-150.0, jitter_s=0.0005, vfr=True, drop_after=(200, 201)
        ),
    },
    "rolling": {
        "left": CameraTiming(readout_ms=15.0),
        "right": CameraTiming(readout_ms=15.0, start_s=0.02),
        "rig": _pitched_rig(6.0),
    },
    "fps120": {"right": CameraTiming(fps=60.0, start_s=0.04), "fps": 120.0},
}


#: The tests' H.264 encoder options (see above); ``bench/bench_free_running.py`` passes ().
FAST_H264 = (("preset", "ultrafast"),)
#: How long each case's recording lasts in the tests (s; the bench's last 10 s).
TEST_SECONDS = {"drift": 10.0, "drops": 10.0, "vfr": 7.0, "rolling": 7.0, "fps120": 7.0}


def tapping(name: str, duration_s: float = TAPPING.duration_s) -> TappingScenario:
    """The tapping of case ``name`` (its frame rate), lasting ``duration_s``."""
    return replace(TAPPING, fps=SCENARIOS[name].get("fps", 60.0), duration_s=duration_s)


def _simulate_and_analyze(
    name: str,
    out: Path,
    encoder_options: tuple[tuple[str, str], ...] = FAST_H264,
    detector: Any = None,
    duration_s: float | None = None,
) -> tuple[SimulatedSession, Analysis]:
    """Case ``name`` simulated into ``out`` and analysed; ``duration_s`` by default the
    tests' (:data:`TEST_SECONDS`)."""
    spec = SCENARIOS[name]
    session = simulate_session(
        out,
        seed=11,
        tapping=tapping(name, TEST_SECONDS[name] if duration_s is None else duration_s),
        imaging=ImagingScenario(
            image_size=SIZE,
            codec="h264",
            left_timing=spec.get("left", CameraTiming()),
            right_timing=spec.get("right", CameraTiming()),
            encoder_options=encoder_options,
        ),
        rig=spec.get("rig"),
    )
    return session, analyze_recording(
        read_rig(session.rig_path), session.left_video, session.right_video, detector=detector
    )


def _rolling_both_ways(out: Path) -> tuple[SimulatedSession, tuple[Analysis, Analysis]]:
    """The rolling-shutter case measured with its rig and as if the shutters were global
    (readout_ms 0). The marker search does not depend on the rig: its answers in the first
    analysis are replayed, checked call by call, in the second."""
    detections = RecordedDetector()
    session, analysis = _simulate_and_analyze("rolling", out, detector=detections.record)
    rig = read_rig(session.rig_path)
    global_rig = StereoRig(replace(rig.left, readout_ms=0.0), replace(rig.right, readout_ms=0.0))
    as_global = analyze_recording(
        global_rig, session.left_video, session.right_video, detector=detections.replay
    )
    assert detections.all_replayed(), "the second analysis searched fewer frames"
    return session, (analysis, as_global)


@pytest.fixture(scope="session")
def free_running(run_once) -> dict[str, Any]:
    """Each scenario simulated and analysed once per test run, whichever xdist worker asks
    first (``run_once`` in tests/conftest.py)."""

    def get(name: str) -> Any:
        if name == "rolling":  # (session, (analysis, analysis as if the shutters were global))
            return run_once("free-running/rolling", _rolling_both_ways)
        return run_once(f"free-running/{name}", lambda out: _simulate_and_analyze(name, out))

    return {"get": get}


def _errors(session: SimulatedSession, analysis: Analysis) -> tuple[float, float, float]:
    truth = np.asarray(session.truth["positions_mm"])[:, :2]
    measured = analysis.status == "measured"
    err = np.linalg.norm(analysis.positions_mm - truth, axis=2)
    rms = float(np.sqrt(np.mean(err[measured] ** 2)))
    both = measured.all(axis=1)
    d = np.linalg.norm(analysis.positions_mm[:, 0] - analysis.positions_mm[:, 1], axis=1)
    d_true = np.linalg.norm(truth[:, 0] - truth[:, 1], axis=1)
    d_rms = float(np.sqrt(np.mean((d - d_true)[both] ** 2)))
    return rms, d_rms, float(np.mean(both))


def _check_metrics(session: SimulatedSession, analysis: Analysis) -> None:
    truth = session.truth
    metrics = analysis.metrics.to_result()["metrics"]
    assert metrics["tap_count"] == truth["tap_count"]
    assert metrics["amplitude_mm_mean"] == pytest.approx(truth["amplitude_mm_mean"], rel=0.01)
    assert metrics["hesitation_count"] == len(truth["hesitations"])
    assert metrics["halt_count"] == len(truth["halts"])


@pytest.mark.parametrize("name", ["drift", "drops", "vfr", "fps120"])
def test_free_running_cameras_measure_to_lab_rig_accuracy(free_running, name):
    session, analysis = free_running["get"](name)
    rms, d_rms, _ = _errors(session, analysis)
    bound = 0.1 if name == "fps120" else 0.08  # mm
    assert rms <= bound, f"{name}: 3D RMS {rms:.3f} mm"
    if name != "fps120":
        assert d_rms <= 0.04, f"{name}: thumb–index distance RMS {d_rms:.3f} mm"  # mm
    _check_metrics(session, analysis)


def test_offset_and_drift_are_reported(free_running):
    session, analysis = free_running["get"]("drift")
    sync = analysis.sync
    assert abs(sync["offset_s"] - 0.237) <= 0.0005  # s
    assert abs(sync["drift_ppm"] - 300.0) <= 50  # ppm
    assert sync["offset_frames"] == pytest.approx(session.truth["offset_frames"], abs=0.05)
    assert sync["epipolar_px_after"] < sync["epipolar_px_before"]


def test_lost_frames_are_found_and_almost_every_frame_is_measured(free_running):
    session, analysis = free_running["get"]("drops")
    found = np.array(analysis.sync["dropped_frames_right"])
    truth = np.array(session.truth["cameras"]["right"]["dropped_after"])
    assert len(found) == len(truth) and np.all(np.abs(found - truth) <= 1)  # frames
    assert analysis.sync["dropped_frames_left"] == []
    _, _, both = _errors(session, analysis)
    assert both >= 0.98


def test_rolling_shutter_is_compensated_with_readout_ms(free_running, tmp_path: Path):
    session, (analysis, plain) = free_running["get"]("rolling")
    rms, _, _ = _errors(session, analysis)
    assert analysis.sync["readout_ms"] == [15.0, 15.0]
    assert rms <= 0.1, f"3D RMS {rms:.3f} mm"  # mm
    _check_metrics(session, analysis)
    # Without readout_ms the same recording is measured worse (docs/sync.md states by how much).
    assert "readout_ms" not in plain.sync  # measured as if the shutters were global
    rms_plain, _, _ = _errors(session, plain)
    assert rms_plain > 2 * rms


def test_metrics_are_measured_at_the_real_frame_times(free_running):
    """Variable frame rate with jitter and lost frames: frequency within 1 % of the truth, peak
    speeds within 3 % per tap and 1 % on average of the same tapping sampled evenly
    (docs/metrics.md §6), tap times within half a frame. Read as frame / fps, the lost left
    frame put the later taps 2 frames early and one tap's peak speed 5 % off."""
    session, analysis = free_running["get"]("vfr")
    assert analysis.metrics is not None
    got = analysis.metrics
    even = tapping("vfr", TEST_SECONDS["vfr"])
    reference = compute_metrics(simulate_tapping(even, seed=11).positions_mm[:, :2], even.fps)
    assert got.metrics["frequency_hz"] == pytest.approx(session.truth["frequency_hz"], rel=0.01)
    assert len(got.taps) == len(reference.taps) == session.truth["tap_count"]
    for key in ("opening_velocity_mm_s_max", "closing_velocity_mm_s_max"):
        assert got.metrics[key] == pytest.approx(reference.metrics[key], rel=0.01), key
        per_tap = np.array([getattr(t, key) for t in got.taps])
        per_tap_ref = np.array([getattr(t, key) for t in reference.taps])
        assert np.max(np.abs(per_tap / per_tap_ref - 1)) <= 0.03, key
    start = np.array([t.t_start_s for t in got.taps])
    start_true = np.array([t["t_start_s"] for t in session.truth["taps"]])
    assert np.max(np.abs(start - start_true)) * even.fps <= 0.5  # frames

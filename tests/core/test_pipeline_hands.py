"""analyze_recording on an IR-lit hand (issue 19 acceptance, short versions).

``bench/bench_hands.py`` runs the 10-s recordings; here 3 s of the same
scenario (mp4v, skin at a quarter of the markers' brightness, a ring glint,
3 Hz taps shrinking by 0.8 mm per tap), at 1280x1024 and at 640x512, and
the ``occlusion`` and ``overlap`` postures (the right camera looks along the
opening direction: at every closure the index fingertip hides part of the thumb
marker there, or the two markers' images merge; the latter 4 s long with a
hesitation and a halt).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core.camera import ImageSize, read_rig
from core.pipeline import Analysis, analyze_recording
from core.simulation.hand import overlap_orientation_deg
from core.simulation.kinematics import TappingScenario
from core.simulation.rig import default_rig
from core.simulation.session import ImagingScenario, SimulatedSession, simulate_session

pytestmark = pytest.mark.slow


def _hand_session(
    out: Path,
    size: ImageSize,
    *,
    overlap_mm: float | None = None,
    tapping: TappingScenario | None = None,
) -> tuple[SimulatedSession, Analysis]:
    if tapping is None:
        tapping = TappingScenario(duration_s=3.0, fps=100.0, decrement_mm_per_tap=-0.8)
    rig = None
    if overlap_mm is not None:
        rig = default_rig(image_size=size)
        turn = overlap_orientation_deg(tapping, rig.right, separation_mm=overlap_mm)
        tapping = replace(tapping, orientation_deg=turn)
    session = simulate_session(
        out,
        seed=19,
        tapping=tapping,
        rig=rig,
        imaging=ImagingScenario(
            image_size=size, codec="mp4v", skin_level=57.0, distractors_moving=1
        ),
    )
    analysis = analyze_recording(
        read_rig(session.rig_path), session.left_video, session.right_video
    )
    return session, analysis


# Each recording and its analysis is made once per test run, in whichever xdist worker
# asks first (``run_once``): the tests of one module may run in both workers.


@pytest.fixture(scope="module")
def skin(run_once: Any) -> tuple[SimulatedSession, Analysis]:
    return run_once("hands-skin", lambda out: _hand_session(out, ImageSize(1280, 1024)))


@pytest.fixture(scope="module")
def small(run_once: Any) -> tuple[SimulatedSession, Analysis]:
    return run_once("hands-small", lambda out: _hand_session(out, ImageSize(640, 512)))


@pytest.fixture(scope="module")
def overlap(run_once: Any) -> tuple[SimulatedSession, Analysis]:
    # closed marker centres 3 mm apart seen from the right camera (5-mm markers); 4 s with
    # a hesitation before tap 3 and a 0.5-s halt before tap 6, both closed (merged)
    tapping = TappingScenario(
        duration_s=4.0,
        fps=100.0,
        decrement_mm_per_tap=-0.8,
        hesitations=(3,),
        halts=((6, 0.5),),
    )
    return run_once(
        "hands-overlap",
        lambda out: _hand_session(out, ImageSize(1280, 1024), overlap_mm=3.0, tapping=tapping),
    )


@pytest.fixture(scope="module")
def occlusion(run_once: Any) -> tuple[SimulatedSession, Analysis]:
    # closed marker centres 5.5 mm apart seen from the right camera: the index fingertip
    # hides up to ~3 % of the thumb marker there, their images do not touch
    return run_once(
        "hands-occlusion", lambda out: _hand_session(out, ImageSize(1280, 1024), overlap_mm=5.5)
    )


def _errors(session: SimulatedSession, analysis: Analysis) -> tuple[np.ndarray, np.ndarray]:
    """3-D errors of measured points (mm) and distance errors where both are measured."""
    truth = np.asarray(session.truth["positions_mm"], dtype=float)[:, :2]
    meas = analysis.status == "measured"
    err = np.linalg.norm(analysis.positions_mm - truth, axis=2)
    dist = np.linalg.norm(analysis.positions_mm[:, 0] - analysis.positions_mm[:, 1], axis=1)
    dist_true = np.linalg.norm(truth[:, 0] - truth[:, 1], axis=1)
    both = np.all(meas, axis=1)
    assert np.mean(meas) > 0.95
    return err[meas], (dist - dist_true)[both]


def test_skin_and_finger_edges_1280(skin: tuple[SimulatedSession, Analysis]) -> None:
    session, analysis = skin
    err, dist = _errors(session, analysis)
    assert np.sqrt(np.mean(err**2)) <= 0.05  # mm (acceptance; the centroid gave 0.13)
    assert np.sqrt(np.mean(dist**2)) <= 0.03  # mm (acceptance; the centroid gave 0.17)
    assert err.max() <= 0.3  # mm: worst measured frame
    assert analysis.metrics is not None
    taps = session.truth["taps"]
    assert analysis.metrics.metrics["tap_count"] == len(taps)
    for got, want in zip(analysis.metrics.taps, taps, strict=True):
        assert abs(got.amplitude_mm - want["amplitude_mm"]) <= 0.01 * want["amplitude_mm"]


def test_skin_640(small: tuple[SimulatedSession, Analysis]) -> None:
    session, analysis = small
    err, _ = _errors(session, analysis)
    assert np.sqrt(np.mean(err**2)) <= 0.08  # mm (acceptance at 640x512, markers ~6 px)
    assert analysis.metrics is not None
    assert analysis.metrics.metrics["tap_count"] == len(session.truth["taps"])


def test_whole_markers_are_not_set_aside(skin: tuple[SimulatedSession, Analysis]) -> None:
    _, analysis = skin
    q = analysis.quality
    # no part of either marker is hidden in this posture: nothing may be set aside
    assert q["set_aside_frames_left"] + q["set_aside_frames_right"] <= 3
    assert q["overlap_frames"] == 0


def test_markers_merged_in_one_camera_at_closures(
    overlap: tuple[SimulatedSession, Analysis],
) -> None:
    """Where the two markers' images merge in the right camera (every closure, the start
    and the end, the closed pauses), both are measured along their rays from the left
    camera (core.merged): no identity swap, every tap and pause found, every reliable
    amplitude within 1 %."""
    session, analysis = overlap
    truth = np.asarray(session.truth["positions_mm"], dtype=float)[:, :2]
    rig = read_rig(session.rig_path)
    px = rig.right.project(truth.reshape(-1, 3)).reshape(-1, 2, 2)
    depth_mm = rig.right.to_camera(truth.reshape(-1, 3))[:, 2].reshape(-1, 2).min(axis=1)
    diam_px = float(rig.right.K[0, 0]) * session.truth["marker_diameter_mm"] / depth_mm
    merged = np.linalg.norm(px[:, 0] - px[:, 1], axis=1) < diam_px
    assert np.count_nonzero(merged) > 100  # the posture makes them merge at closures
    meas = analysis.status == "measured"
    # 0 of the merged frames were measured before core.merged
    assert np.mean(meas[merged]) >= 0.95
    assert analysis.quality["merged_measured_frames_right"] >= 0.95 * np.count_nonzero(merged)
    err = np.linalg.norm(analysis.positions_mm - truth, axis=2)
    other = np.linalg.norm(analysis.positions_mm - truth[:, ::-1], axis=2)
    assert np.count_nonzero(meas & (other < err)) == 0  # no identity swap
    assert np.sqrt(np.mean(err[meas] ** 2)) <= 0.08  # mm (acceptance)
    assert np.sqrt(np.mean(err[meas & merged[:, None]] ** 2)) <= 0.1  # mm, the merged frames
    assert analysis.metrics is not None
    taps = session.truth["taps"]
    assert analysis.metrics.metrics["tap_count"] == len(taps)
    reliable = 0
    for got, want in zip(analysis.metrics.taps, taps, strict=True):
        assert abs(got.t_start_s - want["t_start_s"]) <= 0.05  # s
        if got.reliable:
            reliable += 1
            assert abs(got.amplitude_mm - want["amplitude_mm"]) <= 0.01 * want["amplitude_mm"]
    assert reliable >= len(taps) // 2
    events = sorted(
        (e["kind"], e["tap_index"])
        for e in analysis.metrics.events
        if e["kind"] in ("hesitation", "halt")
    )
    expected = sorted(
        [("hesitation", h["tap_index"]) for h in session.truth["hesitations"]]
        + [("halt", h["tap_index"]) for h in session.truth["halts"]]
    )
    assert len(expected) == 2
    assert events == expected


def test_thumb_marker_partly_hidden_in_one_camera(
    occlusion: tuple[SimulatedSession, Analysis],
) -> None:
    """The acceptance's occlusion case, 3 s: 3D, distance and worst-frame bounds, every tap
    and its amplitude within 1 %, no identity swap (the thumb marker a few per cent behind
    the index fingertip: measured with the finger's edge in the disc fit, docs/markers.md;
    the distance RMS was 0.059 mm before it)."""
    session, analysis = occlusion
    truth = np.asarray(session.truth["positions_mm"], dtype=float)[:, :2]
    meas = analysis.status == "measured"
    err = np.linalg.norm(analysis.positions_mm - truth, axis=2)
    other = np.linalg.norm(analysis.positions_mm - truth[:, ::-1], axis=2)
    assert np.count_nonzero(meas & (other < err)) == 0  # no identity swap
    assert np.sqrt(np.mean(err[meas] ** 2)) <= 0.08  # mm (acceptance)
    assert err[meas].max() <= 0.5  # mm (acceptance: worst measured frame)
    both = np.all(meas, axis=1)
    d = np.linalg.norm(analysis.positions_mm[:, 0] - analysis.positions_mm[:, 1], axis=1)
    d_true = np.linalg.norm(truth[:, 0] - truth[:, 1], axis=1)
    assert np.sqrt(np.mean((d - d_true)[both] ** 2)) <= 0.05  # mm (acceptance)
    assert analysis.metrics is not None
    taps = session.truth["taps"]
    assert analysis.metrics.metrics["tap_count"] == len(taps)
    # every tap, reliable or not
    for got, want in zip(analysis.metrics.taps, taps, strict=True):
        assert abs(got.amplitude_mm - want["amplitude_mm"]) <= 0.01 * want["amplitude_mm"]

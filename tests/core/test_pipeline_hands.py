"""analyze_recording on an IR-lit hand (issue 19 acceptance, short versions).

``bench/bench_hands.py`` runs the 10-s recordings; here 3 s of the same
scenario (mp4v, skin at a quarter of the markers' brightness, a ring glint,
3 Hz taps shrinking by 0.8 mm per tap), at 1280x1024 and at 640x512, and
the ``occlusion`` and ``overlap`` postures (the right camera looks along the
opening direction: at every closure the index fingertip hides part of the thumb
marker there, or the two markers' images merge).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

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
    out: Path, size: ImageSize, *, overlap_mm: float | None = None
) -> tuple[SimulatedSession, Analysis]:
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


@pytest.fixture(scope="module")
def skin(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimulatedSession, Analysis]:
    return _hand_session(tmp_path_factory.mktemp("skin"), ImageSize(1280, 1024))


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimulatedSession, Analysis]:
    return _hand_session(tmp_path_factory.mktemp("small"), ImageSize(640, 512))


@pytest.fixture(scope="module")
def overlap(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimulatedSession, Analysis]:
    # closed marker centres 3 mm apart seen from the right camera (5-mm markers)
    return _hand_session(tmp_path_factory.mktemp("overlap"), ImageSize(1280, 1024), overlap_mm=3.0)


@pytest.fixture(scope="module")
def occlusion(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimulatedSession, Analysis]:
    # closed marker centres 5.5 mm apart seen from the right camera: the index fingertip
    # hides up to ~3 % of the thumb marker there, their images do not touch
    return _hand_session(
        tmp_path_factory.mktemp("occlusion"), ImageSize(1280, 1024), overlap_mm=5.5
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
    """Both markers keep their identity through every closure whose images merge in the
    right camera; those frames are interpolated (the left camera saw them), never measured;
    every tap between the first and the last closure is found."""
    session, analysis = overlap
    truth = np.asarray(session.truth["positions_mm"], dtype=float)[:, :2]
    rig = read_rig(session.rig_path)
    px = rig.right.project(truth.reshape(-1, 3)).reshape(-1, 2, 2)
    depth_mm = rig.right.to_camera(truth.reshape(-1, 3))[:, 2].reshape(-1, 2).min(axis=1)
    diam_px = float(rig.right.K[0, 0]) * session.truth["marker_diameter_mm"] / depth_mm
    merged = np.linalg.norm(px[:, 0] - px[:, 1], axis=1) < diam_px
    assert np.count_nonzero(merged) > 30  # the posture makes them merge at closures
    meas = analysis.status == "measured"
    assert not np.any(meas[merged])  # never a merged image measured
    err = np.linalg.norm(analysis.positions_mm - truth, axis=2)
    other = np.linalg.norm(analysis.positions_mm - truth[:, ::-1], axis=2)
    assert np.count_nonzero(meas & (other < err)) == 0  # no identity swap
    assert np.sqrt(np.mean(err[meas] ** 2)) <= 0.1  # mm (the thumb marker a few % hidden)
    # between the first and the last measured frame nothing is missing: the closures
    # are interpolated from the left camera (the recording starts and ends closed)
    both = np.flatnonzero(meas.all(axis=1))
    inner = np.arange(both.min(), both.max())
    assert np.all(analysis.status[inner] != "missing")
    assert analysis.quality["overlap_frames"] >= np.count_nonzero(merged[inner])
    assert analysis.metrics is not None
    taps = session.truth["taps"]
    found = analysis.metrics.metrics["tap_count"]
    # all but the first and the last: the recording starts and ends closed, merged in the
    # right camera, so the first opening has no closure before it and the last none after
    # it (no measured frame on the far side to interpolate from; 0 of 6 before issue 19)
    assert len(taps) - 2 <= found <= len(taps)


def test_thumb_marker_partly_hidden_in_one_camera(
    occlusion: tuple[SimulatedSession, Analysis],
) -> None:
    """The acceptance's occlusion case, 3 s: 3D and worst-frame bounds, every tap and its
    amplitude within 1 %, no identity swap. The distance bound (0.05 mm) is not met
    (0.059 mm here, 0.058 mm on the 10-s recording, docs/markers.md): guarded at its
    current level, not at the acceptance."""
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
    assert np.sqrt(np.mean((d - d_true)[both] ** 2)) <= 0.07  # mm (acceptance 0.05: open)
    assert analysis.metrics is not None
    taps = session.truth["taps"]
    assert analysis.metrics.metrics["tap_count"] == len(taps)
    # every tap, reliable or not (here none is reliable: each has an interpolated closure)
    for got, want in zip(analysis.metrics.taps, taps, strict=True):
        assert abs(got.amplitude_mm - want["amplitude_mm"]) <= 0.01 * want["amplitude_mm"]

"""Kinematic models of hand movements, pronation–supination, toe tapping and leg agility, with ground truth.

The same cycle timeline as finger tapping (:func:`core.simulation.kinematics.build_timeline`:
cycles with rhythm jitter, amplitude decrement and jitter, hesitations and halts
inserted before a cycle at its resting end) drives each task's geometry
(``docs/simulator.md``), with the markers of its protocol (``docs/protocols.md``):

- **hand movements**: the ``finger`` marker (back of the middle phalanx of the
  middle finger) turns about the knuckles (MCP joint) in the hand's flexion
  plane; its angle is solved in closed form so that the finger–wrist distance
  is *exactly* ``closed_distance + o(t)``. The ``wrist`` marker sits on the
  back of the wrist and shakes a little with the effort (1.5 mm along the hand
  per cycle).
- **pronation–supination**: the hand turns about the forearm axis by
  ``o(t)`` degrees from the pronated rest (palm down), carrying the rigid
  three-marker cluster (``core.protocols.PS_CLUSTER_MM``) on 40-mm posts.
- **toe tapping**: the foot turns about the heel's contact with the floor (a
  lateral axis) by ``o(t) / L`` radians, ``L`` the heel–toe marker distance,
  so the toe marker travels an arc of exactly ``o(t)`` mm; the ``shin`` marker
  stays with the leg.
- **leg agility**: the thigh turns up about the hip's flexion axis (lateral,
  through the hip joint) by ``o(t)`` degrees, carrying the ``thigh`` and
  ``knee`` markers; the knee opens as the foot rises (the shank turns by
  ``(1 - LA_KNEE_OPENING) o(t)``), carrying the ``ankle`` marker.

Every model drifts slowly as a whole (translations; a small rotation of the
hand for hand movements, none that would change the measured angle for the
others). Each marker carries a surface normal: a camera that sees the marker's
mount from behind (more than ``HIDDEN_BEYOND_DEG`` from its normal, 100 degrees;
``HIDDEN_BEYOND_DEG_ON_POST``, 120, for the spheres on posts of 3.6) does not
see the marker — the occlusions the movement itself causes (the fist turns the
finger marker away, the turning hand carries the cluster round).

World frame: the rig's (left camera: x right, y down, z forward, mm). A left
hand is a right one mirrored in its own frame (radial and ulnar exchanged; it
still points at the rig); a left foot or leg is the scene mirrored about the
centre's x (the rig films its lateral side from the patient's left).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core.protocols import PS_CLUSTER_MM, protocol_for
from core.simulation.kinematics import (
    PauseTruth,
    _rotations,
    _Timeline,
    build_timeline,
    cycle_frames,
    least_squares_slope,
    timeline_opening,
)
from core.tasks import Task

FloatArray = NDArray[np.float64]

#: A marker is hidden from a camera seeing its mount this far (or farther) from its normal:
#: a marker on the skin; a sphere on a post (the cluster of 3.6) is seen from farther round.
HIDDEN_BEYOND_DEG = 100.0
HIDDEN_BEYOND_DEG_ON_POST = 120.0

# Hand movements (mm, hand frame: u distal along the middle finger, v radial, w dorsal,
# origin at the middle finger's MCP joint).
HM_FINGER_RADIUS_MM = 62.0  # MCP joint to the finger marker (on the middle phalanx)
HM_WRIST_LOCAL_MM = np.array([-80.0, 0.0, 15.0])  # back of the wrist
_HM_WRIST_SHAKE_MM = 1.5  # the wrist moves along the hand with the effort
# Pronation–supination (forearm frame: u distal along the forearm, v radial at rest, w dorsal).
PS_POST_MM = 35.0  # the radial marker above the forearm axis (the others higher)
PS_CLUSTER_AT_U_MM = 70.0  # the cluster's origin, distal of the wrist along the axis
# Toe tapping (foot frame: origin at the heel's contact with the floor, u forwards along
# the foot, w up; the markers on the lateral side, in one plane across which the foot turns.
# the foot, v = w x u, points medially for a right foot: the lateral side is -v.
TT_TOE_LOCAL_MM = np.array([185.0, -35.0, 40.0])  # lateral forefoot, over the 5th metatarsal head
TT_HEEL_LOCAL_MM = np.array([-5.0, -35.0, 35.0])  # lateral heel
TT_SHIN_LOCAL_MM = np.array([60.0, -35.0, 230.0])  # lateral lower leg
# Leg agility (leg frame: origin at the hip joint, u forwards along the thigh of the
# seated patient, w up, lateral -v as for the foot). The thigh and knee markers sit at
# the same depth across the leg (docs/protocols.md).
LA_KNEE_JOINT_MM = np.array([430.0, 0.0, 0.0])
LA_KNEE_LOCAL_MM = np.array([430.0, -60.0, 0.0])  # lateral femoral epicondyle
LA_THIGH_LOCAL_MM = np.array([200.0, -60.0, 15.0])  # lateral thigh, towards the trochanter
LA_ANKLE_FROM_KNEE_MM = np.array([30.0, -45.0, -410.0])  # lateral malleolus, shank hanging
#: The knee opens by this fraction of the thigh's rise (the foot comes up and forwards).
LA_KNEE_OPENING = 0.6

_DEFAULTS: dict[Task, dict[str, Any]] = {
    Task.HAND_MOVEMENTS: {
        "amplitude": 40.0,
        "frequency_hz": 1.5,
        "closed": 92.0,
        "centre": (0.0, 0.0, 500.0),
    },
    Task.PRONATION_SUPINATION: {
        "amplitude": 150.0,
        "frequency_hz": 1.2,
        "closed": 0.0,
        "centre": (0.0, 0.0, 500.0),
    },
    Task.TOE_TAPPING: {
        "amplitude": 40.0,
        "frequency_hz": 2.5,
        "closed": 0.0,
        "centre": (0.0, 60.0, 800.0),
    },
    Task.LEG_AGILITY: {
        "amplitude": 30.0,
        "frequency_hz": 1.6,
        "closed": 0.0,
        "centre": (50.0, 60.0, 1000.0),
    },
}
#: The largest first amplitude a scenario may ask for (task unit).
_LIMITS = {
    Task.HAND_MOVEMENTS: 45.0,
    Task.PRONATION_SUPINATION: 200.0,
    Task.TOE_TAPPING: 80.0,
    Task.LEG_AGILITY: 50.0,
}
#: Tasks filmed from the limb's lateral side: a left limb is the whole scene mirrored.
_LATERAL_VIEW = (Task.TOE_TAPPING, Task.LEG_AGILITY)


def rig_geometry(task: Task | str) -> RigGeometry:
    """The simulated rig's ``baseline_mm`` and ``convergence_mm`` for ``task``
    (:func:`core.simulation.rig.default_rig`): toe tapping films the foot from 800 mm with
    a 400-mm baseline (lower and wider, docs/protocols.md), leg agility the seated leg from
    1000 mm with a 700-mm baseline; the hand tasks as finger tapping."""
    if Task(task) is Task.TOE_TAPPING:
        return RigGeometry(400.0, 800.0)
    if Task(task) is Task.LEG_AGILITY:
        return RigGeometry(700.0, 1000.0)
    return RigGeometry(250.0, 500.0)


class RigGeometry(NamedTuple):
    """Baseline and convergence distance of a simulated rig (mm)."""

    baseline_mm: float
    convergence_mm: float


@dataclass(frozen=True)
class TaskScenario:
    """What the simulated patient does in one task (not finger tapping).

    Attributes
    ----------
    task : Task
    duration_s, fps : float
        Length (s) and frame rate (Hz) of the truth.
    amplitude : float, optional (NaN: the task's default)
        The first cycle's amplitude in the task's unit (mm; degrees for
        pronation–supination and leg agility); default 40 mm, 150 degrees, 40 mm,
        30 degrees.
    frequency_hz : float, optional
        Cycles per second while moving; default 1.5, 1.2, 2.5, 1.6 Hz.
    decrement_per_cycle : float
        Planned change of the amplitude per cycle (task unit, negative = shrinking).
    rhythm_jitter, amplitude_jitter : float
        Coefficients of variation of the cycle durations and amplitudes.
    hesitations : tuple of int
        Cycles preceded by a pause of ``hesitation_s`` at the resting end.
    hesitation_s : float
    halts : tuple of (int, float)
        ``(cycle, duration_s)`` freezes (at least 0.3 s) before a cycle.
    drift_mm : float
        Amplitude of the slow drift of the whole limb (mm).
    side : {"right", "left"}
    closed_distance_mm : float, optional
        Hand movements: the finger–wrist distance in the fist (mm), default 92.
    centre_mm : tuple of 3 floats, optional
        Where the markers' middle is at rest (world frame, mm).
    """

    task: Task = Task.HAND_MOVEMENTS
    duration_s: float = 6.0
    fps: float = 100.0
    amplitude: float = math.nan
    frequency_hz: float = math.nan
    decrement_per_cycle: float = 0.0
    rhythm_jitter: float = 0.03
    amplitude_jitter: float = 0.0
    hesitations: tuple[int, ...] = ()
    hesitation_s: float = 0.25
    halts: tuple[tuple[int, float], ...] = ()
    drift_mm: float = 3.0
    side: str = "right"
    closed_distance_mm: float = math.nan
    centre_mm: tuple[float, float, float] = (math.nan, math.nan, math.nan)

    def __post_init__(self) -> None:
        task = Task(self.task)
        object.__setattr__(self, "task", task)
        if task is Task.FINGER_TAPPING:
            raise ValueError("finger tapping is simulated by core.simulation.kinematics")
        d = _DEFAULTS[task]
        # NaN (the default) stands for the task's default.
        if math.isnan(self.amplitude):
            object.__setattr__(self, "amplitude", float(d["amplitude"]))
        if math.isnan(self.frequency_hz):
            object.__setattr__(self, "frequency_hz", float(d["frequency_hz"]))
        if math.isnan(self.closed_distance_mm):
            object.__setattr__(self, "closed_distance_mm", float(d["closed"]))
        if any(math.isnan(v) for v in self.centre_mm):
            object.__setattr__(self, "centre_mm", tuple(float(v) for v in d["centre"]))
        object.__setattr__(self, "hesitations", tuple(int(k) for k in self.hesitations))
        object.__setattr__(self, "halts", tuple((int(k), float(s)) for k, s in self.halts))
        if not (self.duration_s > 0 and self.fps > 0):
            raise ValueError(
                f"duration_s and fps must be positive, got {self.duration_s}, {self.fps}"
            )
        if not 0 < self.frequency_hz <= 6 or self.fps < 4 * self.frequency_hz:
            raise ValueError(
                f"frequency_hz must be in (0, 6] and at most fps / 4, got {self.frequency_hz}"
            )
        limit = _LIMITS
        if not 0 < self.amplitude <= limit[task]:
            raise ValueError(
                f"amplitude must be in (0, {limit[task]:g}] {task.amplitude_unit} for {task.value},"
                f" got {self.amplitude}"
            )
        if not (0 <= self.rhythm_jitter <= 0.3 and 0 <= self.amplitude_jitter <= 0.3):
            raise ValueError("rhythm_jitter and amplitude_jitter must be in [0, 0.3]")
        if any(k < 1 for k in self.hesitations) or any(k < 1 for k, _ in self.halts):
            raise ValueError(
                "hesitation and halt cycle indices must be >= 1 (a pause between cycles)"
            )
        if any(s < 0.3 for _, s in self.halts):
            raise ValueError(f"a halt lasts at least 0.3 s, got {self.halts}")
        if not 0 <= self.drift_mm <= 30:
            raise ValueError(f"drift_mm must be in [0, 30], got {self.drift_mm}")
        if self.side not in ("right", "left"):
            raise ValueError(f"side must be 'right' or 'left', got {self.side!r}")
        if task is Task.HAND_MOVEMENTS:
            lo, hi = _hm_distance_range()
            top = self.closed_distance_mm + self.amplitude * (1 + 3 * self.amplitude_jitter)
            if not (lo <= self.closed_distance_mm and top <= hi):
                raise ValueError(
                    f"the fist ({self.closed_distance_mm} mm) and opening ({self.amplitude} mm)"
                    f" must stay within the finger's reach, {lo:.0f}-{hi:.0f} mm from the wrist"
                )

    # The TimelineSpec of core.simulation.kinematics (amplitudes in the task's unit).
    @property
    def amplitude_mm(self) -> float:
        return self.amplitude

    @property
    def decrement_mm_per_tap(self) -> float:
        return self.decrement_per_cycle

    @property
    def marker_names(self) -> tuple[str, ...]:
        return protocol_for(self.task).labels


def _hm_distance_range() -> tuple[float, float]:
    """Finger–wrist distances the hand model reaches (mm): flexed 120 degrees to straight."""
    rho = HM_FINGER_RADIUS_MM
    w = float(np.linalg.norm(HM_WRIST_LOCAL_MM))
    return float(np.sqrt(rho**2 + w**2 + 2 * rho * w * np.cos(np.deg2rad(120.0)))), rho + w


@dataclass(frozen=True)
class TaskModel:
    """The continuous-time model of a task trial (marker positions and normals at any time)."""

    scenario: TaskScenario
    timeline: _Timeline
    R_world_from_body: FloatArray  # (3, 3)
    origin_world_mm: FloatArray  # (3,)
    drift_freqs_hz: FloatArray  # (6,)
    drift_phases: FloatArray  # (6,)
    drift_amps: FloatArray  # (6,): mm for translations, radians for rotations

    @property
    def _mirror_body(self) -> bool:
        """A left hand is a right one mirrored in its own frame (it keeps pointing at the rig);
        a left foot or leg is the whole scene mirrored (the rig films its lateral side)."""
        return self.scenario.side == "left" and self.scenario.task not in _LATERAL_VIEW

    def opening(self, t_s: ArrayLike) -> FloatArray:
        """``o(t)`` in the task's unit (0 at the resting end), same shape as ``t_s``."""
        return timeline_opening(self.timeline, t_s)

    def angle_deg(self, t_s: ArrayLike) -> FloatArray:
        """Pronation–supination: the true supination angle from the pronated rest (degrees)."""
        return self.opening(t_s)

    def positions_mm(self, t_s: ArrayLike) -> FloatArray:
        """Marker centres ``(N, M, 3)`` in the world frame (mm), markers in protocol order."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        local, _ = self._local(t)
        return self._to_world(t, local)

    def normals(self, t_s: ArrayLike) -> FloatArray:
        """The markers' outward mount normals ``(N, M, 3)`` in the world frame (unit)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        _, normals = self._local(t)
        world = self._to_world(t, normals, directions=True)
        result: FloatArray = world / np.linalg.norm(world, axis=2, keepdims=True)
        return result

    def hidden_from(self, centre_mm: FloatArray, t_s: ArrayLike) -> NDArray[np.bool_]:
        """``(N, M)``: markers whose mount a camera at ``centre_mm`` sees from behind."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        pos = self.positions_mm(t)
        view = np.asarray(centre_mm, dtype=np.float64)[None, None] - pos
        view /= np.linalg.norm(view, axis=2, keepdims=True)
        cos = np.sum(view * self.normals(t), axis=2)
        on_post = self.scenario.task is Task.PRONATION_SUPINATION
        limit = HIDDEN_BEYOND_DEG_ON_POST if on_post else HIDDEN_BEYOND_DEG
        result: NDArray[np.bool_] = cos < np.cos(np.deg2rad(limit))
        return result

    def hand_points_mm(self, t_s: ArrayLike, local_points_mm: ArrayLike) -> FloatArray:
        """World positions ``(N, P, 3)`` of points fixed to the limb (moving with its drift)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        pts = np.asarray(local_points_mm, dtype=np.float64)
        return self._to_world(t, np.broadcast_to(pts, (len(t), *pts.shape)))

    # -- geometry --------------------------------------------------------------------
    def _local(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        s = self.scenario
        o = self.opening(t)
        n = len(t)
        if s.task is Task.HAND_MOVEMENTS:
            d = s.closed_distance_mm + o
            rho = HM_FINGER_RADIUS_MM
            w = HM_WRIST_LOCAL_MM
            wn = float(np.linalg.norm(w))
            beta = float(np.arctan2(w[2], w[0]))
            # |C(psi) - W|^2 = rho^2 + |W|^2 - 2 rho |W| cos(psi - beta); the finger is
            # flexed palmwards (psi below beta - 180 degrees).
            cos_arg = np.clip((rho**2 + wn**2 - d * d) / (2 * rho * wn), -1.0, 1.0)
            psi = beta - 2 * np.pi + np.arccos(cos_arg)
            finger = np.column_stack([rho * np.cos(psi), np.zeros(n), rho * np.sin(psi)])
            shake = _HM_WRIST_SHAKE_MM * (o / max(s.amplitude_mm, 1e-9))
            wrist = np.broadcast_to(w, (n, 3)) + shake[:, None] * np.array([1.0, 0.0, 0.0])
            n_finger = np.column_stack([-np.sin(psi), np.zeros(n), np.cos(psi)])
            n_wrist = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (n, 3))
            return np.stack([finger, wrist], axis=1), np.stack([n_finger, n_wrist], axis=1)
        if s.task is Task.PRONATION_SUPINATION:
            # v = w x u points ulnar for a right hand (palm down, looking distally the
            # thumb is on the left): the cluster's radial x is -v.
            local = np.array(
                [
                    [PS_CLUSTER_AT_U_MM + y, -x, PS_POST_MM + z]
                    for x, y, z in (PS_CLUSTER_MM[k] for k in protocol_for(s.task).labels)
                ]
            )
            # A right hand supinates by a positive turn about -u: the radial side (-v)
            # turns towards the back of the hand (w).
            R = _rotations(np.deg2rad(o)[:, None] * np.array([-1.0, 0.0, 0.0])[None])
            pts = np.einsum("nij,mj->nmi", R, local)
            radial = local * np.array([0.0, 1.0, 1.0])  # normals: away from the forearm axis
            radial /= np.linalg.norm(radial, axis=1, keepdims=True)
            normals = np.einsum("nij,mj->nmi", R, radial)
            return pts, normals
        if s.task is Task.LEG_AGILITY:
            return _leg(o)
        # Toe tapping: the foot turns up about the lateral axis v through the origin.
        length = float(np.linalg.norm(TT_TOE_LOCAL_MM - TT_HEEL_LOCAL_MM))
        phi = o / length
        R = _rotations(phi[:, None] * np.array([0.0, -1.0, 0.0])[None])  # toe up (+w)
        toe = R @ TT_TOE_LOCAL_MM
        heel = R @ TT_HEEL_LOCAL_MM
        shin = np.broadcast_to(TT_SHIN_LOCAL_MM, (n, 3))
        lateral_up = np.array([0.0, -1.0, 0.4]) / np.linalg.norm([0.0, -1.0, 0.4])
        normals = np.stack(
            [R @ lateral_up, R @ lateral_up, np.broadcast_to(lateral_up, (n, 3))], axis=1
        )
        return np.stack([toe, heel, shin], axis=1), normals

    def _to_world(
        self, t: FloatArray, local: FloatArray, *, directions: bool = False
    ) -> FloatArray:
        phase = 2 * np.pi * self.drift_freqs_hz[None] * t[:, None] + self.drift_phases[None]
        sig = self.drift_amps[None] * np.sin(phase)  # (N, 6)
        R_drift = _rotations(sig[:, 3:])
        if self._mirror_body:
            local = local * np.array([1.0, -1.0, 1.0])
        rotated = np.einsum("nij,nmj->nmi", R_drift, local)
        world = rotated @ self.R_world_from_body.T
        if not directions:
            world = world + self.origin_world_mm + sig[:, None, :3]
        if self.scenario.side == "left" and not self._mirror_body:
            world = world.copy()
            if directions:
                world[..., 0] = -world[..., 0]
            else:
                world[..., 0] = 2 * self.scenario.centre_mm[0] - world[..., 0]
        result: FloatArray = world
        return result


def _leg(o_deg: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Leg agility's markers (knee, thigh, ankle) and normals in the leg frame: the thigh
    turned up by ``o_deg`` about the hip's lateral axis, the shank by a part of it."""
    n = len(o_deg)
    up = np.array([0.0, -1.0, 0.0])[None]  # about -v: u turns towards w (the knee rises)
    R_thigh = _rotations(np.deg2rad(o_deg)[:, None] * up)
    R_shank = _rotations(np.deg2rad((1.0 - LA_KNEE_OPENING) * o_deg)[:, None] * up)
    knee = R_thigh @ LA_KNEE_LOCAL_MM
    thigh = R_thigh @ LA_THIGH_LOCAL_MM
    ankle = R_thigh @ LA_KNEE_JOINT_MM + R_shank @ LA_ANKLE_FROM_KNEE_MM
    lateral = np.broadcast_to(np.array([0.0, -1.0, 0.0]), (n, 3))  # the axis: unturned
    normals = np.stack([lateral, lateral, lateral], axis=1)
    return np.stack([knee, thigh, ankle], axis=1), normals


@dataclass(frozen=True)
class CycleTruth:
    """One true cycle: from the resting end through the turn back to rest.

    ``amplitude`` (task unit) is measured on the sampled truth (frames
    ``frame_start`` .. ``frame_end``), as the measurement defines it;
    ``amplitude_model`` is the model's.
    """

    index: int
    t_start_s: float
    t_turn_s: float
    t_end_s: float
    amplitude: float
    amplitude_model: float
    frame_start: int
    frame_end: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "t_start_s": self.t_start_s,
            "t_turn_s": self.t_turn_s,
            "t_end_s": self.t_end_s,
            "amplitude": self.amplitude,
            "amplitude_model": self.amplitude_model,
            "frame_start": self.frame_start,
            "frame_end": self.frame_end,
        }


@dataclass(frozen=True)
class TaskTruth:
    """Ground truth of one simulated task trial, sampled at the frames (see :class:`TaskModel`)."""

    t_s: FloatArray
    positions_mm: FloatArray
    marker_names: tuple[str, ...]
    signal: FloatArray
    cycles: tuple[CycleTruth, ...]
    frequency_hz: float
    decrement_per_cycle: float
    hesitations: tuple[PauseTruth, ...]
    halts: tuple[PauseTruth, ...]
    fps: float
    model: TaskModel = field(repr=False, compare=False)

    @property
    def task(self) -> Task:
        return self.model.scenario.task

    def to_dict(self) -> dict[str, Any]:
        """The kinematic part of ``truth.json`` (``docs/simulator.md``)."""
        s = self.model.scenario
        amps = [c.amplitude for c in self.cycles]
        return {
            "task": s.task.value,
            "fps": self.fps,
            "frame_count": len(self.t_s),
            "hand": s.side,
            "side": s.side,
            "marker_names": list(self.marker_names),
            "positions_mm": self.positions_mm.tolist(),
            "signal": self.signal.tolist(),
            "amplitude_unit": s.task.amplitude_unit,
            "cycle_count": len(self.cycles),
            "tap_count": len(self.cycles),
            "frequency_hz": self.frequency_hz,
            "amplitude_mean": float(np.mean(amps)) if amps else None,
            "decrement_per_cycle": self.decrement_per_cycle,
            "cycles": [c.to_dict() for c in self.cycles],
            "hesitations": [p.to_dict() for p in self.hesitations],
            "halts": [p.to_dict() for p in self.halts],
            "scenario": {
                "task": s.task.value,
                "duration_s": s.duration_s,
                "fps": s.fps,
                "amplitude": s.amplitude,
                "frequency_hz": s.frequency_hz,
                "decrement_per_cycle": s.decrement_per_cycle,
                "rhythm_jitter": s.rhythm_jitter,
                "amplitude_jitter": s.amplitude_jitter,
                "hesitations": list(s.hesitations),
                "hesitation_s": s.hesitation_s,
                "halts": [list(h) for h in s.halts],
                "drift_mm": s.drift_mm,
                "side": s.side,
                "closed_distance_mm": s.closed_distance_mm,
                "centre_mm": list(s.centre_mm),
            },
        }


def _unit(v: ArrayLike) -> FloatArray:
    a = np.asarray(v, dtype=np.float64)
    result: FloatArray = a / np.linalg.norm(a)
    return result


def _body_rotation(task: Task) -> FloatArray:
    """``R_world_from_body`` of the task's posture (columns u, v, w)."""
    if task is Task.HAND_MOVEMENTS:
        # Filmed from the front and above the hand: fingers to the image's right and
        # towards the cameras, the back of the hand facing the cameras and up.
        u = _unit([1.0, 0.0, -0.3])
        w_hint = _unit([0.0, -0.5, -1.0])
    elif task is Task.PRONATION_SUPINATION:
        # The forearm points at the rig (the cameras look along it), palm down at rest.
        u = _unit([0.25, 0.0, -0.97])  # at the middle of the two cameras
        w_hint = np.array([0.0, -1.0, 0.0])
    else:
        # The foot (or the seated leg) filmed from its lateral side: toes (the knee) to
        # the image's right, slightly away; up is -y.
        u = _unit([1.0, 0.0, 0.15])
        w_hint = np.array([0.0, -1.0, 0.0])
    w = w_hint - (w_hint @ u) * u
    w /= np.linalg.norm(w)
    v = np.cross(w, u)
    return np.column_stack([u, v, w])


def _sampled_amplitudes(signal: FloatArray, frames: list[tuple[int, int]]) -> FloatArray:
    out = np.empty(len(frames))
    for i, (f0, f1) in enumerate(frames):
        out[i] = np.max(signal[f0 : f1 + 1]) - signal[f0]
    return out


def true_signal(model: TaskModel, t_s: ArrayLike) -> FloatArray:
    """The task's cycle signal from the model alone (task unit): finger–wrist distance
    (hand movements), supination angle (pronation–supination), toe arc (toe tapping), rise
    of the thigh (leg agility)."""
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    s = model.scenario
    if s.task is Task.HAND_MOVEMENTS:
        pos = model.positions_mm(t)
        result: FloatArray = np.linalg.norm(pos[:, 0] - pos[:, 1], axis=1)
        return result
    return model.opening(t)


def simulate_task(scenario: TaskScenario, *, seed: int) -> TaskTruth:
    """Simulate one trial of a task other than finger tapping and return its ground truth.

    Parameters
    ----------
    scenario : TaskScenario
    seed : int
        Seed of the rhythm, amplitudes and drift (same seed, same truth).

    Returns
    -------
    TaskTruth
        Trajectories at ``i / fps``, the true cycle signal per frame, the cycles
        (amplitudes from the sampled signal: maximum in the cycle minus the
        value at its start frame), frequency, decrement, pauses and the model.
    """
    if not isinstance(scenario, TaskScenario):
        raise ValueError(f"scenario must be a TaskScenario, got {type(scenario).__name__}")
    rng = np.random.default_rng([int(seed), 0x7A5C, list(Task).index(scenario.task)])
    timeline, hes, halts = build_timeline(scenario, rng)
    freqs = rng.uniform(0.05, 0.3, size=6)
    phases = rng.uniform(0, 2 * np.pi, size=6)
    amps = np.zeros(6)
    amps[:3] = scenario.drift_mm * np.array([1.0, 1.0, 0.6])
    if scenario.task is Task.HAND_MOVEMENTS:
        amps[3:] = np.deg2rad(1.0) * scenario.drift_mm / 3.0  # wrist wobble: distances unchanged
    R = _body_rotation(scenario.task)
    # A scene mirrored as a whole (left foot) is placed as the right one, then mirrored.
    placed = replace(scenario, side="right") if scenario.task in _LATERAL_VIEW else scenario
    probe = TaskModel(placed, timeline, R, np.zeros(3), freqs, phases, np.zeros(6))
    rest = probe.positions_mm(np.array([-10.0]))[0]  # before the first cycle: at rest
    origin = np.asarray(scenario.centre_mm, dtype=np.float64) - rest.mean(axis=0)
    model = TaskModel(scenario, timeline, R, origin, freqs, phases, amps)

    n_frames = round(scenario.duration_s * scenario.fps)
    fps = scenario.fps
    t_s = np.arange(n_frames) / fps
    positions = model.positions_mm(t_s)
    signal = true_signal(model, t_s)
    frames = cycle_frames(timeline, fps, n_frames)
    amplitudes = _sampled_amplitudes(signal, frames) if frames else np.zeros(0)
    cycles = tuple(
        CycleTruth(
            index=k,
            t_start_s=float(timeline.t_start_s[k]),
            t_turn_s=float(timeline.t_peak_s[k]),
            t_end_s=float(timeline.t_end_s[k]),
            amplitude=float(amplitudes[k]),
            amplitude_model=float(timeline.amplitude_mm[k]),
            frame_start=frames[k][0],
            frame_end=frames[k][1],
        )
        for k in range(len(frames))
    )
    durations = timeline.t_end_s - timeline.t_start_s
    for arr in (t_s, positions, signal):
        arr.setflags(write=False)
    return TaskTruth(
        t_s=t_s,
        positions_mm=positions,
        marker_names=scenario.marker_names,
        signal=signal,
        cycles=cycles,
        frequency_hz=float(1.0 / np.mean(durations)) if len(durations) else 0.0,
        decrement_per_cycle=least_squares_slope(amplitudes),
        hesitations=tuple(hes),
        halts=tuple(halts),
        fps=fps,
        model=model,
    )


__all__ = [
    "CycleTruth",
    "TaskModel",
    "TaskScenario",
    "TaskTruth",
    "rig_geometry",
    "simulate_task",
    "true_signal",
]

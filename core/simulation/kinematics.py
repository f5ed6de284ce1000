"""Kinematic model of the finger-tapping test (MDS-UPDRS 3.4) with exact ground truth.

The model (equations in ``docs/simulator.md``):

1. A timeline of taps. Tap ``k`` starts at a closure (fingers touching),
   opens for ``tau_open``, closes for ``tau_close`` and ends at the next
   closure. Cycle durations vary with ``rhythm_jitter``; a hesitation or a
   halt inserts a pause, fingers closed, before its tap.
2. An *opening* signal ``o(t) >= 0`` (mm): ``A_k * S((t - t0) / tau_open)``
   while opening and ``A_k * (1 - S((t - t_peak) / tau_close))`` while
   closing, with the smootherstep ``S(x) = 6x^5 - 15x^4 + 10x^3``, whose first
   and second derivatives vanish at both ends, so the motion is C2 everywhere
   (also across pauses).
3. Geometry in a hand frame (u distal along the index, v radial / "up",
   w = u x v dorsal), origin at the index MCP joint: the thumb-tip marker moves a
   little (15 % of the opening, mostly down); the index-tip marker lies on a
   circle of radius ``INDEX_LENGTH_MM`` about the MCP joint, and its angle is
   solved in closed form so that the thumb-index distance is *exactly*
   ``closed_distance_mm + o(t)``. The aperture the metrics measure is thus the
   model's aperture, not an approximation of it.
4. The hand frame moves rigidly (slow drift: translation plus a small rotation
   about the MCP joint), which leaves every marker distance unchanged.

World frame: the rig's, i.e. the left camera's (x right, y down, z forward, mm).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

MARKER_NAMES = ("thumb", "index")
HAND_MARKER_NAME = "hand"

# Hand geometry (mm, radians), in the hand frame of a right hand: u distal along the
# index, v radial ("up", towards the thumb side), w = u x v dorsal (the back of the hand).
INDEX_LENGTH_MM = 85.0  # MCP joint to the index-nail marker centre
_INDEX_CLOSED_ANGLE_RAD = np.deg2rad(-15.0)  # index angle above u when the fingers touch
_THUMB_FROM_INDEX_DIR = np.array([-0.10, -0.93, -0.35])  # closed thumb marker (palmar of index)
_THUMB_MOTION_PER_MM = np.array([-0.03, -0.15, -0.02])  # thumb displacement per mm of opening
_HAND_MARKER_LOCAL_MM = np.array([-40.0, -20.0, 15.0])  # back of the hand, behind the knuckles
# Orientation of the right hand in the world frame (the rig films it from the
# patient's right, seeing the back of the hand): the fingers point to the image's
# right (forwards), slightly down and towards the cameras; the index opens upwards (-y).
_RIGHT_HAND_U = np.array([1.0, 0.12, -0.35])
_RIGHT_HAND_V_HINT = np.array([0.0, -1.0, 0.0])
# The long axis of the hand and forearm (hand frame, mm): a turn (``TappingScenario.turns``)
# rolls the hand about the line through this point along u, as the forearm does.
ROLL_AXIS_POINT_MM = (0.0, -35.0, -5.0)

# Timeline constants (s).
_LEAD_IN_S = 0.5  # fingers closed and still before the first tap
_TAIL_S = 0.3  # fingers closed and still after the last tap
_OPEN_FRACTION = 0.5  # mean share of a cycle spent opening
_OPEN_FRACTION_SD = 0.03
_MIN_AMPLITUDE_MM = 2.0
MIN_HALT_S = 0.3


@dataclass(frozen=True)
class TappingScenario:
    """What the simulated patient does.

    Attributes
    ----------
    duration_s : float
        Length of the recording (s).
    fps : float
        Frame rate (Hz) at which the truth is sampled.
    amplitude_mm : float
        Peak-to-trough opening of the first tap (mm): maximal thumb–index
        distance minus the closed distance.
    frequency_hz : float
        Mean tapping rate while moving (taps per second, pauses excluded).
    decrement_mm_per_tap : float
        Planned change of the amplitude per tap (negative = shrinking).
    rhythm_jitter : float
        Coefficient of variation of the cycle durations.
    amplitude_jitter : float
        Coefficient of variation of the per-tap amplitudes around the linear trend.
    hesitations : tuple of int
        Tap indices preceded by a brief pause (fingers closed) of ``hesitation_s``.
    hesitation_s : float
        Duration of a hesitation (s).
    halts : tuple of (int, float)
        ``(tap index, duration_s)``: a freeze (fingers closed, no finger motion)
        before that tap; at least ``MIN_HALT_S`` = 0.3 s.
    drift_mm : float
        Amplitude (mm) of the slow rigid drift of the whole hand.
    hand : {"right", "left"}
    closed_distance_mm : float
        Marker-centre distance when the fingertips touch (markers on the nails).
    hand_marker : bool
        Add a third marker, ``"hand"``, on the back of the hand.
    hand_center_mm : tuple of 3 floats
        Where the middle of the two fingertip markers is at half opening, in the
        rig's world frame (mm); the default rig converges there.
    orientation_deg : tuple of 3 floats
        An extra, fixed rotation of the hand about ``hand_center_mm``: a
        rotation vector (degrees) in the hand frame (u distal, v radial, w
        dorsal). ``(0, 0, 0)`` is the standard posture of ``docs/simulator.md``;
        :func:`core.simulation.hand.overlap_orientation_deg` finds the one
        that makes the closed markers overlap in one camera.
    turns : tuple of (t_start_s, duration_s, angle_deg)
        The hand rolls about its long axis (the line through
        ``ROLL_AXIS_POINT_MM`` along u) by ``angle_deg`` and back: a third of
        the duration turning (smootherstep), a third held, a third turning
        back. Rigid, so every marker distance stays the same; used to hide a
        marker partly behind a finger in one camera.
    """

    duration_s: float = 10.0
    fps: float = 100.0
    amplitude_mm: float = 50.0
    frequency_hz: float = 3.0
    decrement_mm_per_tap: float = 0.0
    rhythm_jitter: float = 0.03
    amplitude_jitter: float = 0.0
    hesitations: tuple[int, ...] = ()
    hesitation_s: float = 0.25
    halts: tuple[tuple[int, float], ...] = ()
    drift_mm: float = 5.0
    hand: str = "right"
    closed_distance_mm: float = 18.0
    hand_marker: bool = False
    hand_center_mm: tuple[float, float, float] = (0.0, 0.0, 500.0)
    orientation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    turns: tuple[tuple[float, float, float], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "hesitations", tuple(int(k) for k in self.hesitations))
        object.__setattr__(self, "halts", tuple((int(k), float(d)) for k, d in self.halts))
        object.__setattr__(self, "hand_center_mm", tuple(float(v) for v in self.hand_center_mm))
        object.__setattr__(self, "orientation_deg", tuple(float(v) for v in self.orientation_deg))
        object.__setattr__(
            self, "turns", tuple((float(t0), float(d), float(a)) for t0, d, a in self.turns)
        )
        if not (self.duration_s > 0 and np.isfinite(self.duration_s)):
            raise ValueError(f"duration_s must be positive, got {self.duration_s}")
        if not (self.fps > 0 and np.isfinite(self.fps)):
            raise ValueError(f"fps must be positive, got {self.fps}")
        if not (0 < self.amplitude_mm <= 120):
            raise ValueError(f"amplitude_mm must be in (0, 120], got {self.amplitude_mm}")
        if not (0 < self.frequency_hz <= 10):
            raise ValueError(f"frequency_hz must be in (0, 10], got {self.frequency_hz}")
        if self.fps < 4 * self.frequency_hz:
            raise ValueError(
                f"fps ({self.fps}) must be at least 4 x frequency_hz ({self.frequency_hz})"
                " to sample every tap"
            )
        if not (0 <= self.rhythm_jitter <= 0.3):
            raise ValueError(f"rhythm_jitter must be in [0, 0.3], got {self.rhythm_jitter}")
        if not (0 <= self.amplitude_jitter <= 0.3):
            raise ValueError(f"amplitude_jitter must be in [0, 0.3], got {self.amplitude_jitter}")
        if not (self.hesitation_s > 0):
            raise ValueError(f"hesitation_s must be positive, got {self.hesitation_s}")
        if any(k < 1 for k in self.hesitations) or any(k < 1 for k, _ in self.halts):
            raise ValueError("hesitation and halt tap indices must be >= 1 (a pause between taps)")
        if any(d < MIN_HALT_S for _, d in self.halts):
            raise ValueError(f"a halt lasts at least {MIN_HALT_S} s, got {self.halts}")
        if not (0 <= self.drift_mm <= 50):
            raise ValueError(f"drift_mm must be in [0, 50], got {self.drift_mm}")
        if self.hand not in ("right", "left"):
            raise ValueError(f"hand must be 'right' or 'left', got {self.hand!r}")
        if not (5 <= self.closed_distance_mm <= 40):
            raise ValueError(
                f"closed_distance_mm must be in [5, 40], got {self.closed_distance_mm}"
            )
        if len(self.hand_center_mm) != 3 or not self.hand_center_mm[2] > 100:
            raise ValueError(
                f"hand_center_mm must be (x, y, z) with z > 100 mm, got {self.hand_center_mm}"
            )
        if len(self.orientation_deg) != 3 or not all(
            np.isfinite(v) and abs(v) <= 180 for v in self.orientation_deg
        ):
            raise ValueError(
                f"orientation_deg must be 3 finite angles within ±180, got {self.orientation_deg}"
            )
        for t0, dur, angle in self.turns:
            if not (np.isfinite(t0) and dur > 0 and np.isfinite(dur) and abs(angle) <= 120):
                raise ValueError(
                    "a turn is (t_start_s, duration_s > 0, angle_deg within ±120),"
                    f" got {(t0, dur, angle)}"
                )

    @property
    def marker_names(self) -> tuple[str, ...]:
        return (*MARKER_NAMES, HAND_MARKER_NAME) if self.hand_marker else MARKER_NAMES


@dataclass(frozen=True)
class TapTruth:
    """One true tap: from a closure through the maximal aperture to the next closure.

    Times come from the continuous model; ``amplitude_mm`` from the sampled
    trajectories (frames ``frame_start`` .. ``frame_end``).
    """

    index: int
    t_start_s: float
    t_max_aperture_s: float
    t_end_s: float
    amplitude_mm: float
    amplitude_model_mm: float
    frame_start: int
    frame_end: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "t_start_s": self.t_start_s,
            "t_max_aperture_s": self.t_max_aperture_s,
            "t_end_s": self.t_end_s,
            "amplitude_mm": self.amplitude_mm,
            "amplitude_model_mm": self.amplitude_model_mm,
            "frame_start": self.frame_start,
            "frame_end": self.frame_end,
        }


@dataclass(frozen=True)
class PauseTruth:
    """A pause before tap ``tap_index`` (fingers closed), from ``t_start_s`` for ``duration_s``."""

    tap_index: int
    t_start_s: float
    duration_s: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "tap_index": self.tap_index,
            "t_start_s": self.t_start_s,
            "duration_s": self.duration_s,
        }


@dataclass(frozen=True)
class _Timeline:
    t_start_s: FloatArray  # (K,)
    t_peak_s: FloatArray
    t_end_s: FloatArray
    amplitude_mm: FloatArray


@dataclass(frozen=True)
class _Drift:
    freqs_hz: FloatArray  # (6, 2): axes tx ty tz rx ry rz, two sinusoids each
    phases: FloatArray  # (6, 2)
    amps: FloatArray  # (6, 2): mm for translations, radians for rotations


def timeline_opening(timeline: _Timeline, t_s: ArrayLike) -> FloatArray:
    """The opening signal ``o(t)`` of a cycle timeline, same shape as ``t_s`` (the unit of
    its amplitudes): smootherstep up to each peak and back down, 0 between cycles."""
    t = np.asarray(t_s, dtype=np.float64)
    tl = timeline
    k = np.searchsorted(tl.t_start_s, t, side="right") - 1
    out = np.zeros_like(t)
    valid = (k >= 0) & (k < len(tl.t_start_s))
    kk = np.clip(k, 0, max(len(tl.t_start_s) - 1, 0))
    if len(tl.t_start_s) == 0:
        return out
    t0, tp, te, amp = tl.t_start_s[kk], tl.t_peak_s[kk], tl.t_end_s[kk], tl.amplitude_mm[kk]
    opening = valid & (t < tp)
    closing = valid & (t >= tp) & (t < te)
    x_open = np.clip((t - t0) / (tp - t0), 0.0, 1.0)
    x_close = np.clip((t - tp) / (te - tp), 0.0, 1.0)
    out = np.where(opening, amp * _smootherstep(x_open), out)
    out = np.where(closing, amp * (1.0 - _smootherstep(x_close)), out)
    return out


@dataclass(frozen=True)
class TappingModel:
    """The continuous-time model behind a :class:`TappingTruth` (positions at any time)."""

    scenario: TappingScenario
    timeline: _Timeline
    drift: _Drift
    R_world_from_hand: FloatArray  # (3, 3)
    mcp_world_mm: FloatArray  # (3,)
    thumb_closed_local_mm: FloatArray  # (3,)

    def opening_mm(self, t_s: ArrayLike) -> FloatArray:
        """Opening ``o(t)`` (mm) = aperture minus the closed distance, same shape as ``t_s``."""
        return timeline_opening(self.timeline, t_s)

    def aperture_mm(self, t_s: ArrayLike) -> FloatArray:
        """True thumb–index marker-centre distance (mm) at times ``t_s``."""
        return self.scenario.closed_distance_mm + self.opening_mm(t_s)

    def positions_mm(self, t_s: ArrayLike) -> FloatArray:
        """Marker centres ``(N, M, 3)`` in the world frame (mm) at times ``t_s`` ``(N,)``.

        Defined for every time, also before 0 and after the duration (fingers
        closed, hand drifting), so cameras with a frame offset can be rendered.
        """
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        return self._to_world(t, self.local_positions_mm(t))

    def local_positions_mm(self, t_s: ArrayLike) -> FloatArray:
        """Marker centres ``(N, M, 3)`` in the hand frame (mm) at times ``t_s`` ``(N,)``.

        The hand frame (origin at the index MCP joint, u distal, v radial, w
        dorsal) before the drift, the turns and the mirroring of a left hand;
        :meth:`hand_points_mm` takes such points to the world.
        """
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        if t.ndim != 1:
            raise ValueError(f"t_s must be a scalar or have shape (N,), got {t.shape}")
        return _local_positions(
            self.opening_mm(t),
            closed_distance_mm=self.scenario.closed_distance_mm,
            thumb_closed_local_mm=self.thumb_closed_local_mm,
            hand_marker=self.scenario.hand_marker,
        )

    def roll_deg(self, t_s: ArrayLike) -> FloatArray:
        """Roll of the hand about its long axis from ``TappingScenario.turns`` (degrees)."""
        t = np.asarray(t_s, dtype=np.float64)
        out = np.zeros_like(t)
        for t0, dur, angle in self.scenario.turns:
            x = np.clip((t - t0) / dur, 0.0, 1.0)
            up = _smootherstep(np.clip(3.0 * x, 0.0, 1.0))
            down = _smootherstep(np.clip(3.0 * x - 2.0, 0.0, 1.0))
            out = out + angle * (up - down)
        return out

    def hand_points_mm(self, t_s: ArrayLike, local_points_mm: ArrayLike) -> FloatArray:
        """World positions ``(N, P, 3)`` of points fixed to the hand (moving with its drift).

        Parameters
        ----------
        t_s : array_like, shape (N,)
        local_points_mm : array_like, shape (P, 3)
            Points in the hand frame (mm): origin at the index MCP joint, u
            distal along the index, v radial ("up"), w = u x v dorsal (right hand).
        """
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        pts = np.asarray(local_points_mm, dtype=np.float64)
        if t.ndim != 1 or pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(
                f"need t_s (N,) and local_points_mm (P, 3), got {t.shape}, {pts.shape}"
            )
        return self._to_world(t, np.broadcast_to(pts, (len(t), *pts.shape)))

    def _to_world(self, t: FloatArray, local: FloatArray) -> FloatArray:
        if self.scenario.turns:
            # Roll about the hand's long axis (u through ROLL_AXIS_POINT_MM), hand frame.
            roll = np.deg2rad(self.roll_deg(t))
            axis_pt = np.asarray(ROLL_AXIS_POINT_MM)
            R_roll = _rotations(roll[:, None] * np.array([1.0, 0.0, 0.0])[None])
            local = np.einsum("nij,nmj->nmi", R_roll, local - axis_pt) + axis_pt
        # Rigid drift: rotation about the MCP joint (hand frame axes), then translation.
        d = self.drift
        phase = 2 * np.pi * d.freqs_hz[None] * t[:, None, None] + d.phases[None]
        sig = np.sum(d.amps[None] * np.sin(phase), axis=2)  # (N, 6)
        R_drift = _rotations(sig[:, 3:])  # (N, 3, 3), in the hand frame
        rotated = np.einsum("nij,nmj->nmi", R_drift, local)
        world = rotated @ self.R_world_from_hand.T + self.mcp_world_mm + sig[:, None, :3]
        if self.scenario.hand == "left":
            cx = self.scenario.hand_center_mm[0]
            world[..., 0] = 2 * cx - world[..., 0]
        result: NDArray[np.float64] = world
        return result


@dataclass(frozen=True)
class TappingTruth:
    """Ground truth of one simulated tapping trial, sampled at the frames.

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Frame times ``i / fps`` (s).
    positions_mm : ndarray, shape (T, M, 3)
        Marker centres in the rig's world frame (mm), markers in ``marker_names`` order.
    marker_names : tuple of str
        ``("thumb", "index")`` or ``("thumb", "index", "hand")``.
    taps : tuple of TapTruth
    frequency_hz : float
        ``1 / mean(t_end_s - t_start_s)`` over the taps (pauses excluded).
    decrement_mm_per_tap : float
        Least-squares slope of the per-tap ``amplitude_mm`` over the tap index.
    hesitations, halts : tuple of PauseTruth
    fps : float
    model : TappingModel
        The continuous model (positions at any time, e.g. within an exposure).
    """

    t_s: FloatArray
    positions_mm: FloatArray
    marker_names: tuple[str, ...]
    taps: tuple[TapTruth, ...]
    frequency_hz: float
    decrement_mm_per_tap: float
    hesitations: tuple[PauseTruth, ...]
    halts: tuple[PauseTruth, ...]
    fps: float
    model: TappingModel = field(repr=False, compare=False)

    @property
    def aperture_mm(self) -> FloatArray:
        """Thumb–index marker-centre distance per frame ``(T,)`` (mm)."""
        return _aperture_from_positions(self.positions_mm)

    def to_dict(self) -> dict[str, Any]:
        """The kinematic part of ``truth.json`` (see ``docs/simulator.md``)."""
        s = self.model.scenario
        amps = [tap.amplitude_mm for tap in self.taps]
        return {
            "fps": self.fps,
            "frame_count": len(self.t_s),
            "hand": s.hand,
            "marker_names": list(self.marker_names),
            "positions_mm": self.positions_mm.tolist(),
            "closed_distance_mm": s.closed_distance_mm,
            "tap_count": len(self.taps),
            "frequency_hz": self.frequency_hz,
            "amplitude_mm_mean": float(np.mean(amps)) if amps else None,
            "decrement_mm_per_tap": self.decrement_mm_per_tap,
            "taps": [tap.to_dict() for tap in self.taps],
            "hesitations": [p.to_dict() for p in self.hesitations],
            "halts": [p.to_dict() for p in self.halts],
            "scenario": {
                "duration_s": s.duration_s,
                "fps": s.fps,
                "amplitude_mm": s.amplitude_mm,
                "frequency_hz": s.frequency_hz,
                "decrement_mm_per_tap": s.decrement_mm_per_tap,
                "rhythm_jitter": s.rhythm_jitter,
                "amplitude_jitter": s.amplitude_jitter,
                "hesitations": list(s.hesitations),
                "hesitation_s": s.hesitation_s,
                "halts": [list(h) for h in s.halts],
                "drift_mm": s.drift_mm,
                "hand_marker": s.hand_marker,
                "hand_center_mm": list(s.hand_center_mm),
                "orientation_deg": list(s.orientation_deg),
                "turns": [list(tr) for tr in s.turns],
            },
        }


def _smootherstep(x: FloatArray) -> FloatArray:
    """``6x^5 - 15x^4 + 10x^3``: 0 -> 1 with zero first and second derivatives at both ends."""
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _rotations(angles: FloatArray) -> FloatArray:
    """Rotation matrices ``(N, 3, 3)`` from small rotation vectors ``(N, 3)`` (Rodrigues)."""
    theta = np.linalg.norm(angles, axis=1)
    safe = np.where(theta > 0, theta, 1.0)
    k = angles / safe[:, None]
    K = np.zeros((len(angles), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -k[:, 2], k[:, 1]
    K[:, 1, 0], K[:, 1, 2] = k[:, 2], -k[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    result: NDArray[np.float64] = np.eye(3)[None] + s * K + (1 - c) * (K @ K)
    return result


def _aperture_from_positions(positions_mm: FloatArray) -> FloatArray:
    result: NDArray[np.float64] = np.linalg.norm(positions_mm[:, 1] - positions_mm[:, 0], axis=-1)
    return result


def _thumb_closed_local(closed_distance_mm: float) -> FloatArray:
    index_closed = INDEX_LENGTH_MM * np.array(
        [np.cos(_INDEX_CLOSED_ANGLE_RAD), np.sin(_INDEX_CLOSED_ANGLE_RAD), 0.0]
    )
    direction = _THUMB_FROM_INDEX_DIR / np.linalg.norm(_THUMB_FROM_INDEX_DIR)
    result: NDArray[np.float64] = index_closed + closed_distance_mm * direction
    return result


def _local_positions(
    opening_mm: FloatArray,
    *,
    closed_distance_mm: float,
    thumb_closed_local_mm: FloatArray,
    hand_marker: bool,
) -> FloatArray:
    """Marker centres in the hand frame ``(N, M, 3)`` for openings ``(N,)`` (mm).

    The index marker lies on the circle of radius ``L`` about the MCP joint in
    the (u, v) plane, at the angle that puts it exactly ``closed + o`` from the
    thumb marker ``T``:  ``|C(phi) - T|^2 = L^2 + |T|^2 - 2 L rho cos(phi - psi)``.
    """
    o = np.asarray(opening_mm, dtype=np.float64)
    thumb = thumb_closed_local_mm[None, :] + o[:, None] * _THUMB_MOTION_PER_MM[None, :]
    d = closed_distance_mm + o
    L = INDEX_LENGTH_MM
    a, b = thumb[:, 0], thumb[:, 1]
    rho = np.hypot(a, b)
    psi = np.arctan2(b, a)
    cos_arg = (L * L + np.sum(thumb * thumb, axis=1) - d * d) / (2 * L * rho)
    if np.any(np.abs(cos_arg) > 1):
        raise ValueError("the requested aperture is out of reach of the hand model")
    phi = psi + np.arccos(cos_arg)  # the index is above (radial to) the thumb
    index = np.column_stack([L * np.cos(phi), L * np.sin(phi), np.zeros_like(phi)])
    markers = [thumb, index]
    if hand_marker:
        markers.append(np.broadcast_to(_HAND_MARKER_LOCAL_MM, thumb.shape))
    return np.stack(markers, axis=1)


def _hand_rotation(orientation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> FloatArray:
    """``R_world_from_hand`` of the standard posture, turned by ``orientation_deg``
    (a rotation vector in the hand frame, degrees)."""
    u = _RIGHT_HAND_U / np.linalg.norm(_RIGHT_HAND_U)
    v = _RIGHT_HAND_V_HINT - (_RIGHT_HAND_V_HINT @ u) * u
    v /= np.linalg.norm(v)
    w = np.cross(u, v)
    R = np.column_stack([u, v, w])
    if any(orientation_deg):
        R = R @ _rotations(np.deg2rad(np.asarray(orientation_deg, dtype=np.float64))[None])[0]
    return R


class TimelineSpec(Protocol):
    """What a cycle timeline is built from (:class:`TappingScenario` and the other tasks'
    scenarios, ``core.simulation.tasks``); ``amplitude_mm`` is in the task's unit."""

    @property
    def duration_s(self) -> float: ...
    @property
    def amplitude_mm(self) -> float: ...
    @property
    def frequency_hz(self) -> float: ...
    @property
    def decrement_mm_per_tap(self) -> float: ...
    @property
    def rhythm_jitter(self) -> float: ...
    @property
    def amplitude_jitter(self) -> float: ...
    @property
    def hesitations(self) -> tuple[int, ...]: ...
    @property
    def hesitation_s(self) -> float: ...
    @property
    def halts(self) -> tuple[tuple[int, float], ...]: ...


def build_timeline(
    scenario: TimelineSpec, rng: np.random.Generator
) -> tuple[_Timeline, list[PauseTruth], list[PauseTruth]]:
    """The cycles of a trial: their start, peak and end times and amplitudes, and the pauses."""
    return _build_timeline(scenario, rng)


def _build_timeline(
    scenario: TimelineSpec, rng: np.random.Generator
) -> tuple[_Timeline, list[PauseTruth], list[PauseTruth]]:
    s = scenario
    pause_hes = set(s.hesitations)
    pause_halt: dict[int, float] = {}
    for k, dur in s.halts:
        pause_halt[k] = pause_halt.get(k, 0.0) + dur
    period = 1.0 / s.frequency_hz
    starts, peaks, ends, amps = [], [], [], []
    hes, halts = [], []
    t = _LEAD_IN_S
    k = 0
    while True:
        pause_start = t
        pause = (s.hesitation_s if k in pause_hes else 0.0) + pause_halt.get(k, 0.0)
        cycle = period * (1.0 + s.rhythm_jitter * float(np.clip(rng.standard_normal(), -3, 3)))
        frac = _OPEN_FRACTION + _OPEN_FRACTION_SD * float(np.clip(rng.standard_normal(), -3, 3))
        amp_noise = s.amplitude_jitter * float(np.clip(rng.standard_normal(), -3, 3))
        t0 = t + pause
        if t0 + cycle > s.duration_s - _TAIL_S:
            break
        if k in pause_hes:
            hes.append(PauseTruth(k, pause_start, s.hesitation_s))
        if k in pause_halt:
            halt_start = pause_start + (s.hesitation_s if k in pause_hes else 0.0)
            halts.append(PauseTruth(k, halt_start, pause_halt[k]))
        amp = (s.amplitude_mm + k * s.decrement_mm_per_tap) * (1.0 + amp_noise)
        starts.append(t0)
        peaks.append(t0 + frac * cycle)
        ends.append(t0 + cycle)
        amps.append(max(amp, _MIN_AMPLITUDE_MM))
        t = t0 + cycle
        k += 1
    n_taps = k
    late = sorted({*s.hesitations, *(h for h, _ in s.halts)} - set(range(1, n_taps)))
    if late:
        raise ValueError(
            f"pauses before taps {late} do not fit: only {n_taps} taps fit in {s.duration_s} s"
        )
    timeline = _Timeline(
        np.asarray(starts, dtype=np.float64),
        np.asarray(peaks, dtype=np.float64),
        np.asarray(ends, dtype=np.float64),
        np.asarray(amps, dtype=np.float64),
    )
    return timeline, hes, halts


def _build_drift(scenario: TappingScenario, rng: np.random.Generator) -> _Drift:
    freqs = rng.uniform(0.05, 0.3, size=(6, 2))
    phases = rng.uniform(0, 2 * np.pi, size=(6, 2))
    weights = np.array([0.65, 0.35])
    scale = np.array([1.0, 1.0, 0.6, 0.0, 0.0, 0.0]) * scenario.drift_mm
    rot_scale = np.deg2rad(1.5) * scenario.drift_mm / 5.0  # a few degrees of wrist wobble
    scale[3:] = rot_scale * np.array([0.5, 0.5, 1.0])
    amps = scale[:, None] * weights[None, :]
    return _Drift(freqs, phases, amps)


def least_squares_slope(values: ArrayLike) -> float:
    """Least-squares slope of ``values`` over their index (0 for fewer than two values)."""
    y = np.asarray(values, dtype=np.float64)
    if len(y) < 2:
        return 0.0
    x = np.arange(len(y), dtype=np.float64)
    x -= x.mean()
    return float(np.sum(x * (y - y.mean())) / np.sum(x * x))


def cycle_frames(timeline: _Timeline, fps: float, n_frames: int) -> list[tuple[int, int]]:
    """The frames (start, end) of each cycle of ``timeline`` in a recording of ``n_frames``."""
    return [
        (min(round(t0 * fps), n_frames - 2), min(round(t1 * fps), n_frames - 1))
        for t0, t1 in zip(timeline.t_start_s, timeline.t_end_s, strict=True)
    ]


def tap_amplitudes_from_positions(
    positions_mm: FloatArray, frame_ranges: Sequence[tuple[int, int]]
) -> FloatArray:
    """Per-tap amplitude (mm) from trajectories, the definition of INTERFACES.md.

    Parameters
    ----------
    positions_mm : ndarray, shape (T, M, 3)
        Thumb (marker 0) and index (marker 1) centres (mm).
    frame_ranges : sequence of (frame_start, frame_end)
        Frames of each tap, inclusive.

    Returns
    -------
    ndarray, shape (K,)
        Maximal thumb–index distance in the tap minus the distance at its start frame.
    """
    pos = np.asarray(positions_mm, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[1] < 2 or pos.shape[2] != 3:
        raise ValueError(f"positions_mm must have shape (T, M>=2, 3), got {pos.shape}")
    aperture = _aperture_from_positions(pos)
    out = np.empty(len(frame_ranges))
    for i, (f0, f1) in enumerate(frame_ranges):
        if not (0 <= f0 < f1 < len(aperture)):
            raise ValueError(f"tap frames ({f0}, {f1}) outside 0..{len(aperture) - 1}")
        out[i] = np.max(aperture[f0 : f1 + 1]) - aperture[f0]
    return out


def simulate_tapping(scenario: TappingScenario, *, seed: int) -> TappingTruth:
    """Simulate one finger-tapping trial and return its ground truth.

    Parameters
    ----------
    scenario : TappingScenario
    seed : int
        Seed of the random rhythm, amplitude and drift (same seed, same truth).

    Returns
    -------
    TappingTruth
        Trajectories sampled at ``i / fps`` for ``i < round(duration_s * fps)``,
        taps, frequency, decrement, pauses, and the continuous model.
    """
    if not isinstance(scenario, TappingScenario):
        raise ValueError(f"scenario must be a TappingScenario, got {type(scenario).__name__}")
    rng = np.random.default_rng([int(seed), 0x7A9])
    timeline, hes, halts = _build_timeline(scenario, rng)
    drift = _build_drift(scenario, rng)
    R = _hand_rotation(scenario.orientation_deg)
    thumb_closed = _thumb_closed_local(scenario.closed_distance_mm)
    # Put the middle of thumb and index at half the first opening on hand_center_mm.
    half = _local_positions(
        np.array([scenario.amplitude_mm / 2]),
        closed_distance_mm=scenario.closed_distance_mm,
        thumb_closed_local_mm=thumb_closed,
        hand_marker=False,
    )[0]
    mcp_world = np.asarray(scenario.hand_center_mm) - R @ half.mean(axis=0)
    model = TappingModel(scenario, timeline, drift, R, mcp_world, thumb_closed)

    n_frames = round(scenario.duration_s * scenario.fps)
    t_s = np.arange(n_frames) / scenario.fps
    positions = model.positions_mm(t_s)
    fps = scenario.fps
    frames = cycle_frames(timeline, fps, n_frames)
    amps = tap_amplitudes_from_positions(positions, frames) if frames else np.zeros(0)
    taps = tuple(
        TapTruth(
            index=k,
            t_start_s=float(timeline.t_start_s[k]),
            t_max_aperture_s=float(timeline.t_peak_s[k]),
            t_end_s=float(timeline.t_end_s[k]),
            amplitude_mm=float(amps[k]),
            amplitude_model_mm=float(timeline.amplitude_mm[k]),
            frame_start=frames[k][0],
            frame_end=frames[k][1],
        )
        for k in range(len(frames))
    )
    cycles = timeline.t_end_s - timeline.t_start_s
    frequency = float(1.0 / np.mean(cycles)) if len(cycles) else 0.0
    for arr in (t_s, positions):
        arr.setflags(write=False)
    return TappingTruth(
        t_s=t_s,
        positions_mm=positions,
        marker_names=scenario.marker_names,
        taps=taps,
        frequency_hz=frequency,
        decrement_mm_per_tap=least_squares_slope(amps),
        hesitations=tuple(hes),
        halts=tuple(halts),
        fps=fps,
        model=model,
    )

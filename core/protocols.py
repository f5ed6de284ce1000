"""Marker protocols of the tasks other than finger tapping: labels, labelling rules, cycle signals.

Each task has a marker protocol (``docs/protocols.md`` has the drawings and the
reasons): where the markers go, what they are called in ``markers.csv``, the
rule that gives each tracked marker its label, and the **cycle signal** the
cycles are found on (:mod:`core.cycles`), in the unit of the task's amplitude.

- **Hand movements** (MDS-UPDRS 3.5): ``finger`` on the back of the middle
  phalanx of the middle finger, ``wrist`` on the back of the wrist. Both face
  the cameras in the open hand *and* in the fist (a fingertip marker would be
  buried in the palm). Signal: the finger–wrist distance (mm), largest when the
  hand is open.
- **Pronation–supination** (3.6): a rigid three-marker cluster on the back of
  the hand, markers on posts (``radial``, ``ulnar``, ``distal``; a mirrored
  cluster for the left hand, so that ``radial`` is always on the thumb side).
  Signal: the rotation of the cluster about the forearm axis (degrees) from
  its full 3D orientation (a proper rotation, swing–twist decomposition), 0 at
  the most pronated position of the recording, positive towards supination.
- **Toe tapping** (3.7): ``toe`` (lateral forefoot, over the 5th metatarsal
  head), ``heel`` (lateral heel), ``shin`` (front of the lower leg, ~20 cm up).
  Signal: the toe's lift (mm): the rotation of the heel–toe line since its
  mean direction, in the plane of the foot and the shin, times the heel–toe
  length (the arc the toe marker travels); positive towards the shin.
- **Leg agility** (3.8): ``knee`` (lateral femoral epicondyle), ``thigh``
  (lateral thigh, on the line from the knee marker to the greater trochanter,
  ~20 cm up), ``ankle`` (lateral malleolus). Signal: the rise of the thigh
  (degrees): the rotation of the thigh–knee line since its mean direction, in
  the plane of the thigh and the shank, positive as the knee rises; 0 at the
  lowest position of the recording.

Labelling rules (from stereo chains of tracklets, :mod:`core.tracks`): the
fastest chain is the distal marker (``finger``, ``toe``); the other labels
follow from distances, which rigid body parts keep and the room's reflections
do not. The cluster of 3.6 is labelled by matching its three distances to
the cluster's known ones; the leg of 3.8 by its two rigid segments (thigh–knee,
knee–ankle), the thigh marker being the slowest of the three (nearest the hip).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from core.tasks import Task

FloatArray = NDArray[np.float64]

#: The three markers of the pronation–supination cluster in its own frame (mm): x from
#: the ulnar to the radial marker, y distal (towards the fingers), z up the posts (15, 30
#: and 45 mm tall). A scalene triangle, so that its three distances name its three
#: markers; tilted, so that with the palm down no two markers share a row of a rig
#: whose cameras stand side by side (the same epipolar line: docs/protocols.md).
PS_CLUSTER_MM: dict[str, tuple[float, float, float]] = {
    "radial": (35.0, 0.0, 0.0),
    "ulnar": (-35.0, 0.0, 30.0),
    "distal": (-10.0, 45.0, 15.0),
}
#: A chain triple is the cluster when each distance is within this of the cluster's (mm).
PS_DISTANCE_TOLERANCE_MM = 6.0
#: ... and each distance varies by less than this (SD, mm): a rigid body.
PS_RIGID_SD_MM = 2.0
#: Chains with fewer stereo frames in common are not compared.
MIN_COMMON_FRAMES = 10
#: The wrist marker lies this far from the finger marker (median, mm).
HM_DISTANCE_RANGE_MM = (40.0, 250.0)
#: The heel marker lies this far from the toe marker (median, mm).
TT_TOE_HEEL_RANGE_MM = (100.0, 320.0)
#: The shin marker lies this far from the heel marker (median, mm).
TT_HEEL_SHIN_RANGE_MM = (60.0, 400.0)
#: The knee marker lies this far from the thigh marker (median, mm).
LA_THIGH_KNEE_RANGE_MM = (100.0, 350.0)
#: The ankle marker lies this far from the knee marker (median, mm).
LA_KNEE_ANKLE_RANGE_MM = (250.0, 550.0)
#: A leg segment's two markers keep their distance within this SD (mm): skin moves over
#: the bone, a reflection in the room does not keep step.
LA_SEGMENT_SD_MM = 8.0
#: A chain moves when its 3D spread is at least this (mm) (as ``core.tracks``).
MIN_SPREAD_MM = 1.0


@dataclass(frozen=True)
class MarkerProtocol:
    """The markers of one task.

    Attributes
    ----------
    task : Task
    labels : tuple of str
        The marker labels of ``markers.csv``, in this order.
    rule : str
        The labelling rule in one sentence (docs/protocols.md).
    markers_in_words : str
        The markers as a clinician or technician names them in a message ("check that
        both cameras see the thumb and index markers").
    """

    task: Task
    labels: tuple[str, ...]
    rule: str
    markers_in_words: str


PROTOCOLS: dict[Task, MarkerProtocol] = {
    Task.FINGER_TAPPING: MarkerProtocol(
        Task.FINGER_TAPPING,
        ("thumb", "index"),
        "the index is the fastest moving marker; the thumb the moving one that comes closest to it",
        "the thumb and index markers",
    ),
    Task.HAND_MOVEMENTS: MarkerProtocol(
        Task.HAND_MOVEMENTS,
        ("finger", "wrist"),
        "the finger is the fastest marker; the wrist the moving marker 40-250 mm from it"
        " seen with it most often",
        "the finger and wrist markers",
    ),
    Task.PRONATION_SUPINATION: MarkerProtocol(
        Task.PRONATION_SUPINATION,
        ("radial", "ulnar", "distal"),
        "the three markers that keep the cluster's three distances (within 6 mm, SD under 2 mm),"
        " named by those distances",
        "the three markers of the cluster on the back of the hand",
    ),
    Task.TOE_TAPPING: MarkerProtocol(
        Task.TOE_TAPPING,
        ("toe", "heel", "shin"),
        "the toe is the fastest marker; the heel the one 100-320 mm from it at the steadiest"
        " distance; the shin the nearest other marker 60-400 mm from the heel among those seen"
        " with it at least half as often as the most seen",
        "the toe, heel and shin markers",
    ),
    Task.LEG_AGILITY: MarkerProtocol(
        Task.LEG_AGILITY,
        ("knee", "thigh", "ankle"),
        "the three moving markers that form two segments of steady length (SD under 8 mm):"
        " thigh-knee 100-350 mm and knee-ankle 250-550 mm, the thigh marker the slowest of"
        " the three",
        "the thigh, knee and ankle markers",
    ),
}


#: The markers' diameter the protocols ask for (mm): 5 mm on the hand, filmed from 500 mm;
#: 10 mm on the foot and leg, filmed from 800 mm and 1 m (docs/protocols.md).
MARKER_DIAMETER_MM = {Task.TOE_TAPPING: 10.0, Task.LEG_AGILITY: 10.0}


def marker_diameter_mm(task: Task | str) -> float:
    """The marker diameter of ``task``'s protocol (mm): 10 for toe tapping and leg agility,
    else 5."""
    return MARKER_DIAMETER_MM.get(Task(task), 5.0)


def marker_columns(labels: Sequence[str], task: Task | str) -> list[int]:
    """The column of each of ``task``'s markers in ``labels`` (e.g. ``markers.csv``'s), in the
    protocol's order, the order :func:`cycle_signal` takes them in.

    Raises
    ------
    ValueError
        A marker of the protocol is not among ``labels`` (the sentence names them all).
    """
    task = Task(task)
    wanted = protocol_for(task).labels
    missing = [name for name in wanted if name not in labels]
    if missing:
        named = f"{', '.join(wanted[:-1])} and {wanted[-1]}"
        raise ValueError(f"{task.label.lower()} needs the markers {named}, got {tuple(labels)}")
    return [list(labels).index(name) for name in wanted]


def protocol_for(task: Task | str) -> MarkerProtocol:
    """The marker protocol of ``task``."""
    return PROTOCOLS[Task(task)]


# ----------------------------------------------------------------------------- labelling


def _speed(track: FloatArray, fps: float) -> float:
    step = np.linalg.norm(np.diff(track, axis=0), axis=1) * fps
    step = step[np.isfinite(step)]
    return float(np.percentile(step, 75)) if len(step) >= 3 else 0.0


def _spread(track: FloatArray) -> float:
    pts = track[np.all(np.isfinite(track), axis=1)]
    return float(np.sqrt(np.sum(np.var(pts, axis=0)))) if len(pts) > 1 else 0.0


def _distances(a: FloatArray, b: FloatArray) -> FloatArray:
    """Distances over the frames where both are seen (mm)."""
    both = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    result: FloatArray = np.linalg.norm(a[both] - b[both], axis=1)
    return result


def label_chains(
    task: Task | str, tracks: Sequence[FloatArray], *, fps: float
) -> tuple[list[int | None], list[str]]:
    """Which chain carries each label of the task's protocol.

    Parameters
    ----------
    task : Task or str
        Not finger tapping (``core.tracks.select_markers`` labels that one).
    tracks : sequence of ndarray, shape (T, 3)
        Each chain's stereo positions on the frame axis (mm), NaN elsewhere.
    fps : float

    Returns
    -------
    picks : list of int or None
        For each label of :func:`protocol_for`, the index of its chain (None: not found).
    warnings : list of str
    """
    task = Task(task)
    if task is Task.FINGER_TAPPING:
        raise ValueError("finger tapping is labelled by core.tracks.select_markers")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    tracks = [np.asarray(t, dtype=np.float64) for t in tracks]
    if task is Task.PRONATION_SUPINATION:
        return _label_cluster(tracks)
    if task is Task.LEG_AGILITY:
        return _label_leg(tracks, fps)
    labels = protocol_for(task).labels
    if not tracks:
        return [None] * len(labels), [
            f"no marker was found; {task.label.lower()} needs {len(labels)}"
        ]
    speeds = [_speed(t, fps) for t in tracks]
    distal = int(np.argmax(speeds))
    if task is Task.HAND_MOVEMENTS:
        return _label_hand(tracks, distal)
    return _label_foot(tracks, distal)


def _label_hand(tracks: list[FloatArray], finger: int) -> tuple[list[int | None], list[str]]:
    lo, hi = HM_DISTANCE_RANGE_MM
    best: tuple[int, int] | None = None
    for k, track in enumerate(tracks):
        if k == finger or _spread(track) < MIN_SPREAD_MM:
            continue
        d = _distances(tracks[finger], track)
        if len(d) < MIN_COMMON_FRAMES or not lo <= float(np.median(d)) <= hi:
            continue
        if best is None or len(d) > best[0]:
            best = (len(d), k)
    if best is None:
        return [finger, None], [
            "no wrist marker was found 40-250 mm from the finger marker; check that the wrist"
            " marker sits on the back of the wrist, in view of both cameras"
        ]
    return [finger, best[1]], []


def _label_foot(tracks: list[FloatArray], toe: int) -> tuple[list[int | None], list[str]]:
    lo, hi = TT_TOE_HEEL_RANGE_MM
    heel: tuple[float, int] | None = None
    for k, track in enumerate(tracks):
        if k == toe:
            continue
        d = _distances(tracks[toe], track)
        if len(d) < MIN_COMMON_FRAMES or not lo <= float(np.median(d)) <= hi:
            continue
        sd = float(np.std(d))
        if heel is None or sd < heel[0]:
            heel = (sd, k)
    if heel is None:
        return [toe, None, None], [
            "no heel marker was found 100-320 mm from the toe marker; check that the heel marker"
            " is in view of both cameras"
        ]
    lo, hi = TT_HEEL_SHIN_RANGE_MM
    near: list[tuple[float, int, int]] = []  # (median distance, frames, chain)
    for k, track in enumerate(tracks):
        if k in (toe, heel[1]):
            continue
        d = _distances(tracks[heel[1]], track)
        if len(d) >= MIN_COMMON_FRAMES and lo <= float(np.median(d)) <= hi:
            near.append((float(np.median(d)), len(d), k))
    # Seen with the heel at least half as often as the best seen (a glint twinkles).
    most = max((n for _, n, _ in near), default=0)
    steady = [(d, k) for d, n, k in near if n >= 0.5 * most]
    shin = min(steady) if steady else None
    if shin is None:
        return [toe, heel[1], None], [
            "no shin marker was found 60-400 mm from the heel marker; check that the shin marker"
            " is in view of both cameras"
        ]
    return [toe, heel[1], shin[1]], []


def _segment(a: FloatArray, b: FloatArray, span: tuple[float, float]) -> float | None:
    """The SD of the distance of two chains (mm) when they form a rigid segment of a length
    within ``span``; None when they do not."""
    d = _distances(a, b)
    if len(d) < MIN_COMMON_FRAMES or not span[0] <= float(np.median(d)) <= span[1]:
        return None
    sd = float(np.std(d))
    return sd if sd <= LA_SEGMENT_SD_MM else None


def _label_leg(tracks: list[FloatArray], fps: float) -> tuple[list[int | None], list[str]]:
    """(knee, thigh, ankle): the triple whose thigh and shank segments are the steadiest;
    without an ankle, the steadiest thigh segment's two markers (the signal needs all three,
    but markers.csv still names them)."""
    seen = [int(np.count_nonzero(np.all(np.isfinite(t), axis=1))) for t in tracks]
    moving = [k for k in range(len(tracks)) if _spread(tracks[k]) >= MIN_SPREAD_MM]
    candidates = sorted(moving, key=lambda k: -seen[k])[:10]
    speeds = {k: _speed(tracks[k], fps) for k in candidates}
    best: tuple[float, tuple[int, int, int]] | None = None
    pair: tuple[float, int, int] | None = None
    for thigh, knee in itertools.permutations(candidates, 2):
        sd_thigh = _segment(tracks[thigh], tracks[knee], LA_THIGH_KNEE_RANGE_MM)
        if sd_thigh is None or speeds[thigh] >= speeds[knee]:
            continue
        if pair is None or sd_thigh < pair[0]:
            pair = (sd_thigh, knee, thigh)
        for ankle in candidates:
            if ankle in (thigh, knee) or speeds[thigh] >= speeds[ankle]:
                continue
            sd_shank = _segment(tracks[knee], tracks[ankle], LA_KNEE_ANKLE_RANGE_MM)
            if sd_shank is not None and (best is None or sd_thigh + sd_shank < best[0]):
                best = (sd_thigh + sd_shank, (knee, thigh, ankle))
    if best is not None:
        return list(best[1]), []
    if pair is None:
        return [None, None, None], [
            "no thigh and knee markers were found 100-350 mm apart at a steady distance; check"
            " that both sit on the lateral side of the thigh, in view of both cameras"
        ]
    return [pair[1], pair[2], None], [
        "no ankle marker was found 250-550 mm from the knee marker at a steady distance; check"
        " that it sits on the lateral malleolus, in view of both cameras"
    ]


def _cluster_distances() -> dict[tuple[str, str], float]:
    pts = {k: np.asarray(v) for k, v in PS_CLUSTER_MM.items()}
    return {
        (a, b): float(np.linalg.norm(pts[a] - pts[b]))
        for a, b in itertools.combinations(PS_CLUSTER_MM, 2)
    }


def _label_cluster(tracks: list[FloatArray]) -> tuple[list[int | None], list[str]]:
    labels = tuple(PS_CLUSTER_MM)
    template = _cluster_distances()
    seen = [int(np.count_nonzero(np.all(np.isfinite(t), axis=1))) for t in tracks]
    candidates = sorted(range(len(tracks)), key=lambda k: -seen[k])[:10]
    best: tuple[float, tuple[int, ...]] | None = None
    for triple in itertools.combinations(candidates, 3):
        stats: dict[tuple[int, int], tuple[float, float]] = {}
        ok = True
        for a, b in itertools.combinations(triple, 2):
            d = _distances(tracks[a], tracks[b])
            if len(d) < MIN_COMMON_FRAMES or float(np.std(d)) > PS_RIGID_SD_MM:
                ok = False
                break
            stats[(a, b)] = stats[(b, a)] = (float(np.median(d)), float(np.std(d)))
        if not ok:
            continue
        for perm in itertools.permutations(triple):
            named = dict(zip(labels, perm, strict=True))
            errors = [stats[(named[a], named[b])][0] - ref for (a, b), ref in template.items()]
            if max(abs(e) for e in errors) > PS_DISTANCE_TOLERANCE_MM:
                continue
            cost = float(sum(e * e for e in errors))
            if best is None or cost < best[0]:
                best = (cost, perm)
    if best is None:
        return [None, None, None], [
            "the three markers of the pronation-supination cluster were not found together;"
            " check that the cluster is on the back of the hand and in view of both cameras"
        ]
    return list(best[1]), []


# ----------------------------------------------------------------------------- cycle signals


@dataclass(frozen=True)
class CycleSignal:
    """A task's cycle signal: one value per frame, largest at the turn of each cycle.

    Attributes
    ----------
    values : ndarray, shape (T,)
        In ``unit``; NaN where a marker it needs is missing.
    unit : {"mm", "deg"}
    details : dict
        What the signal was computed with (JSON-ready), e.g. the forearm axis.
    """

    values: FloatArray
    unit: str
    details: dict[str, Any] = field(default_factory=dict)


def cycle_signal(
    task: Task | str, positions_mm: NDArray[np.floating], *, side: str = "right"
) -> CycleSignal:
    """The cycle signal of ``task`` from the labelled markers.

    Parameters
    ----------
    task : Task or str
    positions_mm : ndarray, shape (T, M, 3)
        Marker positions (mm) in the order of the protocol's labels; NaN where missing.
    side : {"right", "left"}
        The side examined; gives the direction of supination (3.6).

    Returns
    -------
    CycleSignal
    """
    task = Task(task)
    pos = np.asarray(positions_mm, dtype=np.float64)
    n_labels = len(protocol_for(task).labels)
    if pos.ndim != 3 or pos.shape[1] != n_labels or pos.shape[2] != 3:
        raise ValueError(f"positions_mm must have shape (T, {n_labels}, 3), got {pos.shape}")
    if side not in ("right", "left"):
        raise ValueError(f"side must be 'right' or 'left', got {side!r}")
    if task is Task.FINGER_TAPPING or task is Task.HAND_MOVEMENTS:
        return CycleSignal(np.linalg.norm(pos[:, 1] - pos[:, 0], axis=1), "mm")
    if task is Task.TOE_TAPPING:
        return toe_lift_mm(pos)
    if task is Task.LEG_AGILITY:
        return thigh_lift_deg(pos)
    return supination_deg(pos, side=side)


def toe_lift_mm(positions_mm: FloatArray) -> CycleSignal:
    """Toe lift (mm) from toe, heel and shin markers ``(T, 3, 3)``.

    ``f = toe - heel`` rotates with the foot. Its mean direction ``f0`` and the
    shin's direction from the heel span the foot's sagittal plane, with normal
    ``n = f0 x (shin - heel)`` (mean over frames): the signed angle
    ``theta = atan2((f0 x f) . n, f0 . f)`` grows as the toe rises towards the
    shin. The signal is ``L (theta - min theta)`` with ``L`` the median
    heel–toe length: the arc the toe marker travels about the heel, 0 at the
    lowest toe position of the recording. A rotation of the foot about any
    lateral axis (the heel's contact point, the ankle) changes ``theta`` by
    exactly its angle.
    """
    toe, heel, shin = positions_mm[:, 0], positions_mm[:, 1], positions_mm[:, 2]
    out = np.full(len(toe), np.nan)
    turn = _turn_in_plane(toe - heel, shin - heel)
    if turn is None:
        return CycleSignal(out, "mm", {"heel_toe_mm": None})
    theta, ok, length = turn
    out[ok] = length * (theta - float(np.min(theta)))
    return CycleSignal(out, "mm", {"heel_toe_mm": length})


def _turn_in_plane(
    f: FloatArray, g: FloatArray
) -> tuple[FloatArray, NDArray[np.bool_], float] | None:
    """The signed turn (radians) of the segment ``f (T, 3)`` from its mean direction ``f0``,
    in the plane of ``f0`` and ``g (T, 3)`` (normal ``n``: the mean of ``f0 x g``), positive
    from ``f0`` towards ``g``; over the frames ``ok`` where both are seen, with the median
    length of ``f``: ``(theta, ok, length)``; None with fewer than three such frames.

    ``atan2((f0 x f) . n, f0 . f)`` reads only the parts of ``f`` in the plane (``n`` is
    across ``f0``): the angle of ``f`` projected onto it.
    """
    ok = np.all(np.isfinite(f), axis=1) & np.all(np.isfinite(g), axis=1)
    if np.count_nonzero(ok) < 3:
        return None
    length = float(np.median(np.linalg.norm(f[ok], axis=1)))
    unit_f = f[ok] / np.linalg.norm(f[ok], axis=1)[:, None]
    f0 = np.mean(unit_f, axis=0)
    f0 /= np.linalg.norm(f0)
    n = np.mean(np.cross(f0[None], g[ok]), axis=0)
    n /= np.linalg.norm(n)
    sin_part = np.cross(f0[None], unit_f) @ n
    theta: FloatArray = np.arctan2(sin_part, unit_f @ f0)
    return theta, ok, length


def thigh_lift_deg(positions_mm: FloatArray) -> CycleSignal:
    """Rise of the thigh (degrees) from knee, thigh and ankle markers ``(T, 3, 3)``.

    ``f = knee - thigh`` rotates with the thigh. Its mean direction ``f0`` and
    the shank's direction up from the ankle, ``g = knee - ankle``, span the
    leg's sagittal plane, with normal ``n = f0 x g`` (mean over frames): the
    angle ``theta = atan2((f0 x f) . n, f0 . f)`` of ``f`` projected onto that
    plane grows as the knee rises (hip flexion). The signal is ``theta - min theta``
    in degrees: 0 at the lowest position of the recording. A rotation of the
    thigh about any axis across the plane (the hip's flexion axis) changes
    ``theta`` by exactly its angle when the thigh and knee markers sit at the
    same depth across the leg (docs/protocols.md: a mismatch of ``d`` mm over
    the ``L`` mm between them reads the angle short by about ``(d / L)^2 / 2``
    of its value at 30 degrees).
    """
    knee, thigh, ankle = positions_mm[:, 0], positions_mm[:, 1], positions_mm[:, 2]
    out = np.full(len(knee), np.nan)
    turn = _turn_in_plane(knee - thigh, knee - ankle)
    if turn is None:
        return CycleSignal(out, "deg", {"thigh_knee_mm": None})
    theta, ok, length = turn
    out[ok] = np.rad2deg(theta - float(np.min(theta)))
    return CycleSignal(out, "deg", {"thigh_knee_mm": length})


def _kabsch(ref: FloatArray, cur: FloatArray) -> FloatArray:
    """Rotation ``R`` with ``cur - mean(cur) ~ R (ref - mean(ref))`` (least squares, det +1)."""
    a = ref - ref.mean(axis=0)
    b = cur - cur.mean(axis=0)
    u, _, vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(u @ vt))
    result: FloatArray = u @ np.diag([1.0, 1.0, d]) @ vt
    return result


def _quaternion(R: FloatArray) -> FloatArray:
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix (Shepperd's method)."""
    tr = float(np.trace(R))
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    out = np.asarray(q, dtype=np.float64)
    result: FloatArray = out / np.linalg.norm(out)
    return result


def _rotation_vector(R: FloatArray) -> FloatArray:
    q = _quaternion(R)
    if q[0] < 0:
        q = -q
    s = float(np.linalg.norm(q[1:]))
    if s < 1e-15:
        return np.zeros(3)
    result: FloatArray = 2.0 * math.atan2(s, float(q[0])) * q[1:] / s
    return result


def supination_deg(positions_mm: FloatArray, *, side: str) -> CycleSignal:
    """Rotation about the forearm axis (degrees) of the cluster ``(T, 3, 3)`` (radial, ulnar, distal).

    1. The cluster's orientation ``R(t)`` relative to a reference frame (the
       first frame that sees all three markers): the least-squares rotation
       (Kabsch) taking the reference cluster onto the current one.
    2. The forearm axis ``a``: the principal direction of the frame-to-frame
       rotation vectors (the axis the hand turns about), pointing distally
       (towards the ``distal`` marker's side of the cluster).
    3. Supination turns the radial side towards the back of the hand, a
       positive rotation about ``-a`` for a right hand and ``+a`` for a left
       hand; the angle is the *twist* of ``R(t)`` about that axis
       (swing–twist decomposition of its quaternion ``(w, v)``:
       ``2 atan2(v . n, w)``), unwrapped over time, so it stays exact through
       palm up and beyond 180 degrees.
    4. The signal is that angle minus its minimum: 0 at the most pronated
       position of the recording.
    """
    pos = positions_mm
    ok = np.all(np.isfinite(pos), axis=(1, 2))
    out = np.full(len(pos), np.nan)
    frames = np.flatnonzero(ok)
    if len(frames) < 3:
        return CycleSignal(out, "deg", {"forearm_axis": None})
    ref = pos[frames[0]]
    rots = np.stack([_kabsch(ref, pos[i]) for i in frames])
    steps = [
        _rotation_vector(rots[k + 1] @ rots[k].T)
        for k in range(len(frames) - 1)
        if frames[k + 1] - frames[k] <= 3
    ]
    omega = np.asarray(steps) if steps else np.zeros((0, 3))
    if len(omega) < 2 or not np.any(omega):
        return CycleSignal(out, "deg", {"forearm_axis": None})
    _, _, vt = np.linalg.svd(omega, full_matrices=False)
    axis = vt[0]
    distal_dir = ref[2] - 0.5 * (ref[0] + ref[1])
    if float(axis @ distal_dir) < 0:
        axis = -axis
    n = -axis if side == "right" else axis
    quats = np.stack([_quaternion(R) for R in rots])
    twist = 2.0 * np.arctan2(quats[:, 1:] @ n, quats[:, 0])
    angle = np.rad2deg(np.unwrap(twist))
    angle -= float(np.min(angle))
    out[frames] = angle
    return CycleSignal(out, "deg", {"forearm_axis": axis.tolist(), "side": side})


__all__ = [
    "PROTOCOLS",
    "PS_CLUSTER_MM",
    "CycleSignal",
    "MarkerProtocol",
    "cycle_signal",
    "label_chains",
    "marker_columns",
    "marker_diameter_mm",
    "protocol_for",
    "supination_deg",
    "thigh_lift_deg",
    "toe_lift_mm",
]

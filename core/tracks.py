"""Marker identities over time: tracking, distractor rejection, gap filling, labelling.

Three steps (see ``docs/tracking.md``):

1. **Tracklets** (:func:`build_tracklets`): frame by frame, every active track
   predicts its position with a constant-velocity model; tracks and the
   frame's stereo candidates (every epipolar-consistent pair, triangulated)
   are assigned globally (Hungarian method on the 3D distance, gated), each
   detection of either camera used at most once. A track without a stereo
   candidate may continue on a *single-view* observation: the detection
   nearest to its projected prediction in one camera. Stereo candidates left
   over start new tracks. A track ends after a few frames without any
   observation, or after ``max_single_view_frames`` without a stereo one.
2. **Identities** (:func:`select_markers`): tracklets with too few stereo
   points are dropped (flicker, erratic glints); the rest are linked into
   chains (a later tracklet continues an earlier one when they do not overlap
   in time and its start lies within a motion-dependent distance of the
   other's end).
3. **Labels** (standard finger-tapping posture, ``docs/simulator.md``): the
   **index** is the fastest moving chain (it carries ~85 % of the opening;
   reflections on the hand or a ring only follow the hand's slow drift); the
   **thumb** is the other moving chain that comes closest to the index (the
   fingertips touch at every closure). Static reflections never move and
   never qualify. ``swap_labels`` exchanges the two labels.

Gaps of at most ``max_gap_frames`` between measured frames are filled and
marked ``interpolated`` (:func:`fill_gaps`): a cubic spline through the
measured neighbours gives the position; where one camera still sees the
marker, the point is moved onto that camera's ray at the interpolated depth,
so only the depth is interpolated. A gap in which the two markers' images
merged in one camera while the other camera saw both in every frame (a
closure seen along the opening direction) may be longer
(``max_merged_gap_frames``): only its depth is interpolated. Longer gaps stay
``missing`` (NaN).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline
from scipy.optimize import linear_sum_assignment

from core.camera import StereoRig
from core.protocols import label_chains, protocol_for
from core.tasks import Task

try:
    from core import _tracks
except ImportError as exc:  # pragma: no cover - a source tree that was never installed
    raise ImportError(
        "core._tracks (the tracker's compiled loop, core/_tracks.pyx) is not built: install the"
        " project with `pip install -e .` (needs a C compiler), or run"
        " `python setup.py build_ext --inplace`"
    ) from exc

FloatArray = NDArray[np.float64]

MEASURED = "measured"
INTERPOLATED = "interpolated"
MISSING = "missing"

#: Observation kinds in a tracklet.
STEREO, LEFT_ONLY, RIGHT_ONLY = 0, 1, 2

MARKER_NAMES = ("thumb", "index")


@dataclass(frozen=True)
class FrameObservations:
    """What one (left) frame offers the tracker.

    Attributes
    ----------
    candidates_mm : ndarray, shape (C, 3)
        Triangulated stereo candidates (mm), outliers already removed.
    reprojection_px : ndarray, shape (C,)
        Their reprojection errors (px).
    left_index, right_index : ndarray, shape (C,)
        Which detection of each camera a candidate uses.
    left_px : ndarray, shape (NL, 2)
        All left detections (px).
    right_px : ndarray, shape (NR, 2)
        All right detections of the paired right frame (px); empty when the
        right video has no frame paired with this one.
    left_fitted, right_fitted : ndarray, shape (NL,) / (NR,), bool, optional
        Which detections are markers measured in a merged or touching image
        along their rays from the other camera (``core.merged``): used even
        where two markers' images touch. None: none.
    """

    candidates_mm: FloatArray
    reprojection_px: FloatArray
    left_index: NDArray[np.intp]
    right_index: NDArray[np.intp]
    left_px: FloatArray
    right_px: FloatArray
    left_fitted: NDArray[np.bool_] | None = None
    right_fitted: NDArray[np.bool_] | None = None

    @classmethod
    def empty(cls) -> FrameObservations:
        return cls(
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros(0, np.intp),
            np.zeros(0, np.intp),
            np.zeros((0, 2)),
            np.zeros((0, 2)),
        )


@dataclass(frozen=True)
class Tracklet:
    """One uninterrupted track.

    Attributes
    ----------
    frames : ndarray, shape (n,)
        Left frame numbers, increasing.
    kind : ndarray, shape (n,)
        ``STEREO``, ``LEFT_ONLY`` or ``RIGHT_ONLY`` per frame.
    positions_mm : ndarray, shape (n, 3)
        Triangulated point for stereo frames; for single-view frames the
        point on that camera's ray closest to the prediction (provisional).
    reprojection_px : ndarray, shape (n,)
        NaN for single-view frames.
    pixels_px : ndarray, shape (n, 2)
        The single-view detection (NaN for stereo frames).
    """

    frames: NDArray[np.int_]
    kind: NDArray[np.int_]
    positions_mm: FloatArray
    reprojection_px: FloatArray
    pixels_px: FloatArray

    @property
    def stereo(self) -> NDArray[np.bool_]:
        result: NDArray[np.bool_] = self.kind == STEREO
        return result

    @property
    def n_stereo(self) -> int:
        return int(np.count_nonzero(self.stereo))

    @property
    def spread_mm(self) -> float:
        """RMS distance of the stereo points from their mean (mm)."""
        pts = self.positions_mm[self.stereo]
        if len(pts) < 2:
            return 0.0
        return float(np.sqrt(np.sum(np.var(pts, axis=0))))


def build_tracklets(
    rig: StereoRig,
    observations: Sequence[FrameObservations],
    *,
    gate_mm: float,
    max_coast_frames: int = 2,
    max_single_view_frames: int = 12,
    merge_px: tuple[float, float] | None = None,
    overlap_frames: list[int] | None = None,
) -> list[Tracklet]:
    """Link stereo candidates (and single-view detections) frame to frame.

    The loop over frames is compiled (``core/_tracks.pyx``, see ``docs/performance.md``,
    "The tracker compiled"): a frame meets only a few tracks and candidates.

    Parameters
    ----------
    rig : StereoRig
    observations : sequence of FrameObservations
        One per left frame.
    gate_mm : float
        Largest distance between a prediction and its observation (mm) after
        one frame; grows with the number of frames since the last observation.
    max_coast_frames : int
        A track ends after this many frames without any observation.
    max_single_view_frames : int
        A track ends after this many frames without a stereo observation.
    merge_px : (float, float), optional
        Per camera (left, right): where the predictions of two established
        tracks (each seen in stereo within the last frames) project closer
        than this (px; about a marker diameter), their two images touch or
        overlap in that camera and neither can be measured there: the
        detections within this distance of either projection are not used,
        and the tracks continue on the other camera alone (their frames are
        then filled as ``interpolated``, never ``measured``).
    overlap_frames : list of int, optional
        Receives the frames in which that happened (in one camera or both).

    Returns
    -------
    list of Tracklet
        In order of their first frame.
    """
    if gate_mm <= 0:
        raise ValueError(f"gate_mm must be positive, got {gate_mm}")
    if not observations:
        return []
    frames, kind, pos, reproj, pixels, offsets, order = _tracks.link(
        rig.cameras,
        gate_mm,
        max_coast_frames,
        max_single_view_frames,
        merge_px,
        *_concatenated(observations),
        overlap_frames=overlap_frames,
    )
    # Tracks in the order they ended, then (stably) by their first frame.
    order.sort(key=lambda k: int(frames[offsets[k]]))
    bounds = offsets.tolist()
    return [
        Tracklet(
            frames=frames[a:b],
            kind=kind[a:b],
            positions_mm=pos[a:b],
            reprojection_px=reproj[a:b],
            pixels_px=pixels[a:b],
        )
        for a, b in ((bounds[k], bounds[k + 1]) for k in order)
    ]


def _concatenated(observations: Sequence[FrameObservations]) -> tuple[NDArray[np.generic], ...]:
    """The observations of all frames one after the other, with each frame's offsets
    (``_tracks.link``'s arguments): candidates, their reprojection errors and
    detection indices, candidate offsets; left detections, fitted flags, offsets;
    the same for the right."""

    def offsets(arrays: Sequence[NDArray[np.generic]]) -> NDArray[np.intp]:
        out = np.zeros(len(arrays) + 1, dtype=np.intp)
        np.cumsum(np.fromiter(map(len, arrays), np.intp, len(arrays)), out=out[1:])
        return out

    def fitted(
        starts: NDArray[np.intp], flags: list[NDArray[np.bool_] | None]
    ) -> NDArray[np.uint8]:
        out = np.zeros(starts[-1], dtype=np.uint8)
        for k in [k for k, f in enumerate(flags) if f is not None]:
            out[starts[k] : starts[k + 1]] = flags[k]
        return out

    cand = [o.candidates_mm for o in observations]
    left = [o.left_px for o in observations]
    right = [o.right_px for o in observations]
    left_starts, right_starts = offsets(left), offsets(right)
    return (
        np.concatenate(cand, dtype=np.float64).reshape(-1, 3),
        np.concatenate([o.reprojection_px for o in observations], dtype=np.float64),
        np.concatenate([o.left_index for o in observations], dtype=np.intp),
        np.concatenate([o.right_index for o in observations], dtype=np.intp),
        offsets(cand),
        np.concatenate(left, dtype=np.float64).reshape(-1, 2),
        fitted(left_starts, [o.left_fitted for o in observations]),
        left_starts,
        np.concatenate(right, dtype=np.float64).reshape(-1, 2),
        fitted(right_starts, [o.right_fitted for o in observations]),
        right_starts,
    )


def _stereo_ends(t: Tracklet) -> tuple[int, int, FloatArray, FloatArray]:
    idx = np.flatnonzero(t.stereo)
    return (
        int(t.frames[idx[0]]),
        int(t.frames[idx[-1]]),
        t.positions_mm[idx[0]],
        t.positions_mm[idx[-1]],
    )


@dataclass(frozen=True)
class ChainTrack:
    """One chain of tracklets (one marker's identity) on the frame axis.

    Attributes
    ----------
    tracklets : list of int
        Indices of its tracklets.
    track : ndarray, shape (T, 3)
        Its stereo positions (mm), NaN elsewhere (``T`` = last frame of any chain + 1).
    ok : ndarray, shape (T,)
        Where ``track`` is finite.
    spread_mm : float
        RMS distance of its points from their mean (mm).
    speed_mm_s : float
        75th percentile of its frame-to-frame speed (mm/s).
    """

    tracklets: list[int]
    track: FloatArray
    ok: NDArray[np.bool_]
    spread_mm: float
    speed_mm_s: float


def link_chains(
    tracklets: Sequence[Tracklet],
    *,
    fps: float,
    min_stereo_frames: int = 3,
    link_base_mm: float = 10.0,
    link_speed_mm_s: float = 600.0,
    link_max_mm: float = 80.0,
    max_link_gap_s: float = 2.0,
) -> list[list[int]]:
    """Link tracklets into chains (one per marker identity); see :func:`select_markers`.

    Every end of a tracklet may continue at most one later start, and the links
    are chosen together (a linear assignment of ends to starts; cost the
    distance over its allowance, an unlinked end or start costs half the
    allowance): at a closure both fingers' tracklets end and start within a
    few centimetres of each other, and taking the nearest start for each end
    in turn can give the index's start to the thumb's end. Distances and gaps
    are between the last stereo point of one and the first of the other.

    Returns
    -------
    list of list of int
        Chains of tracklet indices in time order, the chain of the longest
        tracklet first.
    """
    usable = [i for i, t in enumerate(tracklets) if t.n_stereo >= min_stereo_frames]
    n = len(usable)
    if n == 0:
        return []
    stereo_ends = [_stereo_ends(tracklets[i]) for i in usable]
    spans = [e[:2] for e in stereo_ends]
    ends = [e[2:] for e in stereo_ends]
    cost = np.full((n, n), np.inf)
    for a in range(n):
        for b in range(n):
            if not spans[a][1] < spans[b][0]:
                continue  # j must start after i's last stereo point
            gap_s = (spans[b][0] - spans[a][1]) / fps
            if gap_s > max_link_gap_s:
                continue
            allow = min(link_base_mm + link_speed_mm_s * gap_s, link_max_mm)
            d = float(np.linalg.norm(ends[b][0] - ends[a][1]))
            if d <= allow:
                cost[a, b] = d / allow
    nxt = [-1] * n
    if np.any(np.isfinite(cost)):
        # Augmented assignment: ends x (starts + "no link"), starts' "no link" rows.
        big = 1e6
        aug = np.zeros((2 * n, 2 * n))
        aug[:n, :n] = np.where(np.isfinite(cost), cost, big)
        aug[:n, n:] = big
        aug[n:, :n] = big
        np.fill_diagonal(aug[:n, n:], 0.5)
        np.fill_diagonal(aug[n:, :n], 0.5)
        rows, cols = linear_sum_assignment(aug)
        for a, b in zip(rows.tolist(), cols.tolist(), strict=True):
            if a < n and b < n and aug[a, b] < big:
                nxt[a] = b
    has_prev = set(b for b in nxt if b >= 0)
    chains: list[list[int]] = []
    for a in range(n):
        if a in has_prev:
            continue
        chain, b = [], a
        while b >= 0:
            chain.append(usable[b])
            b = nxt[b]
        chains.append(chain)
    chains.sort(key=lambda ch: -max(tracklets[i].n_stereo for i in ch))
    return chains


def chain_tracks(
    tracklets: Sequence[Tracklet], chains: Sequence[Sequence[int]], *, fps: float
) -> list[ChainTrack]:
    """Each chain's stereo positions on the frame axis, with its spread and speed."""
    n_frames = 1 + max((int(tracklets[j].frames[-1]) for ch in chains for j in ch), default=-1)
    out = []
    for ch in chains:
        track = np.full((n_frames, 3), np.nan)
        for j in ch:
            t = tracklets[j]
            track[t.frames[t.stereo]] = t.positions_mm[t.stereo]
        ok = np.all(np.isfinite(track), axis=1)
        pts = track[ok]
        spread = float(np.sqrt(np.sum(np.var(pts, axis=0)))) if len(pts) > 1 else 0.0
        step = np.linalg.norm(np.diff(track, axis=0), axis=1) * fps
        step = step[np.isfinite(step)]
        speed = float(np.percentile(step, 75)) if len(step) >= 3 else 0.0
        out.append(ChainTrack(list(ch), track, ok, spread, speed))
    return out


def select_markers(
    tracklets: Sequence[Tracklet],
    *,
    fps: float,
    min_stereo_frames: int = 3,
    min_spread_mm: float = 1.0,
    link_base_mm: float = 10.0,
    link_speed_mm_s: float = 600.0,
    link_max_mm: float = 80.0,
    max_link_gap_s: float = 2.0,
    max_closed_distance_mm: float = 60.0,
) -> tuple[list[list[int]], list[str]]:
    """Link tracklets into chains and pick the thumb and index chains.

    Labelling rule (standard finger-tapping posture): among the chains that
    move (3D spread at least ``min_spread_mm``), the **index** is the fastest
    one (75th percentile of its frame-to-frame speed; the index carries most
    of the opening, reflections on the hand only follow its slow drift), and
    the **thumb** is the other moving chain that comes closest to the index
    (5th percentile of their distance: the fingertips touch at each closure,
    a reflection on the hand or a ring never does).

    Parameters
    ----------
    tracklets : sequence of Tracklet
    fps : float
        Frame rate (Hz), to turn gaps into seconds.
    min_stereo_frames : int
        Tracklets with fewer stereo points are dropped (flicker, erratic reflections).
    min_spread_mm : float
        A chain whose 3D spread is below this is not a finger (mm).
    link_base_mm, link_speed_mm_s, link_max_mm : float
        A tracklet continues a chain across a gap of ``g`` s when its first
        stereo point lies within ``min(link_base_mm + link_speed_mm_s * g,
        link_max_mm)`` of the chain's last one.
    max_link_gap_s : float
        No links across longer gaps (s).
    max_closed_distance_mm : float
        A warning is given when thumb and index never come closer (mm).

    Returns
    -------
    chains : list of list of int
        ``[thumb, index]`` chains of tracklet indices (fewer when not found).
    warnings : list of str
    """
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    warnings: list[str] = []
    chains = link_chains(
        tracklets,
        fps=fps,
        min_stereo_frames=min_stereo_frames,
        link_base_mm=link_base_mm,
        link_speed_mm_s=link_speed_mm_s,
        link_max_mm=link_max_mm,
        max_link_gap_s=max_link_gap_s,
    )
    stats = [
        (c.track, c.ok, c.spread_mm, c.speed_mm_s) for c in chain_tracks(tracklets, chains, fps=fps)
    ]
    moving = [k for k, st in enumerate(stats) if st[2] >= min_spread_mm]
    if not moving:
        warnings.append("no moving marker was found; thumb and index need two")
        return [], warnings
    # The index finger: the fastest chain (it carries most of the opening).
    index = max(moving, key=lambda k: stats[k][3])
    # The thumb: the moving chain that comes closest to the index finger (the
    # fingertips touch at every closure; reflections on the hand stay farther).
    best_thumb: tuple[float, int] | None = None
    for k in moving:
        if k == index:
            continue
        common = stats[k][1] & stats[index][1]
        if np.count_nonzero(common) < min_stereo_frames:
            continue
        dist = np.linalg.norm(stats[k][0][common] - stats[index][0][common], axis=1)
        closest = float(np.percentile(dist, 5))
        if best_thumb is None or closest < best_thumb[0]:
            best_thumb = (closest, k)
    if best_thumb is None:
        warnings.append("only one moving marker was found; thumb and index need two")
        return [sorted(chains[index], key=lambda j: int(tracklets[j].frames[0]))], warnings
    if best_thumb[0] > max_closed_distance_mm:
        warnings.append(
            f"the two finger markers never came closer than {best_thumb[0]:.0f} mm; check that"
            " the fingertips touch at each closure and that the markers sit on the nails"
        )
    ordered = [chains[best_thumb[1]], chains[index]]
    return [sorted(ch, key=lambda j: int(tracklets[j].frames[0])) for ch in ordered], warnings


def fill_gaps(
    positions_mm: FloatArray,
    measured: NDArray[np.bool_],
    *,
    max_gap_frames: int,
    rig: StereoRig | None = None,
    single_view_camera: NDArray[np.int_] | None = None,
    single_view_px: FloatArray | None = None,
    merged: NDArray[np.bool_] | None = None,
    max_merged_gap_frames: int | None = None,
    context_frames: int = 6,
    poly_degree: int = 7,
    path_window_frames: int = 35,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Fill short gaps between measured frames of one marker.

    Parameters
    ----------
    positions_mm : ndarray, shape (T, 3)
        Measured positions (other rows are ignored).
    measured : ndarray, shape (T,)
        Which rows are measured.
    max_gap_frames : int
        Gaps of at most this many frames, with measured frames on both sides,
        are filled; longer ones and gaps at either end are left alone.
    rig, single_view_camera, single_view_px : optional
        ``single_view_camera[t]`` is 0 (left) or 1 (right) when only that
        camera saw the marker at frame ``t`` (else -1), at pixel
        ``single_view_px[t]``; the filled point is then put on that
        camera's ray at the interpolated depth.
    merged : ndarray, shape (T,), optional
        Frames in which this marker's image merged with another marker's in
        one camera while the other camera saw it (``single_view_camera``).
    max_merged_gap_frames : int, optional
        A gap longer than ``max_gap_frames`` is still filled when every frame
        of it is ``merged`` and it is at most this long: only the depth is
        interpolated there. Default ``max_gap_frames``.
    context_frames : int
        Measured frames on each side that shape the spline (at least).
    poly_degree : int
        Degree of the time polynomial fitted across a gap with single-view
        observations, at most ``1 + 2 n`` where ``n`` is the fewer of the measured
        frames it has on either side (one measured frame past a gap let degree 7
        swing 15 mm off on a nail-glint recording; 0.1 mm with degree 3).
    path_window_frames : int
        Measured frames this far on either side of a gap sample the marker's
        path for single-view points.

    Returns
    -------
    positions_mm : ndarray, shape (T, 3)
        Copy with filled rows.
    filled : ndarray, shape (T,)
        Which rows were filled.
    """
    pos = np.array(positions_mm, dtype=np.float64, copy=True)
    meas = np.asarray(measured, dtype=bool)
    if pos.ndim != 2 or pos.shape[1] != 3 or meas.shape != (pos.shape[0],):
        raise ValueError(
            f"positions_mm must be (T, 3) and measured (T,), got {pos.shape}, {meas.shape}"
        )
    if max_gap_frames < 0:
        raise ValueError(f"max_gap_frames must be >= 0, got {max_gap_frames}")
    filled = np.zeros(len(pos), bool)
    idx = np.flatnonzero(meas)
    views = rig is not None and single_view_camera is not None and single_view_px is not None
    long_limit = max_gap_frames
    if views and merged is not None and max_merged_gap_frames is not None:
        long_limit = max(max_gap_frames, max_merged_gap_frames)
    if len(idx) < 2 or long_limit == 0:
        return pos, filled
    holes = np.flatnonzero(np.diff(idx) > 1)
    for h in holes:
        a, b = int(idx[h]), int(idx[h + 1])  # measured frames around the gap
        gap = b - a - 1
        if gap > max_gap_frames and not (
            gap <= long_limit
            and merged is not None
            and single_view_camera is not None
            and np.all(merged[a + 1 : b] & (single_view_camera[a + 1 : b] >= 0))
        ):
            continue
        width = max(context_frames, gap)
        before = idx[max(0, h - width + 1) : h + 1]
        after = idx[h + 1 : h + 1 + width]
        # Only nearby measured neighbours (far ones would not describe this motion).
        before = before[before >= a - 3 * width]
        after = after[after <= b + 3 * width]
        knots = np.concatenate([before, after])
        t_fill = np.arange(a + 1, b)
        if len(knots) >= 4:
            spline = CubicSpline(knots, pos[knots], axis=0)
            est = spline(t_fill)
        else:
            w = (t_fill - a) / (b - a)
            est = pos[a] * (1 - w[:, None]) + pos[b] * w[:, None]
        if rig is not None and single_view_camera is not None and single_view_px is not None:
            sv = single_view_camera[t_fill] >= 0
            if np.any(sv):
                lo, hi = max(0, a - path_window_frames), b + path_window_frames + 1
                window = np.arange(lo, min(hi, len(pos)))
                path = pos[window[meas[window]]]
                est = _fit_gap_with_views(
                    rig,
                    pos,
                    knots,
                    t_fill,
                    single_view_camera,
                    single_view_px,
                    est,
                    degree=min(poly_degree, 1 + 2 * min(len(before), len(after))),
                    path_mm=path,
                )
        pos[t_fill] = est
        filled[t_fill] = True
    return pos, filled


def _fit_gap_with_views(
    rig: StereoRig,
    pos: FloatArray,
    knots: NDArray[np.int_],
    t_fill: NDArray[np.int_],
    sv_camera: NDArray[np.int_],
    sv_px: FloatArray,
    spline_est: FloatArray,
    *,
    degree: int,
    path_mm: FloatArray | None = None,
) -> FloatArray:
    """Positions across a gap from a time polynomial fitted to 3D points and 2D views.

    Unknowns: the coefficients of ``X(t)`` (a polynomial of ``degree`` per
    coordinate). Equations (linear least squares, all in mm): ``X(t_k) =
    P_k`` at the measured neighbours, and for every single-view frame the two
    linear ray constraints ``(R_0 - x R_2) X = x t_z - t_x`` (same with
    ``y``), whose residual is the lateral miss (mm at the marker's depth).
    The views fix where along its path the marker was; the smooth time
    polynomial then only has to supply the depth. Each filled point is finally
    put on its camera's ray: where the ray passes the marker's own path in
    the neighbouring cycles (``path_mm``, see :func:`_ray_meets_path`), or
    else at the polynomial's depth.
    """
    sv_frames = t_fill[sv_camera[t_fill] >= 0]
    t_all = np.concatenate([knots, sv_frames]).astype(np.float64)
    t_mid = 0.5 * (t_all.min() + t_all.max())
    half = max(0.5 * (t_all.max() - t_all.min()), 1.0)
    deg = int(min(degree, len(knots) + 2 * len(sv_frames) // 3 - 1))
    if deg < 1:
        return spline_est

    def basis(t: NDArray[np.int_]) -> FloatArray:
        result: NDArray[np.float64] = ((np.asarray(t, dtype=np.float64) - t_mid) / half)[
            :, None
        ] ** np.arange(deg + 1)
        return result

    n_c = deg + 1
    rows: list[FloatArray] = []
    rhs: list[float] = []
    b_k = basis(knots)
    for axis in range(3):
        block = np.zeros((len(knots), 3 * n_c))
        block[:, axis * n_c : (axis + 1) * n_c] = b_k
        rows.append(block)
        rhs.extend(pos[knots, axis].tolist())
    b_s = basis(sv_frames)
    for k, t in enumerate(sv_frames):
        cam = rig.cameras[int(sv_camera[t])]
        xy = cam.undistort_points(sv_px[t][None])[0]
        if not np.all(np.isfinite(xy)):
            continue
        R, tr = cam.R_cam_from_world, cam.t_cam_from_world_mm
        for a in range(2):
            coef = R[a] - xy[a] * R[2]  # (3,)
            row = np.concatenate([coef[axis] * b_s[k] for axis in range(3)])
            rows.append(row[None])
            rhs.append(float(xy[a] * tr[2] - tr[a]))
    A = np.vstack(rows)
    sol, *_ = np.linalg.lstsq(A, np.asarray(rhs), rcond=None)
    coeffs = sol.reshape(3, n_c)
    est = basis(t_fill) @ coeffs.T  # (n, 3)
    out = est.copy()
    for k, t in enumerate(t_fill):
        ci = int(sv_camera[t])
        if ci < 0:
            continue
        cam = rig.cameras[ci]
        origin, direction = cam.backproject(sv_px[t][None])
        if not np.all(np.isfinite(direction)):
            continue
        depth = cam.to_camera(est[k][None])[0, 2]
        pt = cam.backproject_depth(sv_px[t][None], depth)[0]
        if path_mm is not None and len(path_mm):
            on_path = _ray_meets_path(origin[0], direction[0], path_mm, est[k])
            if on_path is not None:
                pt = 0.5 * (pt + on_path)
        out[k] = pt
    result: NDArray[np.float64] = out
    return result


def _ray_meets_path(
    origin: FloatArray,
    direction: FloatArray,
    path_mm: FloatArray,
    guess_mm: FloatArray,
    *,
    near_guess_mm: float = 12.0,
    near_ray_mm: float = 1.0,
    n_points: int = 6,
    min_extent_mm: float = 0.5,
    max_cos: float = 0.95,
) -> FloatArray | None:
    """Where a camera ray crosses the path a marker followed in neighbouring cycles.

    Tapping repeats the same hinge motion, so the measured positions of the
    surrounding second sample the 3D path densely. Near the time-interpolated
    guess, the ``n_points`` path points closest to the ray define a local
    line (principal direction); the result is the point of the ray closest
    to that line. Only the depth along the ray comes from the path; the
    observation fixes the rest. None when the path does not pass close to
    the ray, or runs along it.
    """
    near = path_mm[np.linalg.norm(path_mm - guess_mm, axis=1) < near_guess_mm]
    if len(near) < 3:
        return None
    rel = near - origin
    along = rel @ direction
    dist_ray = np.linalg.norm(rel - along[:, None] * direction, axis=1)
    order = np.argsort(dist_ray)[:n_points]
    if len(order) < 3 or dist_ray[order[0]] > near_ray_mm:
        return None
    pts = near[order]
    centre = pts.mean(axis=0)
    _, sing, vt = np.linalg.svd(pts - centre, full_matrices=False)
    e = vt[0]
    if sing[0] < min_extent_mm * np.sqrt(len(pts)):
        return None  # a cluster (the marker rested here): no direction to follow
    c = float(np.dot(direction, e))
    if abs(c) > max_cos:
        return None
    w = origin - centre
    # Closest points of the lines origin + s d and centre + u e (|d| = |e| = 1).
    d_w, e_w = float(np.dot(direction, w)), float(np.dot(e, w))
    s_ray = (c * e_w - d_w) / (1.0 - c * c)
    return origin + s_ray * direction


@dataclass(frozen=True)
class Tracks:
    """Labelled marker trajectories of a recording.

    Attributes
    ----------
    positions_mm : ndarray, shape (T, M, 3)
        NaN where missing; marker order as ``marker_names``.
    status : ndarray, shape (T, M)
        ``"measured"``, ``"interpolated"`` or ``"missing"``.
    reprojection_px : ndarray, shape (T, M)
        NaN unless measured.
    marker_names : tuple of str
    warnings : list of str
    overlap_frames : int
        Frames in which the two markers' images touched in a camera, so that
        camera did not measure them (``marker_diameter_px`` of :func:`track_markers`),
        or merged there (set aside by the detector) and were filled from the other
        camera (``merged``).
    merged : ndarray, shape (T, M), optional
        ``interpolated`` frames in which the markers' images merged in one
        camera while the other camera saw each of them: only the depth is
        interpolated.
    """

    positions_mm: FloatArray
    status: NDArray[np.str_]
    reprojection_px: FloatArray
    marker_names: tuple[str, ...]
    warnings: list[str]
    overlap_frames: int = 0
    merged: NDArray[np.bool_] | None = None


def track_markers(
    rig: StereoRig,
    observations: Sequence[FrameObservations],
    *,
    fps: float,
    max_gap_s: float = 0.1,
    max_merged_gap_s: float = 0.15,
    swap_labels: bool = False,
    gate_mm: float | None = None,
    max_reprojection_px: float | None = None,
    marker_diameter_px: tuple[float, float] | None = None,
    task: Task | str = Task.FINGER_TAPPING,
) -> Tracks:
    """Thumb and index trajectories from per-frame stereo candidates.

    Parameters
    ----------
    rig : StereoRig
    observations : sequence of FrameObservations
        One per left frame (``T`` frames).
    fps : float
        Frame rate (Hz).
    max_gap_s : float
        Gaps up to this long (s) are interpolated; longer ones stay missing.
    max_merged_gap_s : float
        Gaps in which the markers' images merged in one camera in every frame
        (a closure or closed pause seen along the opening direction) while the
        other camera saw each marker are interpolated up to this long (s): only
        the depth is. At least ``max_gap_s``.
    swap_labels : bool
        Exchange the automatic thumb/index labels.
    gate_mm : float, optional
        Tracking gate after one frame (mm); default ``5 mm + 8e4 mm/s² · dt²``
        (the prediction error of a constant-velocity model at tapping
        accelerations).
    max_reprojection_px : float, optional
        Measured points with a larger reprojection error become gaps; default
        ``max(1 px, 5 x`` the median of the track).
    marker_diameter_px : (float, float), optional
        Typical marker diameter in the left and right images (px).  When
        given, a camera in which the two markers' images come closer than a
        diameter + 2 px (touching or overlapping: each centre is pulled by
        the other) does not measure them; the other camera and the track's
        path fill those frames as ``interpolated`` (see :func:`build_tracklets`).
    task : Task or str
        Finger tapping (default) is labelled by :func:`select_markers`; the
        other tasks by their marker protocol (:func:`core.protocols.label_chains`).

    Returns
    -------
    Tracks
        ``M = 2`` markers for finger tapping (thumb, index); the protocol's
        markers for another task. ``swap_labels`` applies to finger tapping only.
    """
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if max_gap_s < 0:
        raise ValueError(f"max_gap_s must be >= 0, got {max_gap_s}")
    if not max_merged_gap_s >= max_gap_s:
        raise ValueError(
            f"max_merged_gap_s must be >= max_gap_s ({max_gap_s}), got {max_merged_gap_s}"
        )
    n_frames = len(observations)
    dt = 1.0 / fps
    if gate_mm is None:
        gate_mm = 5.0 + 8e4 * dt * dt
    max_gap_frames = int(np.floor(max_gap_s * fps + 1e-9))
    max_sv_frames = int(np.floor(max_merged_gap_s * fps + 1e-9))
    overlaps: list[int] = []
    tracklets = build_tracklets(
        rig,
        observations,
        gate_mm=gate_mm,
        max_single_view_frames=max_sv_frames + 2,
        merge_px=None
        if marker_diameter_px is None
        else (marker_diameter_px[0] + 2.0, marker_diameter_px[1] + 2.0),
        overlap_frames=overlaps,
    )
    task = Task(task)
    names: tuple[str, ...] = MARKER_NAMES
    if task is Task.FINGER_TAPPING:
        chains, warnings = select_markers(tracklets, fps=fps)
    else:
        linked = chain_tracks(tracklets, link_chains(tracklets, fps=fps), fps=fps)
        picks, warnings = label_chains(task, [c.track for c in linked], fps=fps)
        chains = [linked[k].tracklets if k is not None else [] for k in picks]
        names = protocol_for(task).labels
    m = len(names)
    positions = np.full((n_frames, m, 3), np.nan)
    status = np.full((n_frames, m), MISSING, dtype=object)
    reproj = np.full((n_frames, m), np.nan)
    per_marker = []
    for chain in chains:
        pos = np.full((n_frames, 3), np.nan)
        rep = np.full(n_frames, np.nan)
        sv_cam = np.full(n_frames, -1, dtype=int)
        sv_px = np.full((n_frames, 2), np.nan)
        for j in chain:
            t = tracklets[j]
            st = t.stereo
            pos[t.frames[st]] = t.positions_mm[st]
            rep[t.frames[st]] = t.reprojection_px[st]
            sv = ~st
            sv_cam[t.frames[sv]] = t.kind[sv] - 1
            sv_px[t.frames[sv]] = t.pixels_px[sv]
        meas = np.isfinite(rep)
        # Outlier rejection: points that do not reproject well become gaps.
        if np.any(meas):
            limit = max_reprojection_px
            if limit is None:
                limit = max(1.0, 5.0 * float(np.median(rep[meas])))
            bad = meas & (rep > limit)
            pos[bad] = np.nan
            rep[bad] = np.nan
            meas &= ~bad
        per_marker.append((pos, rep, sv_cam, sv_px, meas))
    # Merged: two markers seen by the same single camera in one frame (their images
    # merged in the other, or both hidden there: never one marker alone).
    cams_sv = np.array([pm[2] for pm in per_marker]).reshape(len(per_marker), n_frames)
    merged = np.zeros((n_frames, m), dtype=bool)
    for k in range(len(per_marker)):
        same = (cams_sv == cams_sv[k]) & (cams_sv[k] >= 0)
        merged[:, k] = np.count_nonzero(same, axis=0) >= 2
    for k, (pos, rep, sv_cam, sv_px, meas) in enumerate(per_marker):
        filled_pos, filled = fill_gaps(
            pos,
            meas,
            max_gap_frames=max_gap_frames,
            rig=rig,
            single_view_camera=sv_cam,
            single_view_px=sv_px,
            merged=merged[:, k],
            max_merged_gap_frames=max_sv_frames,
        )
        positions[:, k] = np.where(meas[:, None] | filled[:, None], filled_pos, np.nan)
        status[meas, k] = MEASURED
        status[filled & ~meas, k] = INTERPOLATED
        reproj[meas, k] = rep[meas]
        merged[:, k] &= filled & ~meas
    if task is Task.FINGER_TAPPING:
        order = [1, 0] if swap_labels else [0, 1]
        positions = positions[:, order]
        status = status[:, order]
        reproj = reproj[:, order]
        merged = merged[:, order]
    return Tracks(
        positions_mm=positions,
        status=status.astype(str),
        reprojection_px=reproj,
        marker_names=names,
        warnings=warnings,
        # blocked by the tracker, or both markers seen by the same single camera
        overlap_frames=len(set(overlaps) | set(np.flatnonzero(merged.any(axis=1)).tolist())),
        merged=merged,
    )

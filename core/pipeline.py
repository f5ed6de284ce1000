"""From a stereo recording and a rig to labelled 3D marker trajectories (``analyze``).

Stages (one module each, see ``docs/architecture.md`` and ``docs/tracking.md``):

1. **Videos** (:mod:`core.video`): both are probed and checked against each
   other and the rig before any work.
2. **Detection** (:mod:`core.markers`): both videos are decoded and searched
   for markers at the same time, one thread per camera (decoding and the
   compiled marker search release the GIL, so the two cameras run on two
   cores). Only the few detections of each frame are kept: memory does not
   grow with the length of the video beyond a few numbers per frame. After a full-frame search, each frame is only searched
   around the positions predicted from the previous frames; a full-frame
   search is repeated every ``FULL_SEARCH_EVERY`` frames and whenever fewer
   markers are found than the last full searches typically saw (so a marker
   that reappears after a short occlusion is picked up at once; after two such
   searches in a row that found nothing more, only on every other frame, so a
   reappearing marker is picked up at most one frame later).
3. **Synchronisation** (:mod:`core.timing`, :mod:`core.clock`,
   :mod:`core.sync`): each frame's capture time, the time model (offset,
   drift, lost frames, rolling shutter) from the marker motion, or the offset
   given; the right markers are brought to the left frames' instants.
4. **Matching and triangulation** (:mod:`core.matching`,
   :mod:`core.triangulation`): every epipolar-consistent pair of a frame is
   triangulated (linear start, reprojection refinement); pairs that do not
   reproject are dropped.
5. **Tracks** (:mod:`core.tracks`): identities, distractor rejection, gap
   filling, thumb/index labels.
6. **Metrics** (:mod:`core.metrics`): taps and per-trial measures, at the
   left frames' real capture times (:mod:`core.resample`).

:func:`write_analysis` writes ``markers.csv`` and ``result.json`` exactly as
INTERFACES.md defines them.
"""

from __future__ import annotations

import io
import json
import math
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from numpy.typing import NDArray

from core.camera import Camera, StereoRig
from core.clock import TimeModelResult, corrected_times, synchronise
from core.cycles import TaskMetrics, compute_task_metrics, with_common_keys
from core.errors import DetectionError, InputError
from core.markers import EXPECTED_COUNT_FULL_SEARCHES as EXPECTED_COUNT_FULL_SEARCHES
from core.markers import FULL_SEARCH_EVERY as FULL_SEARCH_EVERY
from core.markers import MAX_DETECTIONS_PER_FRAME as MAX_DETECTIONS_PER_FRAME
from core.markers import (
    UNPRODUCTIVE_FALLBACKS_BEFORE_BACKOFF as UNPRODUCTIVE_FALLBACKS_BEFORE_BACKOFF,
)
from core.markers import (  # the per-camera search lives with the detector (light to import)
    Detector,
    ImagePatch,
    MarkerParams,
    _CameraDetections,
    _default_detector,
)
from core.markers_csv import MARKERS_CSV_HEADER, MarkerTable
from core.markers_csv import write_markers_csv as write_marker_table
from core.matching import concatenate_frames, frame_pairs_epipolar_px
from core.merged import measure_merged

# Imported with the module, not inside the timed call (scipy's first import costs ~0.5 s).
from core.metrics import TappingMetrics, compute_metrics
from core.overlay import CameraOverlay, camera_overlay
from core.progress import ProgressCallback, report
from core.protocols import protocol_for
from core.resample import uniform_trajectories
from core.tasks import Task, parse_task
from core.timing import (
    FrameTimes,
    describe_lost_frames,
    fit_to_frames,
    frame_times_from_timestamps,
    read_times_csv,
)
from core.tracks import INTERPOLATED, MEASURED, MISSING, FrameObservations, track_markers
from core.triangulation import triangulate
from core.version import software_document
from core.video import VideoInfo

FloatArray = NDArray[np.float64]

#: Receives each decoded frame of one video (``analyze_recording(frame_sinks=...)``).
FrameSink = Callable[[NDArray[np.uint8]], None]

RESULT_FORMAT = "bradyscope.result/1"
CSV_HEADER = MARKERS_CSV_HEADER  # the columns of markers.csv (core.markers_csv)

#: Pairs farther from the epipolar constraint are not stereo candidates (px).
MAX_EPIPOLAR_PX = 3.0
#: Stereo candidates with a larger reprojection error are dropped (px).
MAX_CANDIDATE_REPROJECTION_PX = 2.0


@dataclass(frozen=True)
class Analysis:
    """The measurement of one stereo recording.

    Attributes
    ----------
    fps : float
        Frame rate (Hz) of the (left) video.
    frame_numbers : ndarray, shape (T,)
        Left video frame numbers ``0 .. T-1``.
    positions_mm : ndarray, shape (T, M, 3)
        Marker positions in the rig's world (left-camera) frame (mm); NaN
        where missing.
    status : ndarray, shape (T, M)
        ``"measured"``, ``"interpolated"`` or ``"missing"``.
    reprojection_px : ndarray, shape (T, M)
        Reprojection error of measured points (px); NaN otherwise.
    marker_names : tuple of str
        ``("thumb", "index")``.
    sync : dict
        The ``sync`` object of result.json.
    metrics : TappingMetrics or None
        Tapping metrics (``core.metrics``), None when they could not be computed.
    quality : dict
        ``tracked_fraction``, ``interpolated_fraction``, ``reprojection_px_median``
        and more (see ``docs/tracking.md``).
    warnings : list of str
        Things a technician should know about this measurement.
    frame_time_s : ndarray, shape (T,), optional
        Capture time of each left frame (s): its timestamp, with lost frames
        put back (``core.clock``); ``frame / fps`` when absent.
    detections_px : (list, list) of ndarray (N_f, 2), optional
        The detector's marker centres in each frame of the left and of the
        right video (px, each video's own frame numbers), before synchronisation.
    right_left_frame : ndarray, shape (F_right,), optional
        Where each right frame lies on the left frame axis (the time model:
        right frame ``j`` is left frame ``j + K`` for a whole-frame offset).
    right_fps : float, optional
        Frame rate of the right video (Hz).
    task : str
        The examination task (:class:`core.tasks.Task` value), ``"finger_tapping"`` by default.
    task_metrics : TaskMetrics or None
        The cycle metrics of another task (``core.cycles``); ``metrics`` is then None.
    """

    fps: float
    frame_numbers: NDArray[np.int_]
    positions_mm: FloatArray
    status: NDArray[np.str_]
    reprojection_px: FloatArray
    marker_names: tuple[str, ...]
    sync: dict[str, Any]
    metrics: TappingMetrics | None = None
    quality: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    frame_time_s: FloatArray | None = None
    detections_px: tuple[list[FloatArray], list[FloatArray]] | None = None
    right_left_frame: FloatArray | None = None
    right_fps: float | None = None
    task: str = Task.FINGER_TAPPING.value
    task_metrics: TaskMetrics | None = None

    @property
    def time_s(self) -> FloatArray:
        """Capture time of each frame (s, left clock): ``frame_time_s``, else ``frame / fps``."""
        if self.frame_time_s is not None:
            return np.asarray(self.frame_time_s, dtype=np.float64)
        return self.frame_numbers / self.fps

    def marker_table(self) -> MarkerTable:
        """The trajectories as :class:`core.markers_csv.MarkerTable` (what markers.csv holds)."""
        return MarkerTable(
            fps=float(self.fps),
            frames=np.asarray(self.frame_numbers, dtype=np.int64),
            labels=tuple(self.marker_names),
            positions_mm=self.positions_mm,
            status=self.status,
            reprojection_px=self.reprojection_px,
            frame_time_s=self.time_s,
        )

    def overlays(self, rig: StereoRig) -> list[CameraOverlay]:
        """What the review view draws on each video (:mod:`core.overlay`): left, then right.

        Raises
        ------
        ValueError
            The analysis kept no detections (made without them).
        """
        if self.detections_px is None or self.right_left_frame is None:
            raise ValueError("this analysis kept no detections to draw")
        left_det, right_det = self.detections_px
        return [
            camera_overlay(rig.left, self.positions_mm, self.marker_names, left_det, fps=self.fps),
            camera_overlay(
                rig.right,
                self.positions_mm,
                self.marker_names,
                right_det,
                fps=float(self.right_fps or self.fps),
                left_frame=self.right_left_frame,
            ),
        ]

    def result_document(self) -> dict[str, Any]:
        """``result.json`` as INTERFACES.md defines it (format ``bradyscope.result/1``)."""
        metrics: dict[str, Any] = {}
        taps: list[dict[str, Any]] = []
        extra: dict[str, Any] = {}
        if self.metrics is not None:
            # The common keys of every task (docs/interfaces.md), beside finger tapping's own.
            res = with_common_keys(self.metrics.to_result(), self.metrics)
            metrics = dict(res["metrics"])
            taps = list(res.get("taps", []))
            extra = {k: v for k, v in res.items() if k not in ("metrics", "taps")}
        elif self.task_metrics is not None:
            res = self.task_metrics.to_result()
            metrics = dict(res["metrics"])
            extra = {k: v for k, v in res.items() if k != "metrics"}
        quality = dict(self.quality)
        quality["warnings"] = list(self.warnings)
        doc: dict[str, Any] = {
            "format": RESULT_FORMAT,
            "task": str(self.task),
            "fps": float(self.fps),
            "sync": dict(self.sync),
            "metrics": _json_clean(metrics),
            "taps": _json_clean(taps),
            "quality": _json_clean(quality),
            "markers": list(self.marker_names),
            "frame_count": len(self.frame_numbers),
            "software": software_document(),
        }
        for k, v in extra.items():
            doc.setdefault(k, _json_clean(v))
        return doc


def _json_clean(obj: Any) -> Any:
    """Numpy scalars to Python, non-finite floats to None (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {str(k): _json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_clean(obj.tolist())
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


# ----------------------------------------------------------------------------- detection


def _detect_videos(
    paths: tuple[Path, Path],
    expected_counts: tuple[int, int],
    detect: Detector | None,
    progress: ProgressCallback | None,
    *,
    marker_params: MarkerParams | None = None,
    timestamps: tuple[list[float], list[float]] | None = None,
    frame_sinks: tuple[FrameSink | None, FrameSink | None] | None = None,
) -> tuple[
    list[FloatArray], list[FloatArray], dict[str, float], tuple[dict[int, list[ImagePatch]], ...]
]:
    """Decode and detect both videos concurrently; per-frame (N, 2) pixel arrays, and the
    pixels each camera kept around blobs that are not one whole marker (``core.merged``).

    ``detect`` None means ``core.markers.detect_markers`` with ``marker_params``.
    One thread per camera: decoding and the compiled search release the GIL,
    so the two cameras use two cores without a worker process each (which
    cost ~0.3 s of CPU to start and ~190 MB of memory; a custom ``detect``
    written in Python shares the GIL). Each camera's thread decodes its own
    frames, unless cores are spare for a decoding thread each
    (``core.video.decode_in_background``).
    """
    from core.video import decode_in_background, decoder_threads_for, iter_frames

    detector = detect if detect is not None else _default_detector(marker_params)
    decoder_threads = decoder_threads_for(2)
    background = decode_in_background(2)
    sinks = frame_sinks if frame_sinks is not None else (None, None)
    states = [_CameraDetections(detector), _CameraDetections(detector)]
    errors: list[BaseException] = []
    halt = threading.Event()

    def work(k: int) -> None:
        try:
            times = None if timestamps is None else timestamps[k]
            sink = sinks[k]
            for image in iter_frames(
                paths[k],
                gray=True,
                expected_count=expected_counts[k],
                times_out=times,
                decoder_threads=decoder_threads,
                background=background,
            ):
                if halt.is_set():
                    return
                states[k].process(image)
                if sink is not None:
                    sink(image)
        except BaseException as exc:  # re-raised in the calling thread
            errors.append(exc)
            halt.set()

    total = int(sum(expected_counts))
    threads = [
        threading.Thread(target=work, args=(k,), name=f"detect-{k}", daemon=True) for k in (0, 1)
    ]
    for t in threads:
        t.start()
    report(progress, "detection", 0, total)
    while True:  # reported once more when both are done, however soon that is
        for t in threads:
            t.join(timeout=0.25)
        report(progress, "detection", min(total, sum(len(s.frames) for s in states)), total)
        if not any(t.is_alive() for t in threads):
            break
    if errors:
        raise errors[0]
    info = {
        "full_searches_left": states[0].n_full,
        "full_searches_right": states[1].n_full,
        # frames with a marker image set aside: partly hidden or merged (core.markers)
        "set_aside_frames_left": states[0].n_set_aside,
        "set_aside_frames_right": states[1].n_set_aside,
        "marker_diameter_px_left": states[0].diameter_px,
        "marker_diameter_px_right": states[1].diameter_px,
    }
    return states[0].frames, states[1].frames, info, (states[0].patches, states[1].patches)


def _undistort_all(cam: Camera, frames: list[FloatArray]) -> list[FloatArray]:
    """Undistorted normalized points per frame, with one vectorised call."""
    counts = [len(f) for f in frames]
    if sum(counts) == 0:
        return [np.zeros((0, 2)) for _ in frames]
    flat = cam.undistort_points(np.concatenate(frames, axis=0))
    return list(np.split(flat, np.cumsum(counts)[:-1]))


def _observations(
    rig: StereoRig,
    left_px: list[FloatArray],
    right_px: list[FloatArray],
    left_norm: list[FloatArray],
    right_norm: list[FloatArray],
    offset: int,
    *,
    fitted: tuple[list[NDArray[np.bool_]], list[NDArray[np.bool_]]] | None = None,
) -> tuple[list[FrameObservations], int]:
    """Stereo candidates (every gated pair, triangulated) for each left frame.

    ``fitted``: per frame of each video, which detections are markers measured in a
    merged image (``core.merged``); the tracker uses them where images touch.

    All pairs of all frames are gated at once (:func:`core.matching.frame_pairs_epipolar_px`)
    and triangulated in one call; each frame then gets its slice, in pair order.
    """
    n_left = len(left_px)
    pairs = frame_pairs_epipolar_px(rig, left_norm, right_norm, offset)
    with np.errstate(invalid="ignore"):
        gated = np.flatnonzero(pairs.epipolar_px <= MAX_EPIPOLAR_PX)
    frames = pairs.frame[gated]
    li_arr = pairs.left_index[gated]
    ri_arr = pairs.right_index[gated]
    if len(frames):
        left_flat, left_counts = concatenate_frames(left_px)
        right_flat, right_counts = concatenate_frames(right_px)
        if left_counts.tolist() != [len(f) for f in left_norm] or right_counts.tolist() != [
            len(f) for f in right_norm
        ]:
            raise ValueError("the normalized points do not match the pixel points frame by frame")
        tri = triangulate(rig, left_flat[pairs.left_row[gated]], right_flat[pairs.right_row[gated]])
        ok = tri.valid & (tri.reprojection_px <= MAX_CANDIDATE_REPROJECTION_PX)
        points, reproj = tri.points_mm[ok], tri.reprojection_px[ok]
        li_arr, ri_arr = li_arr[ok], ri_arr[ok]
        bounds = np.searchsorted(frames[ok], np.arange(n_left + 1)).tolist()
    else:
        ok = np.zeros(0, bool)
        points, reproj = np.zeros((0, 3)), np.zeros(0)
        bounds = [0] * (n_left + 1)
    n_rejected = int(np.count_nonzero(~ok))
    no_right = np.zeros((0, 2))
    n_right = len(right_px)
    obs: list[FrameObservations] = []
    for i in range(n_left):
        j = i - offset
        b0, b1 = bounds[i], bounds[i + 1]
        paired = 0 <= j < n_right
        fl = fr = None
        if fitted is not None:
            fl = fitted[0][i] if fitted[0][i].any() else None
            fr = fitted[1][j] if paired and fitted[1][j].any() else None
        obs.append(
            FrameObservations(
                points[b0:b1],
                reproj[b0:b1],
                li_arr[b0:b1],
                ri_arr[b0:b1],
                left_px[i],
                right_px[j] if paired else no_right,
                left_fitted=fl,
                right_fitted=fr,
            )
        )
    return obs, n_rejected


def _compute_metrics(
    positions_mm: FloatArray,
    fps: float,
    status: NDArray[np.str_],
    time_s: FloatArray | None = None,
    *,
    max_gap_s: float = 0.1,
    merged: NDArray[np.bool_] | None = None,
) -> tuple[TappingMetrics | None, list[str]]:
    """Tapping metrics (core.metrics) at the frames' real times ``time_s`` (core.resample:
    an even grid from uneven frame times); None with a warning when they cannot be computed.
    ``merged`` (T, M): filled-in positions whose images merged in one camera
    (``Tracks.merged``)."""
    measured = status == MEASURED  # core.metrics: False where filled in or missing
    even = uniform_trajectories(positions_mm, measured, time_s, fps, max_gap_s=max_gap_s)
    sv = merged
    if sv is not None and even.resampled and time_s is not None:
        # each instant of the even grid takes the frame at or before it
        grid = even.t0_s + np.arange(even.positions_mm.shape[0]) / even.fps
        at = np.clip(np.searchsorted(np.asarray(time_s), grid + 1e-9, side="right") - 1, 0, None)
        sv = sv[np.minimum(at, len(sv) - 1)]
    try:
        return compute_metrics(even.positions_mm, even.fps, measured=even.measured, merged=sv), []
    except ValueError as exc:
        return None, [f"tapping metrics could not be computed: {exc}"]


#: How core.clock's warning about many lost frames starts (it lists every frame number).
_CLOCK_LOST_FRAMES = " frames were lost during the recording (left after frames "


def _lost_frames_in_words(
    warnings: list[str], sync: dict[str, Any], times: Sequence[FrameTimes]
) -> list[str]:
    """The time model's warnings, its warning about many lost frames saying per camera how
    many were lost in how many gaps, the longest and where
    (:func:`core.timing.describe_lost_frames`), not every frame number of each loss."""
    out = []
    for text in warnings:
        head, sep, advice = text.partition("); ")
        if _CLOCK_LOST_FRAMES in head and sep:
            n = head.split(" ", 1)[0]
            left, right = (
                describe_lost_frames(sync.get(f"dropped_frames_{side}") or [], fps=t.fps)
                for side, t in zip(("left", "right"), times, strict=True)
            )
            text = (
                f"{n} frames were lost during the recording (left camera: {left};"
                f" right camera: {right}); {advice}"
            )
        out.append(text)
    return out


def _few_whole_taps(metrics: dict[str, Any], task: Task) -> list[str]:
    """A warning when most taps (cycles) are not measured whole: their amplitude and speed
    are left out (filled-in frames at the widest opening or a closure), which the metrics
    alone would only show as missing values."""
    n, whole = int(metrics.get("tap_count") or 0), int(metrics.get("reliable_tap_count") or 0)
    if n < 3 or whole >= 0.5 * n:
        return []
    word = task.cycle_word
    measured = f"are over those {whole} only" if whole else "could not be measured"
    return [
        f"only {whole} of the {n} {word}s were measured whole (the others have filled-in"
        f" frames at their widest opening or a closure), so amplitude and speed {measured};"
        " check that the markers stay in view of both cameras, are not partly hidden and do"
        " not sit beside a glint (nail polish, a ring)"
    ]


def _compute_task_metrics(
    task: Task,
    positions_mm: FloatArray,
    fps: float,
    status: NDArray[np.str_],
    time_s: FloatArray | None = None,
    *,
    side: str,
    max_gap_s: float = 0.1,
) -> tuple[TaskMetrics | None, list[str]]:
    """The metrics of a task other than finger tapping (core.cycles), at the frames' real
    times as finger tapping's; None with a warning when they cannot be computed."""
    even = uniform_trajectories(positions_mm, status == MEASURED, time_s, fps, max_gap_s=max_gap_s)
    try:
        return compute_task_metrics(
            task, even.positions_mm, even.fps, measured=even.measured, side=side
        ), []
    except ValueError as exc:
        return None, [f"{task.label.lower()} metrics could not be computed: {exc}"]


def analyze_recording(
    rig: StereoRig,
    left_video: str | Path,
    right_video: str | Path,
    *,
    offset_frames: float | None = None,
    max_gap_s: float = 0.1,
    swap_labels: bool = False,
    max_offset_s: float = 0.5,
    marker_params: MarkerParams | None = None,
    detector: Detector | None = None,
    progress: ProgressCallback | None = None,
    left_times: str | Path | None = None,
    right_times: str | Path | None = None,
    task: str | Task = Task.FINGER_TAPPING,
    side: str = "right",
    frame_sinks: tuple[FrameSink | None, FrameSink | None] | None = None,
) -> Analysis:
    """Measure thumb and index trajectories (and tapping metrics) from a stereo recording.

    Parameters
    ----------
    rig : StereoRig
        Calibration of the two cameras.
    left_video, right_video : str or Path
        The two recordings.
    offset_frames : float, optional
        Right frame ``j`` was taken with left frame ``j + offset_frames``
        (``--offset-frames``); estimated from the marker motion when None.
    max_gap_s : float
        Gaps up to this long (s) are interpolated, longer ones stay missing.
    swap_labels : bool
        Exchange the automatic thumb/index labels.
    max_offset_s : float
        Largest offset searched by the automatic synchronisation (s).
    marker_params : core.markers.MarkerParams, optional
        Marker size and shape limits for the detector.
    detector : callable, optional
        Replaces ``core.markers.detect_markers`` (tests, other marker kinds):
        ``(image, search_xy_px | None, radius_px | None) -> (xy_px, diameter_px, quality)``.
    progress : callable, optional
        ``progress(stage, done, total)``.
    left_times, right_times : str or Path, optional
        Timestamps files (``frame,time_s`` CSV) with each frame's capture
        time; otherwise the container's timestamps or ``i / fps`` (:mod:`core.timing`).
    task : Task or str
        The examination task (``--task``): its marker protocol labels the
        tracks and its cycle signal gives the metrics (``docs/protocols.md``).
    side : {"right", "left"}
        The side examined (the trial's hand or foot): the direction of
        supination of pronation–supination; the other tasks do not use it.
    frame_sinks : (callable or None, callable or None), optional
        Called with every frame decoded from the left and the right video, in order,
        in the thread that searches that video's frames (``(H, W)`` uint8 gray, not to
        be kept or changed): a caller that needs the frames too (the worker's browser proxies,
        ``core.video.ProxyWriter``) gets them without decoding the video again. An
        exception a sink raises stops the analysis.

    Returns
    -------
    Analysis

    Raises
    ------
    InputError
        A video cannot be read, or the two videos do not match each other or the rig.
    DetectionError
        No markers (or fewer than two moving markers) were found.
    """
    from core.video import check_stereo_videos, probe_video

    if not (math.isfinite(max_gap_s) and max_gap_s >= 0):
        raise InputError(f"the longest gap to fill must be 0 s or more, got {max_gap_s}.")
    if offset_frames is not None and not math.isfinite(offset_frames):
        raise InputError(f"the frame offset must be a number of frames, got {offset_frames}.")
    task = parse_task(task)
    if side not in ("right", "left"):
        raise ValueError(f"side must be 'right' or 'left', got {side!r}")

    def probe(video: str | Path, csv: str | Path | None) -> VideoInfo:
        # A raw stream states no rate: its timestamps file's (which gives its frame times)
        # stands in.
        return probe_video(video, fps_if_none=None if csv is None else read_times_csv(csv).fps)

    # Both at once: each opens its file and decodes a frame with the GIL released, before
    # the decoding can start (a 10-s 1280x1024 mp4v pair: 26 ms one after the other, 14 ms
    # at once). The left video's error comes first when both fail, as before.
    with ThreadPoolExecutor(max_workers=2) as pool:
        left_info, right_info = pool.map(
            probe, (left_video, right_video), (left_times, right_times)
        )
    warnings = list(check_stereo_videos(left_info, right_info, rig=rig))
    fps = float(left_info.fps)
    stamps: tuple[list[float], list[float]] = ([], [])
    left_px, right_px, det_info, patches = _detect_videos(
        (left_info.path, right_info.path),
        (left_info.frame_count, right_info.frame_count),
        detector,
        progress,
        frame_sinks=frame_sinks,
        marker_params=marker_params,
        timestamps=stamps,
    )
    n_left, n_right = len(left_px), len(right_px)
    detections = (left_px, right_px)  # as found, each video's own frames (for the review view)
    if n_left == 0 or n_right == 0:
        raise InputError("a video decoded to no frames; check that the files are complete.")
    for name, frames in (("left", left_px), ("right", right_px)):
        seen = sum(1 for f in frames if len(f) > 0)
        if seen < max(3, 0.05 * len(frames)):
            raise DetectionError(
                f"markers were found in only {seen} of {len(frames)} frames of the {name} video;"
                " check that the markers are in view, lit by the ring light and not over-exposed."
            )

    report(progress, "synchronisation", 0, 1)
    times = [
        _frame_times(info, csv_path, stamp, n)
        for info, csv_path, stamp, n in (
            (left_info, left_times, stamps[0], n_left),
            (right_info, right_times, stamps[1], n_right),
        )
    ]
    fps = times[0].fps
    left_norm = _undistort_all(rig.left, left_px)
    right_norm = _undistort_all(rig.right, right_px)
    max_step_px = 0.05 * rig.right.image_size.width  # 2D linking gate for sub-frame pairing
    if offset_frames is not None and abs(offset_frames) >= n_left:
        raise InputError(
            f"an offset of {offset_frames:g} frames leaves no common frames in videos of"
            f" {n_left} frames; check --offset-frames."
        )
    timed = synchronise(
        rig,
        left_px,
        right_px,
        left_norm,
        right_norm,
        left_times=times[0],
        right_times=times[1],
        offset_frames=offset_frames,
        max_offset_s=max_offset_s,
        max_step_px=max_step_px,
    )
    warnings.extend(_lost_frames_in_words(timed.warnings, timed.sync, times))
    if timed.pairing_offset is None:
        left_px, right_px = timed.left_px, timed.right_px
        if rig.left.readout_ms > 0:
            left_norm = _undistort_all(rig.left, left_px)
        right_norm = _undistort_all(rig.right, right_px)
        pairing_offset = 0
    else:
        pairing_offset = timed.pairing_offset
    right_left_frame = _right_on_left_frames(timed, times[1], n_left, n_right)
    report(progress, "synchronisation", 1, 1)

    report(progress, "triangulation", 0, 1)
    fitted: tuple[list[NDArray[np.bool_]], list[NDArray[np.bool_]]] | None = None
    merged_frames = [0, 0]
    if timed.pairing_offset is not None and (patches[0] or patches[1]):
        # Merged or touching images measured along the rays from the other camera
        # (core.merged); only with whole-frame pairing: the two cameras' frames are
        # then the same instants.
        mm = measure_merged(rig, left_px, right_px, patches[0], patches[1], pairing_offset)
        if mm.frames_left or mm.frames_right:
            left_px, right_px = mm.left_px, mm.right_px
            left_norm = _undistort_all(rig.left, left_px)
            right_norm = _undistort_all(rig.right, right_px)
            fitted = (mm.left_measured, mm.right_measured)
            merged_frames = [mm.frames_left, mm.frames_right]
    obs, n_rejected = _observations(
        rig, left_px, right_px, left_norm, right_norm, pairing_offset, fitted=fitted
    )
    report(progress, "triangulation", 1, 1)
    paired = [o for o in obs if len(o.left_px) and len(o.right_px)]
    with_candidates = sum(1 for o in paired if len(o.candidates_mm))
    if paired and with_candidates < 0.5 * len(paired):
        raise DetectionError(
            f"the markers seen by the two cameras agree with the rig's geometry in only"
            f" {with_candidates} of {len(paired)} frames; check that the left and right videos are"
            " not swapped and that the rig file belongs to these cameras."
        )

    report(progress, "tracking", 0, 1)
    diameters = (
        float(det_info.pop("marker_diameter_px_left")),
        float(det_info.pop("marker_diameter_px_right")),
    )
    tracks = track_markers(
        rig,
        obs,
        fps=fps,
        max_gap_s=max_gap_s,
        # gaps of merged images (depth only) are filled at least as far as the others
        max_merged_gap_s=max(0.15, max_gap_s),
        swap_labels=swap_labels,
        marker_diameter_px=diameters,
        task=task,
    )
    report(progress, "tracking", 1, 1)
    warnings.extend(tracks.warnings)
    if not np.any(tracks.status == MEASURED):
        raise DetectionError(
            "no marker was seen consistently by both cameras; check that both cameras see the"
            f" {protocol_for(task).markers_in_words} and that the rig file belongs to these"
            " cameras."
        )
    measured_any = tracks.status == MEASURED
    lost = np.all(tracks.status == MISSING, axis=0)
    if np.count_nonzero(lost) and task is Task.FINGER_TAPPING:
        raise DetectionError(
            "only one moving marker was found; the thumb and the index finger both need a marker"
            " visible to both cameras."
        )
    if np.count_nonzero(lost):
        names = ", ".join(n for n, gone in zip(tracks.marker_names, lost, strict=True) if gone)
        raise DetectionError(
            f"the {names} marker{'s were' if np.count_nonzero(lost) > 1 else ' was'} not found;"
            f" {task.label.lower()} needs the markers {', '.join(tracks.marker_names)} in view of"
            " both cameras."
        )

    report(progress, "metrics", 0, 1)
    metrics: TappingMetrics | None = None
    task_metrics: TaskMetrics | None = None
    if task is Task.FINGER_TAPPING:
        metrics, metric_warnings = _compute_metrics(
            tracks.positions_mm,
            fps,
            tracks.status,
            timed.left_time_s,
            max_gap_s=max_gap_s,
            merged=tracks.merged,
        )
    else:
        task_metrics, metric_warnings = _compute_task_metrics(
            task,
            tracks.positions_mm,
            fps,
            tracks.status,
            timed.left_time_s,
            side=side,
            max_gap_s=max_gap_s,
        )
    warnings.extend(metric_warnings)
    measured_taps = metrics if metrics is not None else (task_metrics and task_metrics.tapping)
    if measured_taps is not None:
        warnings.extend(_few_whole_taps(measured_taps.metrics, task))
    report(progress, "metrics", 1, 1)

    reproj = tracks.reprojection_px[measured_any]
    quality: dict[str, Any] = {
        "tracked_fraction": float(np.mean(tracks.status != MISSING)),
        "measured_fraction": float(np.mean(measured_any)),
        "interpolated_fraction": float(np.mean(tracks.status == INTERPOLATED)),
        "reprojection_px_median": float(np.median(reproj)) if len(reproj) else None,
        "reprojection_px_p95": float(np.percentile(reproj, 95)) if len(reproj) else None,
        "rejected_candidates": n_rejected,
        "frames_left": n_left,
        "frames_right": n_right,
        # left frames where the two markers' images touched in a camera (core.tracks)
        "overlap_frames": tracks.overlap_frames,
        # frames of each camera whose merged or touching images were measured (core.merged)
        "merged_measured_frames_left": merged_frames[0],
        "merged_measured_frames_right": merged_frames[1],
        **det_info,
    }
    sync_doc = timed.sync
    return Analysis(
        fps=fps,
        frame_numbers=np.arange(n_left),
        positions_mm=tracks.positions_mm,
        status=tracks.status,
        reprojection_px=tracks.reprojection_px,
        marker_names=tracks.marker_names,
        sync=sync_doc,
        metrics=metrics,
        task_metrics=task_metrics,
        quality=quality,
        warnings=warnings,
        frame_time_s=timed.left_time_s,
        detections_px=detections,
        right_left_frame=right_left_frame,
        right_fps=times[1].fps,
        task=task.value,
    )


def _right_on_left_frames(
    timed: TimeModelResult, right_times: FrameTimes, n_left: int, n_right: int
) -> FloatArray:
    """Position of each right frame on the left frame axis, from the time model."""
    if timed.pairing_offset is not None:
        return np.arange(n_right, dtype=np.float64) + timed.pairing_offset
    if timed.model is not None:
        t_left = timed.model.right_to_left(corrected_times(right_times, timed.model.dropped_right))
        left_t = np.asarray(timed.left_time_s, dtype=np.float64)
        return np.interp(
            t_left, left_t, np.arange(n_left, dtype=np.float64), left=np.nan, right=np.nan
        )
    offset = float(timed.sync.get("offset_frames") or 0.0)
    return np.arange(n_right, dtype=np.float64) + offset


def _frame_times(
    info: VideoInfo, csv_path: str | Path | None, stamps: list[float], n_frames: int
) -> FrameTimes:
    """Capture times of a decoded video: its timestamps file, else its container (core.timing)."""
    if csv_path is not None:
        return fit_to_frames(read_times_csv(csv_path, n_frames=n_frames), n_frames)
    return container_frame_times(info, stamps, n_frames)


def container_frame_times(info: VideoInfo, stamps: Sequence[float], n_frames: int) -> FrameTimes:
    """Capture times of a video from its container's frame timestamps ``stamps`` (s, in
    display order; ignored when the container has none): read by
    :func:`core.timing.frame_times_from_timestamps` (``"container"`` with lost frames when
    they deviate from a constant rate, else ``i / fps``) and fitted to ``n_frames``. The
    analysis passes the decoder's timestamps; the upload's check the packets' (the same
    times, to the time base's resolution)."""
    usable = list(stamps) if info.has_timestamps and len(stamps) >= n_frames else []
    ts = frame_times_from_timestamps(usable[:n_frames], fps=info.fps, name=info.path.name)
    return fit_to_frames(ts, n_frames)


# ----------------------------------------------------------------------------- outputs


def write_markers_csv(analysis: Analysis, path_or_file: str | Path | TextIO) -> None:
    """Write ``markers.csv`` (docs/interfaces.md): one row per frame and marker, header first.

    The columns and their formatting are :mod:`core.markers_csv`'s.
    """
    write_marker_table(analysis.marker_table(), path_or_file)


def write_analysis(analysis: Analysis, out_dir: str | Path) -> None:
    """Write ``markers.csv`` and ``result.json`` into ``out_dir`` (created if needed).

    Each file is written beside its name and renamed into place once complete: a full
    disk leaves the files of an earlier run as they were, never half a file.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    buf = io.StringIO()
    write_markers_csv(analysis, buf)
    doc = analysis.result_document()
    texts = {
        "markers.csv": buf.getvalue(),
        "result.json": json.dumps(doc, indent=2, allow_nan=False) + "\n",
    }
    partial = {name: out / f".{name}.part" for name in texts}
    try:
        for name, text in texts.items():
            with open(partial[name], "w", encoding="utf-8", newline="") as fh:
                fh.write(text)
                fh.flush()
                os.fsync(fh.fileno())
    except BaseException:
        for path in partial.values():
            path.unlink(missing_ok=True)
        raise
    for name, path in partial.items():
        os.replace(path, out / name)

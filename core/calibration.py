"""Stereo calibration from board recordings: detection, view selection, fit, quality.

The path from two recordings to a rig (``calibrate_stereo_from_paths``):

1. **Sampling and detection** (:func:`collect_views`): at most
   ``max_candidates`` evenly spaced frame pairs of the two synchronous videos
   (or every pair of two image folders) are searched for the board with
   :func:`core.boards.detect_board`; other frames are decoded but not searched.
2. **Frame selection** (:func:`select_views`): blurred views are dropped
   (edge width well above the recording's median), then views are picked by
   farthest-point sampling in a pose descriptor (where the board is in both
   images, how large, how tilted), so near-duplicate poses are skipped and
   coverage and tilt variety are preferred, up to ``max_views``. Up to
   ``max_held_out`` further distinct views are kept aside to check the result.
3. **Fit** (:func:`calibrate_stereo`): intrinsics of each camera
   (``cv2.calibrateCamera``, OpenCV's 5-coefficient lens model), the
   left/right corner numbering reconciled (a chessboard's half-turn
   ambiguity), views whose board pose disagrees with the others or whose
   reprojection error is far above the median rejected, then a joint
   refinement of both cameras' intrinsics and the stereo extrinsics
   (``cv2.stereoCalibrate`` started from the per-camera intrinsics, which are
   left free), repeated once after outlier rejection.
4. **Quality** (stored in ``rig.quality``): see :func:`quality_verdict` and
   docs/calibration.md.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from numpy.typing import NDArray

from core import board_sync
from core.board_sync import BoardSync, BoardTrack
from core.boards import BoardDetection, BoardSpec, chessboard_extends, detect_board
from core.camera import Camera, ImageSize, StereoRig
from core.errors import CalibrationError, DetectionError, InputError
from core.progress import ProgressCallback, report

if TYPE_CHECKING:
    from core.timing import FrameTimes

FloatArray = NDArray[np.float64]

# OpenCV's type stubs reject None and float64 where the functions accept them.
_cv: Any = cv2

#: Fewest usable stereo views a calibration accepts.
MIN_VIEWS = 6
#: A view is an outlier if its RMS reprojection error exceeds both this (px)...
_OUTLIER_FLOOR_PX = 1.0
#: ...and this multiple of the median view error.
_OUTLIER_FACTOR = 4.0
#: A view is blurred if its edge width exceeds both this (px) and this factor x the median.
_BLUR_FLOOR_PX = 1.5
_BLUR_FACTOR = 1.3
#: Pose-descriptor distance under which two views count as the same pose.
_DUPLICATE_DISTANCE = 0.03
#: A calibration whose final RMS exceeds this (px) is refused: the board spec is wrong.
_FAIL_RMS_PX = 3.0
#: Frames searched by the quick check that the board is in the recording at all.
_PROBE_FRAMES = 12
#: Left views checked for a chessboard larger than described.
_SIZE_CHECKS = 8
#: Coverage grid (columns, rows) over the image.
_COVERAGE_GRID = (10, 8)
#: Two videos at one rate whose board motion lines up within this many frames
#: are taken as synchronous (frames paired by number) until the fitted rig says otherwise.
_SYNCHRONOUS_FRAMES = 0.5
#: After the epipolar refinement, an offset within this many frames of 0 is a lab rig's.
_SYNCHRONOUS_REFINED_FRAMES = 0.1
#: How far (frames) an offset refined by epipolar consistency is taken to be off.
_REFINED_UNCERTAINTY_FRAMES = 0.1


# -- data ----------------------------------------------------------------------


@dataclass(frozen=True)
class StereoView:
    """The board detections of one synchronous frame pair.

    Attributes
    ----------
    frame : int
        Left frame number (video) or image index (folders), from 0.
    left, right : BoardDetection or None
        ``None`` where the board was not found.
    edge_width_px : float
        Blur estimate of the view (NaN if not measured): larger is blurrier.
    """

    frame: int
    left: BoardDetection | None
    right: BoardDetection | None
    edge_width_px: float = float("nan")

    @property
    def both(self) -> bool:
        return self.left is not None and self.right is not None


@dataclass(frozen=True)
class ViewCollection:
    """Everything detection found in a pair of recordings.

    Attributes
    ----------
    views : list of StereoView
        One per searched left frame (detected or not), its right board at the
        same instant where it could be told.
    image_size : ImageSize
        ``(width, height)`` of the left camera (of both unless ``image_size_right``).
    frames_total : int
        Frame pairs in the recordings (the shorter video's frames).
    source : str
        ``"video"`` or ``"images"``.
    image_size_right : ImageSize or None
        The right camera's size when it differs from the left one's.
    left_track, right_track : BoardTrack or None
        Each camera's detections at its searched frames, with their times
        (videos); the views pair them.
    sync : BoardSync or None
        How the two recordings' clocks relate and how the views were paired.
    warnings : tuple of str
        What did not stop the calibration but deserves a look (one sentence each).
    """

    views: list[StereoView]
    image_size: ImageSize
    frames_total: int
    source: str
    image_size_right: ImageSize | None = None
    left_track: BoardTrack | None = None
    right_track: BoardTrack | None = None
    sync: BoardSync | None = None
    warnings: tuple[str, ...] = ()

    @property
    def frames_tried(self) -> int:
        return len(self.views)

    @property
    def sizes(self) -> tuple[ImageSize, ImageSize]:
        """``(left, right)`` image sizes."""
        return self.image_size, self.image_size_right or self.image_size


@dataclass(frozen=True)
class CalibrationResult:
    """A calibrated rig and its quality report (also in ``rig.quality``).

    Attributes
    ----------
    rig : StereoRig
    quality : dict
        JSON-serialisable quality figures (``rms_px`` and friends).
    """

    rig: StereoRig
    quality: dict[str, Any] = field(default_factory=dict)


# -- input ----------------------------------------------------------------------


def _frame_source(path: str | Path, side: str, times: FrameTimes | None) -> tuple[str, Any]:
    """``("images", [paths])`` or ``("video", VideoInfo)`` for a calibrate input; a raw
    stream states no rate, and its timestamps file's (``times``) stands in."""
    from core.video import list_images, probe_video

    p = Path(path)
    if p.is_dir():
        if times is not None:
            raise InputError("timestamps files belong to videos, not to folders of images.")
        return "images", list_images(p)
    if not p.exists():
        raise InputError(
            f"the {side} input {p} does not exist; give a video file or a folder of images."
        )
    return "video", probe_video(p, fps_if_none=None if times is None else times.fps)


def _sample_indices(n_frames: int, max_candidates: int) -> list[int]:
    if n_frames <= max_candidates:
        return list(range(n_frames))
    return sorted({round(v) for v in np.linspace(0, n_frames - 1, max_candidates)})


def _sampled_frames(
    kind: str, src: Any, indices: Sequence[int], times_out: list[float] | None
) -> Iterator[tuple[int, NDArray[np.uint8]]]:
    """``(frame number, gray frame)`` of the searched frames of one input, in order (the
    left and right inputs are decoded at once)."""
    from core.video import decoder_threads_for, iter_frames, read_image

    if kind == "images":
        for i in indices:
            yield i, read_image(src[i])
        return
    if not indices:
        return
    wanted = set(indices)
    frames: Any = iter_frames(
        src.path,
        gray=True,
        stop=max(indices) + 1,
        times_out=times_out,
        decoder_threads=decoder_threads_for(2),
        expected_count=src.frame_count,  # a truncated file is refused, as analyze refuses it
    )
    try:
        for i, frame in enumerate(frames):
            if i in wanted:
                yield i, frame
    finally:
        frames.close()


def _right_indices(left_idx: list[int], fps_l: float, fps_r: float, n_right: int) -> list[int]:
    """The right frames nearest the left searched frames' nominal times (cameras at other rates)."""
    idx = np.clip(np.rint(np.asarray(left_idx) * fps_r / fps_l), 0, n_right - 1).astype(int)
    return sorted({int(i) for i in idx})


def _length_warning(kind: str, n_left: int, n_right: int, fps: tuple[float, float]) -> str | None:
    if kind == "images" or n_left == n_right:
        return None
    if abs(fps[0] - fps[1]) <= 1e-3 * max(fps):
        return (
            f"the left video has {n_left} frames and the right {n_right}; the frames past the"
            f" end of the shorter one ({min(n_left, n_right)}) are not used."
        )
    d_l, d_r = n_left / fps[0], n_right / fps[1]
    if abs(d_l - d_r) <= 1.0 / min(fps):
        return None
    return (
        f"the left video lasts {d_l:.2f} s ({n_left} frames at {fps[0]:g} Hz) and the right"
        f" {d_r:.2f} s ({n_right} at {fps[1]:g} Hz); only the part both recorded is used."
    )


def collect_views(
    left: str | Path,
    right: str | Path,
    board: BoardSpec,
    *,
    max_candidates: int = 240,
    progress: ProgressCallback | None = None,
    left_times: str | Path | None = None,
    right_times: str | Path | None = None,
) -> ViewCollection:
    """Search evenly spaced frames of two recordings for the board and pair the views in time.

    Parameters
    ----------
    left, right : str or Path
        Two videos (synchronous or not: the time offset is found from the
        board's motion, :mod:`core.board_sync`), or two folders of images
        paired in sorted file-name order.
    board : BoardSpec
    max_candidates : int, keyword-only
        Frames searched at most in each recording (evenly spaced over it).
    progress : callable, optional
        ``progress("detection", done, total)``.
    left_times, right_times : str or Path, optional
        Timestamps files (``frame,time_s``, :func:`core.timing.read_times_csv`) of the
        videos: each frame's capture time, which stands in for the video's own rate and
        timestamps (as in ``analyze``). A browser take's WebM files carry the recorder's
        times, which a loaded machine can squeeze; the capture page writes these.

    Raises
    ------
    InputError
        Unreadable input, a folder and a video mixed, different numbers of
        images, or a timestamps file that does not fit its video (or is given
        for a folder of images).
    """
    if max_candidates < 1:
        raise ValueError(f"max_candidates must be >= 1, got {max_candidates}")
    from core.timing import (
        check_frame_count,
        fit_to_frames,
        frame_times_from_timestamps,
        read_times_csv,
        uniform_times,
    )

    given = [None if p is None else read_times_csv(p) for p in (left_times, right_times)]
    kind_l, src_l = _frame_source(left, "left", given[0])
    kind_r, src_r = _frame_source(right, "right", given[1])
    if kind_l != kind_r:
        raise InputError(
            "one input is a video and the other a folder of images; give two videos or two folders."
        )
    warnings: list[str] = []
    if kind_l == "images":
        if len(src_l) != len(src_r):
            raise InputError(
                f"the left folder holds {len(src_l)} images but the right {len(src_r)}; the images"
                " are paired in file-name order, so both folders need the same number."
            )
        n_left = n_right = len(src_l)
        fps_l = fps_r = 1.0
    else:
        n_left, n_right = src_l.frame_count, src_r.frame_count
        fps_l, fps_r = src_l.fps, src_r.fps
    for file_times, path, n in ((given[0], left_times, n_left), (given[1], right_times, n_right)):
        if file_times is not None:
            check_frame_count(file_times, n, Path(str(path)).name)
    fps_l = given[0].fps if given[0] is not None else fps_l
    fps_r = given[1].fps if given[1] is not None else fps_r
    same_rate = abs(fps_l - fps_r) <= 1e-3 * max(fps_l, fps_r)
    note = _length_warning(kind_l, n_left, n_right, (fps_l, fps_r))
    if note:
        warnings.append(note)
    n_total = min(n_left, n_right)
    _probe(kind_l, src_l, src_r, board, n_total)
    if same_rate:
        idx_l = idx_r = _sample_indices(n_total, max_candidates)
    else:
        idx_l = _sample_indices(n_left, max_candidates)
        idx_r = _right_indices(idx_l, fps_l, fps_r, n_right)
    times_l: list[float] | None = None if kind_l == "images" else []
    times_r: list[float] | None = None if kind_l == "images" else []
    found: dict[str, list[tuple[int, BoardDetection | None, float]]] = {"left": [], "right": []}
    sizes: dict[str, ImageSize] = {}
    checked: list[bool] = []
    n_steps = max(len(idx_l), len(idx_r))
    # Left and right are searched at once: OpenCV releases the GIL while it detects.
    with ThreadPoolExecutor(max_workers=2) as pool:
        pairs = itertools.zip_longest(
            _sampled_frames(kind_l, src_l, idx_l, times_l),
            _sampled_frames(kind_r, src_r, idx_r, times_r),
        )
        for done, (item_l, item_r) in enumerate(pairs):
            futures = {}
            for side, item in (("left", item_l), ("right", item_r)):
                if item is None:
                    continue
                i, img = item
                size = ImageSize.of_image(img)
                if sizes.setdefault(side, size) != size:
                    raise InputError(
                        f"{side} frame {i} is {size.width}x{size.height}, not"
                        f" {sizes[side].width}x{sizes[side].height}; all images of one camera"
                        " must have one size."
                    )
                futures[side] = pool.submit(_detect_one, img, board)
            for side, item in (("left", item_l), ("right", item_r)):
                if item is None:
                    continue
                det, width = futures[side].result()
                found[side].append((item[0], det, width))
                if (
                    side == "left"
                    and board.kind == "chessboard"
                    and det is not None
                    and len(checked) < _SIZE_CHECKS
                ):
                    checked.append(chessboard_extends(item[1], det, board))
                    if len(checked) == _SIZE_CHECKS:
                        _check_board_size(checked, board)
            report(progress, "detection", done + 1, n_steps)
    if len(checked) >= 2:
        _check_board_size(checked, board)
    tracks = []
    for side, times, fps, src, csv in (
        ("left", times_l, fps_l, src_l, given[0]),
        ("right", times_r, fps_r, src_r, given[1]),
    ):
        rows = found[side]
        frames = np.array([r[0] for r in rows], dtype=np.int64)
        if times is None or kind_l == "images":
            t_all = uniform_times(int(frames.max()) + 1 if len(frames) else 0, fps).t_s
        elif csv is not None:  # within two frames of the video's count: cut or continued
            t_all = fit_to_frames(csv, src.frame_count).t_s
        else:
            t_all = frame_times_from_timestamps(times, fps=fps, name=src.path.name).t_s
            if len(t_all) <= (int(frames.max()) if len(frames) else -1):
                t_all = uniform_times(int(frames.max()) + 1, fps).t_s
        tracks.append(
            BoardTrack(
                frames=frames,
                t_s=np.asarray(t_all[frames], dtype=np.float64),
                detections=tuple(r[1] for r in rows),
                edge_width_px=np.array([r[2] for r in rows], dtype=np.float64),
                fps=fps,
                image_size=sizes.get(side, ImageSize(1, 1)),
            )
        )
    track_l, track_r = tracks
    size_l, size_r = track_l.image_size, track_r.image_size
    if kind_l == "images":
        sync = BoardSync(0.0, fps_left=fps_l, method=board_sync.IMAGES)
    else:
        sync = board_sync.estimate_offset(track_l, track_r, board)
        whole_frame = abs(sync.offset_s) * fps_l < _SYNCHRONOUS_FRAMES
        if same_rate and (not np.isfinite(sync.correlation) or whole_frame):
            sync = dataclasses.replace(sync, offset_s=0.0, method=board_sync.SYNCHRONOUS)
        elif not np.isfinite(sync.correlation) or sync.correlation < board_sync.MIN_CORRELATION:
            # Cameras at different rates and no motion to time them by: pair in time from
            # their starts (frame numbers differ), the still views at least.
            sync = dataclasses.replace(sync, offset_s=0.0)
    views = pair_views(track_l, track_r, board, sync)
    return ViewCollection(
        views,
        size_l,
        n_total,
        kind_l,
        image_size_right=size_r if size_r != size_l else None,
        left_track=track_l,
        right_track=track_r,
        sync=sync,
        warnings=tuple(warnings),
    )


def pair_views(
    left: BoardTrack, right: BoardTrack, board: BoardSpec, sync: BoardSync
) -> list[StereoView]:
    """One stereo view per searched left frame, its right board at the same instant.

    ``"synchronous"`` and ``"images"``: the frames searched together are
    paired as they are. ``"estimated"``: the right board at the left
    instant, where :func:`core.board_sync.right_at_left_instants` can tell it
    well (``right`` is None elsewhere).
    """
    if sync.method != board_sync.ESTIMATED:
        # Frames searched together (the same numbers), as far as both recordings go.
        at = {int(f): j for j, f in enumerate(right.frames)}
        out = []
        for k, dl in enumerate(left.detections):
            j = at.get(int(left.frames[k]))
            if j is None:
                continue
            dr = right.detections[j]
            width = (
                max(left.edge_width_px[k], right.edge_width_px[j])
                if dl is not None and dr is not None
                else np.nan
            )
            out.append(StereoView(int(left.frames[k]), dl, dr, float(width)))
        return out
    paired = {p.left_index: p for p in board_sync.right_at_left_instants(left, right, board, sync)}
    views = []
    for k, dl in enumerate(left.detections):
        p = paired.get(k)
        if dl is None or p is None:
            views.append(StereoView(int(left.frames[k]), dl, None))
            continue
        width = max([left.edge_width_px[k], *(right.edge_width_px[j] for j in p.right_indices)])
        views.append(StereoView(int(left.frames[k]), dl, p.detection, float(width)))
    return views


def _check_board_size(extends: list[bool], board: BoardSpec) -> None:
    """Refuse a chessboard that is larger than described (found as a sub-grid)."""
    n = sum(extends)
    if n >= max(2, len(extends) / 2):
        raise DetectionError(
            f"the chessboard has more inner corners than the {board.cols}x{board.rows} given"
            f" (its corners continue past the grid found in {n} of {len(extends)} views checked);"
            " check --cols/--rows: count the inner corners, e.g. 9x6 for a board of 10x7 squares."
        )


def _detect_one(image: NDArray[np.uint8], board: BoardSpec) -> tuple[BoardDetection | None, float]:
    """The board in one image and the blur of its edges (NaN when not found)."""
    det = detect_board(image, board)
    return det, (edge_width_px(image, det) if det is not None else float("nan"))


def _probe(kind: str, src_l: Any, src_r: Any, board: BoardSpec, n_total: int) -> None:
    """Fail fast when the board is in no frame: search a few frames spread over the recording.

    A board that is absent, or whose size was given wrong, makes every
    detection fail slowly; a dozen frames tell. Videos are read by seeking
    (not frame-exact, which does not matter here). When the board is in none
    of them, the same frames are searched for the board described the other
    way round (``--cols/--rows`` swapped) and, for ChArUco, in the legacy
    layout, so that the error can say which was meant.
    """
    from core.video import read_frame, read_image

    indices = _sample_indices(n_total, _PROBE_FRAMES)
    img: Any
    for side, src in (("left", src_l), ("right", src_r)):
        seen: list[Any] = []
        found = False
        for i in indices:
            img = read_image(src[i]) if kind == "images" else read_frame(src.path, i)
            if img is None:
                continue
            if detect_board(img, board) is not None:
                found = True
                break
            seen.append(img)
        if not found:
            raise DetectionError(
                f"the board ({board.describe()}) was found in 0 of {len(indices)} {side} frames"
                f" tried across the recording; {_variant_hint(seen, board) or _board_hint(board)}."
            )


def _board_variants(board: BoardSpec) -> list[tuple[BoardSpec, str]]:
    """Boards a user may have meant instead, with what to change (ends without a full stop)."""
    out: list[tuple[BoardSpec, str]] = []
    swapped = dataclasses.replace(board, cols=board.rows, rows=board.cols)
    if board.kind == "charuco":
        # A chessboard is found whichever way round it is described (the grid is the same).
        swap = f"swap --cols and --rows (--cols {board.rows} --rows {board.cols})"
        flip = dataclasses.replace(board, legacy=not board.legacy)
        legacy = (
            "it is a board in OpenCV's layout of before 4.6: add --legacy"
            if not board.legacy
            else "it is a board in OpenCV's current layout: drop --legacy"
        )
        out.append((swapped, f"the board is found the other way round: {swap}"))
        if board.rows % 2 == 0 or board.cols % 2 == 0:
            out.append((flip, legacy))
            out.append(
                (dataclasses.replace(swapped, legacy=not board.legacy), f"{legacy}, and {swap}")
            )
    return out


def _variant_hint(images: Sequence[Any], board: BoardSpec) -> str | None:
    """What to change when ``board`` is in none of ``images`` but a variant of it is."""
    for variant, hint in _board_variants(board):
        try:
            if any(detect_board(img, variant) is not None for img in images):
                return hint
        except (ValueError, cv2.error):
            continue
    return None


def _board_hint(board: BoardSpec) -> str:
    """What to check when a board is not found (ends without a full stop)."""
    if board.kind == "chessboard":
        return (
            "check --cols/--rows (a chessboard counts inner corners, e.g. 9x6 for 10x7 squares)"
            " and that the whole board is in view of the camera"
        )
    return (
        "check --cols/--rows (a ChArUco board counts squares) and --dictionary, and that the"
        " recording shows the board"
    )


def edge_width_px(image: NDArray[np.uint8], detection: BoardDetection) -> float:
    """Blur estimate of a board view: the width (px) of its sharpest black/white edges.

    ``contrast / max gradient`` over the board region, the worse of the x and
    y directions (motion blur widens the edges across the motion). A sharp,
    well-sampled edge gives about 1-1.5 px; blur of ``sigma`` px adds about
    ``2.5 sigma``.
    """
    pts = detection.corners_px
    x0, y0 = np.floor(pts.min(axis=0)).astype(int)
    x1, y1 = np.ceil(pts.max(axis=0)).astype(int) + 1
    h, w = image.shape[:2]
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return float("nan")
    roi = image[y0:y1, x0:x1].astype(np.float32)
    gx = np.abs(cv2.Sobel(roi, cv2.CV_32F, 1, 0, ksize=3)) / 8.0
    gy = np.abs(cv2.Sobel(roi, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
    lo, hi = np.percentile(roi, [5, 95])
    contrast = float(hi - lo)
    g = min(float(np.percentile(gx, 99.5)), float(np.percentile(gy, 99.5)))
    if contrast <= 0 or g <= 0:
        return float("nan")
    return contrast / g


# -- view selection ---------------------------------------------------------------


def _pose_descriptor(det: BoardDetection, size: ImageSize) -> FloatArray | None:
    """Where, how large and how tilted the board is: (5,) or None if degenerate."""
    w, h = size
    pts = det.corners_px
    centre = pts.mean(axis=0) / np.array([w, h])
    hull = cv2.convexHull(pts.astype(np.float32))
    area = float(cv2.contourArea(hull)) / (w * h)
    f0 = float(np.hypot(w, h))
    K0 = np.array([[f0, 0, w / 2], [0, f0, h / 2], [0, 0, 1]])
    H, _ = cv2.findHomography(det.object_points_mm[:, :2], pts, 0)
    if H is None:
        return None
    M = np.linalg.inv(K0) @ H
    r1, r2 = M[:, 0], M[:, 1]
    normal = np.cross(r1 / np.linalg.norm(r1), r2 / np.linalg.norm(r2))
    normal /= np.linalg.norm(normal)
    if normal[2] < 0:
        normal = -normal
    return np.array([centre[0], centre[1], 2.0 * np.sqrt(area), 1.5 * normal[0], 1.5 * normal[1]])


def _square_of(det: BoardDetection) -> float:
    """The grid step (mm) of a detection's object points."""
    d = np.diff(np.unique(det.object_points_mm[:, 0]))
    return float(d.min()) if len(d) else 1.0


def _enough_common_corners(
    left: BoardDetection, right: BoardDetection, *, board_square_mm: float
) -> bool:
    """Whether the corners seen in both images fix a board pose: >= 6 and not collinear."""
    ids = np.intersect1d(left.ids, right.ids)
    if len(ids) < 6:
        return False
    obj = left.object_points_mm[np.isin(left.ids, ids)][:, :2]
    sv = np.linalg.svd(obj - obj.mean(axis=0), compute_uv=False)
    return bool(sv[-1] >= 0.5 * board_square_mm)


@dataclass(frozen=True)
class ViewSelection:
    """Indices (into the collection's views) chosen for the fit and for the check."""

    used: list[int]
    held_out: list[int]
    blurred: list[int]
    duplicates: int


def select_views(
    collection: ViewCollection,
    *,
    max_views: int = 40,
    max_held_out: int = 10,
) -> ViewSelection:
    """Choose varied, sharp stereo views: farthest-point sampling of pose descriptors.

    The first pick is the view with the largest board; each next pick is the
    view farthest (in the descriptor of both cameras) from those already
    chosen. Views closer than ``_DUPLICATE_DISTANCE`` to a chosen one are
    near-duplicates and never picked. After ``max_views``, up to
    ``max_held_out`` further views are picked the same way for the check.
    """
    if max_views < MIN_VIEWS:
        raise ValueError(f"max_views must be >= {MIN_VIEWS}, got {max_views}")
    size = collection.image_size
    candidates: list[int] = []
    descs: list[FloatArray] = []
    widths = np.array([v.edge_width_px for v in collection.views if v.both])
    median_width = float(np.nanmedian(widths)) if np.any(np.isfinite(widths)) else np.nan
    blurred: list[int] = []
    for i, v in enumerate(collection.views):
        if not v.both:
            continue
        assert v.left is not None and v.right is not None
        if (
            np.isfinite(v.edge_width_px)
            and v.edge_width_px > _BLUR_FLOOR_PX
            and v.edge_width_px > _BLUR_FACTOR * median_width
        ):
            blurred.append(i)
            continue
        if not _enough_common_corners(v.left, v.right, board_square_mm=_square_of(v.left)):
            continue
        dl = _pose_descriptor(v.left, size)
        dr = _pose_descriptor(v.right, size)
        if dl is None or dr is None:
            continue
        # Partial ChArUco views count for less: scale by the fraction of corners seen.
        candidates.append(i)
        descs.append(np.concatenate([dl, dr]))
    if not candidates:
        return ViewSelection([], [], blurred, 0)
    D = np.array(descs)
    n_corners = np.array(
        [
            min(len(collection.views[i].left or ()), len(collection.views[i].right or ()))
            for i in candidates
        ],
        dtype=np.float64,
    )
    weight = np.sqrt(n_corners / n_corners.max())
    chosen: list[int] = []
    min_dist = np.full(len(candidates), np.inf)
    first = int(np.argmax(D[:, 2] + D[:, 7] + weight))
    order: list[int] = []
    nxt = first
    while True:
        order.append(nxt)
        d = np.linalg.norm(D - D[nxt], axis=1)
        min_dist = np.minimum(min_dist, d)
        score = min_dist * weight
        score[order] = -1.0
        best = int(np.argmax(score))
        if score[best] < 0:
            break
        if min_dist[best] < _DUPLICATE_DISTANCE:
            break
        if len(order) >= max_views + max_held_out:
            break
        nxt = best
    # Views left out that repeat a chosen pose.
    left_out = np.ones(len(candidates), dtype=bool)
    left_out[order] = False
    duplicates = int(np.sum(left_out & (min_dist < _DUPLICATE_DISTANCE)))
    chosen = [candidates[k] for k in order]
    used = sorted(chosen[:max_views])
    held = sorted(chosen[max_views:])
    return ViewSelection(used, held, blurred, duplicates)


# -- fitting -----------------------------------------------------------------------


def _cv_obj(det: BoardDetection, ids: NDArray[np.int64] | None = None) -> NDArray[np.float32]:
    obj = det.object_points_mm if ids is None else det.object_points_mm[np.isin(det.ids, ids)]
    return obj.astype(np.float32).reshape(-1, 1, 3)


def _cv_img(det: BoardDetection, ids: NDArray[np.int64] | None = None) -> NDArray[np.float32]:
    px = det.corners_px if ids is None else det.corners_px[np.isin(det.ids, ids)]
    return px.astype(np.float32).reshape(-1, 1, 2)


def _common(left: BoardDetection, right: BoardDetection) -> NDArray[np.int64]:
    return np.intersect1d(left.ids, right.ids)


def _calibrate_camera(
    dets: Sequence[BoardDetection],
    size: ImageSize,
    *,
    K: FloatArray | None = None,
    dist: FloatArray | None = None,
) -> tuple[float, FloatArray, FloatArray, list[FloatArray], list[FloatArray], FloatArray]:
    """``cv2.calibrateCamera``: rms, K, dist (5,), rvecs, tvecs, per-view RMS (px)."""
    obj = [_cv_obj(d) for d in dets]
    img = [_cv_img(d) for d in dets]
    flags = 0
    if K is not None:
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    K0 = None if K is None else K.copy()
    d0 = None if dist is None else dist.copy()
    rms, K_out, d_out, rvecs, tvecs, _si, _se, per_view = _cv.calibrateCameraExtended(
        obj, img, tuple(size), K0, d0, flags=flags, criteria=criteria
    )
    return (
        float(rms),
        np.asarray(K_out, dtype=np.float64),
        np.asarray(d_out, dtype=np.float64).reshape(-1)[:5],
        [np.asarray(r, dtype=np.float64).reshape(3) for r in rvecs],
        [np.asarray(t, dtype=np.float64).reshape(3) for t in tvecs],
        np.asarray(per_view, dtype=np.float64).reshape(-1),
    )


def _relative_pose(
    rl: FloatArray, tl: FloatArray, rr: FloatArray, tr: FloatArray
) -> tuple[FloatArray, FloatArray]:
    Rl, _ = _cv.Rodrigues(rl)
    Rr, _ = _cv.Rodrigues(rr)
    R = Rr @ Rl.T
    return R, tr - R @ tl


def _rotation_angle(Ra: FloatArray, Rb: FloatArray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def _reconcile_numbering(
    lefts: list[BoardDetection],
    rights: list[BoardDetection],
    board: BoardSpec,
    K_l: FloatArray,
    d_l: FloatArray,
    K_r: FloatArray,
    d_r: FloatArray,
) -> tuple[list[BoardDetection], list[bool], FloatArray]:
    """Make the right numbering agree with the left; flag views whose relative pose disagrees.

    For each view the left and right board poses give a left-to-right
    transform, which must be the same in every view. A chessboard's right
    detection may be numbered a half turn off; that numbering is tried too
    and the one that agrees with the consensus is kept. Views that agree in
    neither numbering (a mis-detection, a sub-board) are flagged: their
    transform is off the consensus by more than 3 degrees or 5 % of the
    baseline and by more than five times the views' median scatter.

    Returns
    -------
    rights : list of BoardDetection
        Right detections, renumbered where needed.
    consistent : list of bool
    deviations : ndarray, shape (n,)
        Each view's disagreement with the consensus, in units of (3 degrees,
        5 % of the baseline; inf where no pose was found): the median is well
        below 1 when the left and right views were taken at the same moments,
        far above when they were not.
    """
    candidates: list[list[tuple[BoardDetection, FloatArray, FloatArray]]] = []
    for dl, dr in zip(lefts, rights, strict=True):
        numberings = [dr] if board.kind == "charuco" else [dr, dr.flipped(board)]
        view_opts = []
        ok_l, rl, tl = _cv.solvePnP(
            _cv_obj(dl), _cv_img(dl), K_l, d_l, flags=cv2.SOLVEPNP_ITERATIVE
        )
        for o in numberings:
            ok_r, rr, tr = _cv.solvePnP(
                _cv_obj(o), _cv_img(o), K_r, d_r, flags=cv2.SOLVEPNP_ITERATIVE
            )
            if ok_l and ok_r:
                R, t = _relative_pose(rl.reshape(3), tl.reshape(3), rr.reshape(3), tr.reshape(3))
                view_opts.append((o, R, t))
        candidates.append(view_opts)
    all_opts = [(R, t) for opts in candidates for (_, R, t) in opts]
    if not all_opts:
        return rights, [False] * len(rights), np.full(len(rights), np.inf)
    scale = float(np.median([np.linalg.norm(t) for _, t in all_opts])) or 1.0

    def dist(a: tuple[FloatArray, FloatArray], b: tuple[FloatArray, FloatArray]) -> float:
        """Disagreement of two transforms, in units of (3 degrees, 5 % of the baseline)."""
        return max(
            float(_rotation_angle(a[0], b[0]) / np.deg2rad(3.0)),
            float(np.linalg.norm(a[1] - b[1])) / (0.05 * scale),
        )

    # Consensus: the transform nearest (in the median) to the best numbering of every view.
    def nearest(a: tuple[FloatArray, FloatArray]) -> list[float]:
        return [min((dist(a, (R, t)) for _, R, t in opts), default=np.inf) for opts in candidates]

    ref = min(all_opts, key=lambda a: float(np.median(nearest(a))))
    devs = np.array(nearest(ref))
    finite = devs[np.isfinite(devs)]
    # Far beyond the views' own scatter (and beyond 3 degrees / 5 % of the baseline) disagrees.
    limit = max(1.0, 5.0 * float(np.median(finite))) if len(finite) else 1.0
    out: list[BoardDetection] = []
    consistent: list[bool] = []
    for dr, opts, dev in zip(rights, candidates, devs, strict=True):
        if opts and dev <= limit:
            best = min(opts, key=lambda o: dist(ref, (o[1], o[2])))
            out.append(best[0])
            consistent.append(True)
        else:
            out.append(dr)
            consistent.append(False)
    return out, consistent, devs


@dataclass
class _StereoFit:
    rms: float
    K_l: FloatArray
    d_l: FloatArray
    K_r: FloatArray
    d_r: FloatArray
    R: FloatArray
    T: FloatArray
    per_view: FloatArray  # (n, 2) RMS px, left and right


def _stereo_calibrate(
    lefts: Sequence[BoardDetection],
    rights: Sequence[BoardDetection],
    size: ImageSize,
    K_l: FloatArray,
    d_l: FloatArray,
    K_r: FloatArray,
    d_r: FloatArray,
    *,
    fix_intrinsic: bool = False,
) -> _StereoFit:
    obj, img_l, img_r = [], [], []
    for dl, dr in zip(lefts, rights, strict=True):
        ids = _common(dl, dr)
        obj.append(_cv_obj(dl, ids))
        img_l.append(_cv_img(dl, ids))
        img_r.append(_cv_img(dr, ids))
    flags = cv2.CALIB_FIX_INTRINSIC if fix_intrinsic else cv2.CALIB_USE_INTRINSIC_GUESS
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    out = _cv.stereoCalibrateExtended(
        obj,
        img_l,
        img_r,
        K_l.copy(),
        d_l.copy(),
        K_r.copy(),
        d_r.copy(),
        tuple(size),
        None,
        None,
        flags=flags,
        criteria=criteria,
    )
    rms, K1, D1, K2, D2, R, T, _E, _F, _rv, _tv, per_view = out
    return _StereoFit(
        float(rms),
        np.asarray(K1, dtype=np.float64),
        np.asarray(D1, dtype=np.float64).reshape(-1)[:5],
        np.asarray(K2, dtype=np.float64),
        np.asarray(D2, dtype=np.float64).reshape(-1)[:5],
        np.asarray(R, dtype=np.float64),
        np.asarray(T, dtype=np.float64).reshape(3),
        np.asarray(per_view, dtype=np.float64).reshape(-1, 2),
    )


def _outliers(per_view_rms: FloatArray) -> NDArray[np.bool_]:
    """Views whose RMS (px) is above both the floor and a multiple of the median."""
    worst = per_view_rms if per_view_rms.ndim == 1 else per_view_rms.max(axis=1)
    med = float(np.median(worst))
    return (worst > _OUTLIER_FLOOR_PX) & (worst > _OUTLIER_FACTOR * med)


def _rig_from_fit(
    fit: _StereoFit, sizes: tuple[ImageSize, ImageSize], quality: dict[str, Any]
) -> StereoRig:
    left = Camera("left", sizes[0], _clean_K(fit.K_l), fit.d_l)
    right = Camera("right", sizes[1], _clean_K(fit.K_r), fit.d_r, _orthonormal(fit.R), fit.T)
    return StereoRig(left, right, quality)


def _clean_K(K: FloatArray) -> FloatArray:
    out = np.array(K, dtype=np.float64)
    out[0, 1] = out[1, 0] = out[2, 0] = out[2, 1] = 0.0
    out[2, 2] = 1.0
    return out


def _orthonormal(R: FloatArray) -> FloatArray:
    U, _, Vt = np.linalg.svd(R)
    out = U @ Vt
    if np.linalg.det(out) < 0:
        out = -out
    result: NDArray[np.float64] = out
    return result


def _short(exc: BaseException) -> str:
    """The first line of an exception message, trimmed (OpenCV's are long)."""
    text = str(exc).strip().splitlines()
    line = next((t.strip() for t in text if "error:" in t), text[0] if text else type(exc).__name__)
    return line[-120:].rstrip(".")


#: Views whose board poses disagree (median, in units of 3 degrees / 5 % of the
#: baseline) by more than this were not taken at the same moments.
_UNPAIRED_SPREAD = 1.0


def _fit(
    used: list[int],
    lefts_d: list[BoardDetection],
    rights_d: list[BoardDetection],
    board: BoardSpec,
    sizes: tuple[ImageSize, ImageSize],
    *,
    progress: ProgressCallback | None,
) -> tuple[_StereoFit, list[int], list[BoardDetection], list[BoardDetection], list[int], float]:
    """Steps 1-3 of :func:`calibrate_stereo`: the fit, the views kept and rejected, the spread
    of the views' left-to-right transforms (see :func:`_reconcile_numbering`)."""
    size_l, size_r = sizes
    # 1. Intrinsics of each camera, with outlier views removed.
    rejected: list[int] = []
    _, K_l, d_l, *_rest_l, pv_l = _calibrate_camera(lefts_d, size_l)
    _, K_r, d_r, *_rest_r, pv_r = _calibrate_camera(rights_d, size_r)
    report(progress, "calibration", 1, 4)
    # 2. Consistent numbering and a consistent left-to-right transform.
    rights_d, consistent, devs = _reconcile_numbering(lefts_d, rights_d, board, K_l, d_l, K_r, d_r)
    spread = float(np.median(devs))
    if not spread <= _UNPAIRED_SPREAD:
        raise _Unpaired(spread, int(np.sum(~(devs <= _UNPAIRED_SPREAD))), len(devs))
    bad = ~np.array(consistent) | _outliers(np.column_stack([pv_l, pv_r]))
    if np.any(bad) and np.sum(~bad) >= MIN_VIEWS:
        rejected += [used[k] for k in np.flatnonzero(bad)]
        keep = np.flatnonzero(~bad)
        used = [used[k] for k in keep]
        lefts_d = [lefts_d[k] for k in keep]
        rights_d = [rights_d[k] for k in keep]
        _, K_l, d_l, *_ = _calibrate_camera(lefts_d, size_l, K=K_l, dist=d_l)
        _, K_r, d_r, *_ = _calibrate_camera(rights_d, size_r, K=K_r, dist=d_r)
    report(progress, "calibration", 2, 4)
    # 3. Joint refinement, once more without outliers.
    fit = _stereo_calibrate(lefts_d, rights_d, size_l, K_l, d_l, K_r, d_r)
    bad = _outliers(fit.per_view)
    if np.any(bad) and np.sum(~bad) >= MIN_VIEWS:
        rejected += [used[k] for k in np.flatnonzero(bad)]
        keep = np.flatnonzero(~bad)
        used = [used[k] for k in keep]
        lefts_d = [lefts_d[k] for k in keep]
        rights_d = [rights_d[k] for k in keep]
        fit = _stereo_calibrate(lefts_d, rights_d, size_l, fit.K_l, fit.d_l, fit.K_r, fit.d_r)
    return fit, used, lefts_d, rights_d, rejected, spread


class _Unpaired(Exception):
    """The left and right views disagree on the left-to-right transform: not simultaneous."""

    def __init__(self, spread: float, n_bad: int, n: int) -> None:
        super().__init__(f"spread {spread:.1f}")
        self.spread, self.n_bad, self.n = spread, n_bad, n


@dataclass(frozen=True)
class _Calibrated:
    """One fit of :func:`calibrate_stereo` before its quality figures."""

    collection: ViewCollection
    selection: ViewSelection
    fit: _StereoFit
    used: list[int]
    lefts: list[BoardDetection]
    rights: list[BoardDetection]
    rejected: list[int]
    spread: float
    rig: StereoRig


def _fit_views(
    collection: ViewCollection,
    board: BoardSpec,
    *,
    max_views: int,
    max_held_out: int,
    progress: ProgressCallback | None,
) -> _Calibrated:
    """Select views, fit the rig; :class:`CalibrationError` (or :class:`_Unpaired`) if it fails."""
    views = collection.views
    selection = select_views(collection, max_views=max_views, max_held_out=max_held_out)
    if len(selection.used) < MIN_VIEWS:
        raise CalibrationError(_too_few_views_message(collection, len(selection.used)))
    used = list(selection.used)
    lefts_d = [d for d in (views[i].left for i in used) if d is not None]
    rights_d = [d for d in (views[i].right for i in used) if d is not None]
    assert len(lefts_d) == len(used) and len(rights_d) == len(used)
    failure = (
        "the calibration could not be computed from these views ({});"
        " record the board in more varied poses, tilted and across the whole image."
    )
    try:
        fit, used, lefts_d, rights_d, rejected, spread = _fit(
            used, lefts_d, rights_d, board, collection.sizes, progress=progress
        )
    except (cv2.error, ValueError, np.linalg.LinAlgError) as exc:
        raise CalibrationError(failure.format(_short(exc))) from exc
    try:
        rig = _rig_from_fit(fit, collection.sizes, {})
    except ValueError as exc:
        raise CalibrationError(failure.format(_short(exc))) from exc
    return _Calibrated(collection, selection, fit, used, lefts_d, rights_d, rejected, spread, rig)


def _too_few_views_message(collection: ViewCollection, n_used: int) -> str:
    n_both = sum(v.both for v in collection.views)
    sync = collection.sync
    if sync is not None and sync.method == board_sync.ESTIMATED:
        return (
            f"only {n_used} sharp, distinct views show the board in both cameras at the same"
            f" moment ({n_both} left frames could be paired with the right camera, which"
            f" {_offset_words(sync)}); at least {MIN_VIEWS} are needed — the cameras are not"
            " synchronised, so hold the board still for about a second in each pose."
        )
    return (
        f"only {n_used} sharp, distinct views show the board in both cameras"
        f" ({n_both} frame pairs in all); at least {MIN_VIEWS} are needed — move the board"
        " slowly through the region both cameras see, holding it still at varied angles."
    )


def _offset_words(sync: BoardSync) -> str:
    """``"starts 0.300 s (4.5 frames) after the left"`` for the right camera."""
    when = "after" if sync.offset_s >= 0 else "before"
    return (
        f"starts {abs(sync.offset_s):.3f} s ({abs(sync.offset_frames):.1f} frames) {when} the left"
    )


def _unpaired_message(collection: ViewCollection, exc: _Unpaired) -> str:
    disagree = f"{exc.n_bad} of {exc.n} views"
    if collection.source == "images":
        return (
            "the left and right images do not pair up: the board's pose relative to the two"
            f" cameras changes from pair to pair ({disagree} disagree), so each left image was"
            " not taken at the same moment as the right image of the same rank in file-name"
            " order; give two folders of simultaneous pairs with matching names."
        )
    sync = collection.sync
    if sync is not None and sync.method == board_sync.ESTIMATED:
        return (
            "the two videos do not show the board at the same moments even at the time offset"
            f" found from its motion (the right {_offset_words(sync)}; {disagree} disagree);"
            " check that they were recorded together, and hold the board still for about a"
            " second in each pose."
        )
    return (
        "the two videos do not show the board at the same moments and their time offset could"
        f" not be found from its motion ({disagree} disagree); check that they were recorded"
        " together, and move the board between poses held still for about a second."
    )


def calibrate_stereo(
    collection: ViewCollection,
    board: BoardSpec,
    *,
    max_views: int = 40,
    max_held_out: int = 10,
    progress: ProgressCallback | None = None,
) -> CalibrationResult:
    """Calibrate a stereo rig from detected board views.

    When the collection holds the two cameras' board tracks (videos), the
    time offset found from the board's motion is refined by epipolar
    consistency with the fitted rig, the views are paired again at that
    offset and the rig is fitted again (:mod:`core.board_sync`); the offset
    is reported in ``quality["sync"]``.

    Parameters
    ----------
    collection : ViewCollection
        From :func:`collect_views`.
    board : BoardSpec
        The board that was filmed (its ``square_mm`` sets the rig's scale).
    max_views : int, keyword-only
        Stereo views used in the fit at most.
    max_held_out : int, keyword-only
        Further distinct views kept aside to check the board-square length.
    progress : callable, optional
        ``progress("calibration", step, total)``.

    Raises
    ------
    DetectionError
        The board was found in too few frames of either camera.
    CalibrationError
        Too few usable common views, views that were not taken at the same
        moments (and no time offset explains them), or a fit too poor to be
        the board asked for.
    """
    views = collection.views
    counts = [(sum(v.left is not None for v in views), len(views))] * 2
    counts[1] = (sum(v.right is not None for v in views), len(views))
    track = collection.right_track
    if track is not None and collection.sync and collection.sync.method == board_sync.ESTIMATED:
        counts[1] = (track.detected, len(track))  # the views hold the paired right boards only
    for side, (n, n_tried) in zip(("left", "right"), counts, strict=True):
        if n < MIN_VIEWS:
            raise DetectionError(
                f"the board ({board.describe()}) was found in {n} of {n_tried} {side} frames;"
                f" at least {MIN_VIEWS} are needed — {_board_hint(board)}."
            )
    report(progress, "calibration", 0, 4)
    options = {"max_views": max_views, "max_held_out": max_held_out, "progress": progress}
    done = _calibrate_in_time(collection, board, options)
    fit = done.fit
    collection = done.collection
    report(progress, "calibration", 3, 4)
    if not np.isfinite(fit.rms) or fit.rms > _FAIL_RMS_PX:
        sync = collection.sync
        if sync is not None and sync.method == board_sync.ESTIMATED:
            raise CalibrationError(
                f"the board views of the two cameras do not fit one rig (reprojection error"
                f" {fit.rms:.1f} px) at the time offset found from the board's motion (the right"
                f" {_offset_words(sync)}); check that the videos were recorded together and that"
                f" --cols/--rows/--square-mm describe the board filmed ({board.describe()})."
            )
        raise CalibrationError(
            f"the board corners do not fit one rig (reprojection error {fit.rms:.1f} px);"
            f" check that --cols/--rows/--square-mm describe the board filmed ({board.describe()})."
        )
    # 4. Quality.
    held = [collection.views[i] for i in done.selection.held_out]
    quality = _quality(
        done.rig,
        board,
        fit,
        used=done.used,
        lefts=done.lefts,
        rights=done.rights,
        held_out=held,
        collection=collection,
        selection=done.selection,
        rejected=done.rejected,
    )
    rig = StereoRig(done.rig.left, done.rig.right, quality)
    report(progress, "calibration", 4, 4)
    return CalibrationResult(rig=rig, quality=quality)


def _calibrate_in_time(
    collection: ViewCollection, board: BoardSpec, options: dict[str, Any]
) -> _Calibrated:
    """Fit, then (videos) refine the time offset with the rig and fit again where it moved.

    A first fit uses the views as paired: frames searched together when the
    board motion says the cameras were synchronous, else the still views at
    the coarse offset. If its views were not simultaneous (their
    left-to-right transforms disagree), the still views at the coarse offset
    and then at its rivals (other offsets where the board motion lines up
    almost as well) are tried. The rig then gives the offset by epipolar
    consistency (:func:`_refine_offset`); where it differs from the pairing
    used, the views are paired again and the rig refitted.
    """
    sync = collection.sync
    left, right = collection.left_track, collection.right_track
    if collection.source != "video" or sync is None or left is None or right is None:
        try:
            return _fit_views(collection, board, **options)
        except _Unpaired as exc:
            raise CalibrationError(_unpaired_message(collection, exc)) from None
    try:
        done = _fit_views(collection, board, **options)
    except (_Unpaired, CalibrationError) as exc:
        failures: list[_Unpaired | CalibrationError] = [exc]
        for candidate in _rival_pairings(collection, board):
            try:
                done = _fit_views(candidate, board, **options)
                break
            except (_Unpaired, CalibrationError) as rival_failure:
                failures.append(rival_failure)
        else:
            unpaired = [f for f in failures if isinstance(f, _Unpaired)]
            if unpaired:
                # No offset tried gives simultaneous views: say so, not which offset was tried.
                untimed = dataclasses.replace(collection, sync=None)
                raise CalibrationError(_unpaired_message(untimed, unpaired[0])) from None
            raise failures[0] from None
    collection = done.collection
    assert collection.sync is not None
    refined = _refine_offset(done.rig, board, left, right, collection.sync)
    if refined is None:
        return done
    if collection.sync.method == board_sync.SYNCHRONOUS and (
        abs(refined.offset_s) * left.fps < _SYNCHRONOUS_REFINED_FRAMES
    ):
        # A lab rig: frames were paired right; report the measured offset.
        kept = dataclasses.replace(refined, method=board_sync.SYNCHRONOUS)
        return dataclasses.replace(done, collection=dataclasses.replace(collection, sync=kept))
    refined = dataclasses.replace(refined, method=board_sync.ESTIMATED)
    again = dataclasses.replace(
        collection, views=pair_views(left, right, board, refined), sync=refined
    )
    try:
        return _fit_views(again, board, **options)
    except _Unpaired as exc:
        raise CalibrationError(_unpaired_message(again, exc)) from None


#: Rival offsets tried at most when the first pairing's views are not simultaneous.
_MAX_RIVALS = 4


def _rival_pairings(collection: ViewCollection, board: BoardSpec) -> Iterator[ViewCollection]:
    """The collection paired at the coarse offset (if it was paired by frame number) and
    at its rivals, still views only, best scored first; last, by frame number (one rate)."""
    sync = collection.sync
    left, right = collection.left_track, collection.right_track
    if sync is None or left is None or right is None or not np.isfinite(sync.correlation):
        return
    offsets = [] if sync.method == board_sync.ESTIMATED else [sync.coarse_offset_s]
    offsets += list(sync.candidates_s[:_MAX_RIVALS])
    for offset in offsets:
        coarse = dataclasses.replace(sync, offset_s=offset, method=board_sync.ESTIMATED)
        yield dataclasses.replace(
            collection, views=pair_views(left, right, board, coarse), sync=coarse
        )
    if sync.method == board_sync.ESTIMATED and left.frames.tolist() == right.frames.tolist():
        # Last: the frames searched together, as a lab rig's.
        together = dataclasses.replace(sync, offset_s=0.0, method=board_sync.SYNCHRONOUS)
        yield dataclasses.replace(
            collection, views=pair_views(left, right, board, together), sync=together
        )


def _refine_offset(
    rig: StereoRig,
    board: BoardSpec,
    left: BoardTrack,
    right: BoardTrack,
    sync: BoardSync,
) -> BoardSync | None:
    """The clock offset at which the board corners of the two cameras agree best with the rig.

    Around ``sync.offset_s`` (over ``±max(2 × its uncertainty, 1.5 frames)``,
    in steps of a tenth of a left frame) the right corners are interpolated
    in time to each left detection's instant (cubic through the four
    searched right frames around it), and the symmetric epipolar distance of every
    common corner (px, truncated at 3 px) is averaged over the views that
    cover every offset tried. The minimum, refined by a parabola, is the
    offset. None when fewer than ``MIN_VIEWS`` views cover the range or the
    cost does not depend on the offset (the board never moved).
    """
    fps = left.fps
    step = 0.1 / fps
    span = max(2.0 * sync.uncertainty_s, 1.5 / fps)
    n = int(np.ceil(span / step))
    offsets = sync.offset_s + np.arange(-n, n + 1) * step
    max_gap = 1.5 * right.sample_interval_s + 1e-9
    E = rig.essential_matrix
    f_l = 0.5 * (rig.left.K[0, 0] + rig.left.K[1, 1])
    f_r = 0.5 * (rig.right.K[0, 0] + rig.right.K[1, 1])
    costs = []
    for k, dl in enumerate(left.detections):
        if dl is None:
            continue
        taus = (left.t_s[k] - offsets) / sync.rate  # decreasing with the offset
        # The searched right frames around every instant, one more on each side (cubic).
        j0 = int(np.searchsorted(right.t_s, taus.min(), side="right")) - 2
        j1 = int(np.searchsorted(right.t_s, taus.max(), side="left")) + 1
        if j0 < 0 or j1 >= len(right) or j1 - j0 < 3:
            continue
        window = list(range(j0, j1 + 1))
        t_win = right.t_s[window]
        if np.any(np.diff(t_win) > max_gap):
            continue
        ref = right.detections[j0]
        if ref is None:
            continue
        ref = _best_numbering(rig, board, dl, ref)
        dets = [ref]
        for j in window[1:]:
            d = right.detections[j]
            if d is None:
                break
            dets.append(board_sync.align_numbering(dets[-1], d, board))
        if len(dets) != len(window):
            continue
        ids = dl.ids
        for d in dets:
            ids = np.intersect1d(ids, d.ids)
        if len(ids) < 4:
            continue
        xl = rig.left.undistort_points(dl.corners_px[np.isin(dl.ids, ids)])
        xr = np.stack(
            [rig.right.undistort_points(d.corners_px[np.isin(d.ids, ids)]) for d in dets]
        )  # (W, n, 2)
        pts = _cubic_at(t_win, xr, taus)
        hl = np.column_stack([xl, np.ones(len(xl))])  # (n, 3)
        hr = np.concatenate([pts, np.ones((*pts.shape[:2], 1))], axis=2)  # (m, n, 3)
        lines_r = hl @ E.T  # (n, 3): epipolar lines in the right image
        alg = np.einsum("mni,ni->mn", hr, lines_r)
        lines_l = hr @ E  # (m, n, 3)
        d_r = np.abs(alg) / np.linalg.norm(lines_r[:, :2], axis=1)[None, :] * f_r
        d_l = np.abs(alg) / np.linalg.norm(lines_l[..., :2], axis=2) * f_l
        d = np.minimum(np.sqrt(0.5 * (d_l**2 + d_r**2)), 3.0)
        costs.append(np.mean(d**2, axis=1))
    if len(costs) < MIN_VIEWS:
        return None
    cost = np.mean(np.array(costs), axis=0)
    best = int(np.argmin(cost))
    if not np.isfinite(cost[best]) or cost.max() - cost[best] < 0.05 * max(cost[best], 1e-6):
        return None
    offset = float(offsets[best])
    if 0 < best < len(offsets) - 1:
        y0, y1, y2 = cost[best - 1 : best + 2]
        denom = y0 - 2 * y1 + y2
        if denom > 0:
            offset += float(np.clip(0.5 * (y0 - y2) / denom, -0.5, 0.5)) * step
    return dataclasses.replace(
        sync, offset_s=offset, uncertainty_s=_REFINED_UNCERTAINTY_FRAMES / fps, refined=True
    )


def _cubic_at(t: FloatArray, values: FloatArray, at: FloatArray) -> FloatArray:
    """``values (W, ...)`` at times ``t (W,)`` interpolated at ``at (M,)``: the cubic through
    the two samples before and the two after each instant (Lagrange; ``W >= 4``, and
    every instant between ``t[1]`` and ``t[-2]``). Returns ``(M, ...)``."""
    seg = np.clip(np.searchsorted(t, at, side="right") - 1, 1, len(t) - 3)
    q = seg[:, None] + np.arange(-1, 3)[None, :]  # (M, 4) sample indices
    tq = t[q]
    w = np.ones(q.shape)
    for a in range(4):
        for b in range(4):
            if a != b:
                w[:, a] *= (at - tq[:, b]) / (tq[:, a] - tq[:, b])
    return np.asarray(np.einsum("ma,ma...->m...", w, values[q]), dtype=np.float64)


def calibrate_stereo_from_paths(
    left: str | Path,
    right: str | Path,
    board: BoardSpec,
    *,
    max_views: int = 40,
    max_candidates: int = 240,
    progress: ProgressCallback | None = None,
    left_times: str | Path | None = None,
    right_times: str | Path | None = None,
) -> CalibrationResult:
    """Calibrate a stereo rig from two board recordings.

    Parameters
    ----------
    left, right : str or Path
        Videos of the board (synchronous or not), or folders of images
        paired in sorted file-name order.
    board : BoardSpec
        The board filmed.
    max_views : int, keyword-only
        Stereo views used in the fit at most (the rest of the sharp, distinct
        views check the result).
    max_candidates : int, keyword-only
        Frame pairs searched for the board at most (evenly spaced).
    progress : callable, optional
        ``progress(stage, done, total)`` with stages ``"detection"`` and ``"calibration"``.
    left_times, right_times : str or Path, optional
        The videos' timestamps files (:func:`collect_views`).

    Returns
    -------
    CalibrationResult
        ``result.rig`` (with ``rig.quality``) is ready for ``core.camera.write_rig``.

    Raises
    ------
    InputError, DetectionError, CalibrationError
        With one sentence that says what to do.
    """
    collection = collect_views(
        left,
        right,
        board,
        max_candidates=max_candidates,
        progress=progress,
        left_times=left_times,
        right_times=right_times,
    )
    return calibrate_stereo(collection, board, max_views=max_views, progress=progress)


# -- quality ------------------------------------------------------------------------


def epipolar_errors_px(rig: StereoRig, left_px: FloatArray, right_px: FloatArray) -> FloatArray:
    """Symmetric epipolar distance (px) of matched distorted pixels ``(N, 2)`` each, ``(N,)``.

    Points are undistorted to ideal pixels of each camera; the result is the
    mean of the right point's distance to the left point's epipolar line and
    vice versa.
    """
    ul = rig.left.undistort_pixels(left_px)
    ur = rig.right.undistort_pixels(right_px)
    F = rig.fundamental_matrix()
    hl = np.column_stack([ul, np.ones(len(ul))])
    hr = np.column_stack([ur, np.ones(len(ur))])
    lines_r = hl @ F.T  # epipolar lines in the right image
    lines_l = hr @ F  # in the left image
    num = np.abs(np.sum(hr * lines_r, axis=1))
    d_r = num / np.hypot(lines_r[:, 0], lines_r[:, 1])
    d_l = num / np.hypot(lines_l[:, 0], lines_l[:, 1])
    return np.asarray(0.5 * (d_l + d_r), dtype=np.float64)


def _pair_points(
    dl: BoardDetection, dr: BoardDetection
) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
    ids = _common(dl, dr)
    return ids, dl.corners_px[np.isin(dl.ids, ids)], dr.corners_px[np.isin(dr.ids, ids)]


def square_lengths_mm(
    rig: StereoRig, board: BoardSpec, pairs: Sequence[tuple[BoardDetection, BoardDetection]]
) -> FloatArray:
    """Triangulated lengths (mm) of every board square side seen in both images of the pairs.

    Adjacent corners (same row or same column of the corner grid) are
    triangulated with :func:`core.triangulation.triangulate`; each length
    should equal ``board.square_mm``.
    """
    from core.triangulation import triangulate

    cols, _rows = board.corner_grid
    out: list[FloatArray] = []
    for dl, dr in pairs:
        ids, pl, pr = _pair_points(dl, dr)
        if len(ids) < 2:
            continue
        pts = triangulate(rig, pl, pr).points_mm
        index = {int(k): n for n, k in enumerate(ids)}
        for n, k in enumerate(ids):
            k = int(k)
            for nb in (k + 1 if (k + 1) % cols else None, k + cols):
                if nb is not None and nb in index:
                    out.append(np.array([np.linalg.norm(pts[index[nb]] - pts[n])]))
    return np.concatenate(out) if out else np.zeros(0)


def image_coverage(
    points_px: FloatArray, size: ImageSize, *, grid: tuple[int, int] = _COVERAGE_GRID
) -> float:
    """Fraction of the cells of a ``grid`` (columns, rows) over the image that hold a point."""
    if len(points_px) == 0:
        return 0.0
    w, h = size
    gc, gr = grid
    cx = np.clip((points_px[:, 0] + 0.5) / w * gc, 0, gc - 1).astype(int)
    cy = np.clip((points_px[:, 1] + 0.5) / h * gr, 0, gr - 1).astype(int)
    return float(len(set(zip(cx.tolist(), cy.tolist(), strict=True)))) / (gc * gr)


def _nan_stat(stat: Any, values: FloatArray) -> float | None:
    """A statistic of the finite values (rounded), or None when there are none."""
    values = np.asarray(values, dtype=np.float64)
    if not np.any(np.isfinite(values)):
        return None
    return _round(float(stat(values)))


def _round(x: float, nd: int = 4) -> float | None:
    return round(float(x), nd) if np.isfinite(x) else None


def _quality(
    rig: StereoRig,
    board: BoardSpec,
    fit: _StereoFit,
    *,
    used: list[int],
    lefts: list[BoardDetection],
    rights: list[BoardDetection],
    held_out: list[StereoView],
    collection: ViewCollection,
    selection: ViewSelection,
    rejected: list[int],
) -> dict[str, Any]:
    views = collection.views
    per_view = [
        {"frame": views[i].frame, "left_rms_px": _round(e[0]), "right_rms_px": _round(e[1])}
        for i, e in zip(used, fit.per_view, strict=True)
    ]
    epi_used = np.concatenate(
        [
            epipolar_errors_px(rig, *_pair_points(dl, dr)[1:])
            for dl, dr in zip(lefts, rights, strict=True)
        ]
    )
    # Held-out views: renumber right detections the way the fit expects.
    held_pairs: list[tuple[BoardDetection, BoardDetection]] = []
    for v in held_out:
        assert v.left is not None and v.right is not None
        held_pairs.append((v.left, _best_numbering(rig, board, v.left, v.right)))
    method = "held_out"
    if len(held_pairs) < 3:
        # No spare views: check the square length on the fitted views themselves.
        method = "fitted_views"
        held_pairs = list(zip(lefts, rights, strict=True))
    lengths = square_lengths_mm(rig, board, held_pairs)
    err = lengths - board.square_mm
    epi_held = (
        np.concatenate(
            [epipolar_errors_px(rig, *_pair_points(dl, dr)[1:]) for dl, dr in held_pairs]
        )
        if held_pairs
        else np.zeros(0)
    )
    pts_l = np.concatenate([d.corners_px for d in lefts])
    pts_r = np.concatenate([d.corners_px for d in rights])
    size_l, size_r = collection.sizes
    return {
        "rms_px": _round(fit.rms),
        "rms_px_left": _round(float(np.sqrt(np.mean(fit.per_view[:, 0] ** 2)))),
        "rms_px_right": _round(float(np.sqrt(np.mean(fit.per_view[:, 1] ** 2)))),
        "view_rms_px_max": _round(float(fit.per_view.max())),
        "per_view": per_view,
        "epipolar_px_mean": _nan_stat(np.nanmean, epi_used),
        "epipolar_px_max": _nan_stat(np.nanmax, epi_used),
        "epipolar_px_mean_check": _nan_stat(np.nanmean, epi_held),
        "square_mm": board.square_mm,
        "square_mm_measured": _nan_stat(np.nanmean, lengths),
        "square_error_mm_mean": _nan_stat(np.nanmean, err),
        "square_error_mm_rms": _nan_stat(lambda e: np.sqrt(np.nanmean(e**2)), err),
        "square_check_views": len(held_pairs),
        "square_check_method": method,
        "coverage_left": _round(image_coverage(pts_l, size_l), 3),
        "coverage_right": _round(image_coverage(pts_r, size_r), 3),
        "views_used": len(used),
        "views_rejected": len(rejected),
        "views_rejected_frames": [views[i].frame for i in rejected],
        "views_blurred": len(selection.blurred),
        "views_duplicate": selection.duplicates,
        "views_held_out": len(selection.held_out),
        "views_both_detected": sum(v.both for v in views),
        "frames_tried": collection.frames_tried,
        "frames_total": collection.frames_total,
        "frames_left_detected": _detected(collection.left_track, [v.left for v in views]),
        "frames_right_detected": _detected(collection.right_track, [v.right for v in views]),
        "baseline_mm": _round(rig.baseline_mm),
        "board": board.to_dict(),
        "source": collection.source,
        "method": "opencv calibrateCamera + stereoCalibrate (intrinsics free), 5-coefficient lens model",
        "sync": _sync_quality(collection),
        "warnings": [*collection.warnings, *_placement_warnings(rig)],
    }


def _placement_warnings(rig: StereoRig) -> list[str]:
    """A camera given as right that sits to the left of the one given as left: most likely
    the two recordings were exchanged (the fit itself is as good either way)."""
    x_mm = float(rig.right.center_world_mm[0])
    if x_mm >= 0:
        return []
    return [
        f"the camera given as right sits {-x_mm:.0f} mm to the left of the camera given as"
        " left: if the two recordings were exchanged, calibrate again with them swapped"
        " (analyses with this rig would measure the cameras the wrong way round)."
    ]


def _detected(track: BoardTrack | None, dets: Sequence[BoardDetection | None]) -> int:
    return track.detected if track is not None else sum(d is not None for d in dets)


def _sync_quality(collection: ViewCollection) -> dict[str, Any]:
    """``quality["sync"]``: how the views of the two recordings were paired in time."""
    if collection.sync is None:
        return {"method": board_sync.IMAGES if collection.source == "images" else "given"}
    doc = collection.sync.to_dict()
    if collection.right_track is not None:
        doc["fps_right"] = round(collection.right_track.fps, 4)
    doc["views_paired"] = sum(v.both for v in collection.views)
    return doc


def _best_numbering(
    rig: StereoRig, board: BoardSpec, dl: BoardDetection, dr: BoardDetection
) -> BoardDetection:
    """The right numbering (as given or a half turn off) with the smaller epipolar error."""
    if board.kind == "charuco":
        return dr
    options = [dr, dr.flipped(board)]
    errs = [float(np.mean(epipolar_errors_px(rig, *_pair_points(dl, o)[1:]))) for o in options]
    return options[int(np.argmin(errs))]


# -- verdict ------------------------------------------------------------------------

#: (good if <=, acceptable if <=) thresholds; see docs/calibration.md.
VERDICT_THRESHOLDS: dict[str, tuple[float, float]] = {
    "rms_px": (0.5, 1.0),
    "epipolar_px_mean": (0.3, 0.7),
    "square_error_relative": (0.002, 0.005),
}
#: (good if >=, acceptable if >=).
VERDICT_MINIMA: dict[str, tuple[float, float]] = {
    "coverage": (0.5, 0.3),
    "views_used": (15, MIN_VIEWS + 2),
}


def quality_verdict(quality: dict[str, Any]) -> tuple[str, list[str]]:
    """Judge a calibration from its quality figures.

    Returns
    -------
    verdict : {"good", "acceptable", "poor"}
        The worst of the figures' verdicts.
    reasons : list of str
        One sentence per figure that is not good (empty when all are good).
        Figures missing from ``quality`` are not judged.
    """
    levels = {"good": 0, "acceptable": 1, "poor": 2}
    worst = 0
    reasons: list[str] = []

    def judge(
        value: float | None, good: float, ok: float, higher_is_better: bool, text: str
    ) -> None:
        nonlocal worst
        if value is None or not np.isfinite(value):
            return
        if higher_is_better:
            level = 0 if value >= good else 1 if value >= ok else 2
        else:
            level = 0 if value <= good else 1 if value <= ok else 2
        if level:
            worst = max(worst, level)
            reasons.append(text)

    rms = quality.get("rms_px")
    g, a = VERDICT_THRESHOLDS["rms_px"]
    judge(
        rms,
        g,
        a,
        False,
        f"reprojection error {rms} px is above {g} px: blurred or mis-detected views, or a board that is not flat.",
    )
    epi = quality.get("epipolar_px_mean")
    g, a = VERDICT_THRESHOLDS["epipolar_px_mean"]
    judge(
        epi,
        g,
        a,
        False,
        f"epipolar error {epi} px is above {g} px: the two cameras' geometry is uncertain.",
    )
    sq_err = quality.get("square_error_mm_mean")
    sq = quality.get("square_mm")
    if sq_err is not None and sq:
        rel = abs(float(sq_err)) / float(sq)
        g, a = VERDICT_THRESHOLDS["square_error_relative"]
        judge(
            rel,
            g,
            a,
            False,
            f"board squares measure {float(sq_err):+.3f} mm off their true {sq:g} mm on average"
            f" ({100 * rel:.2f} %, above {100 * g:.1f} %): 3D lengths will be off by as much.",
        )
    cov_vals = [quality.get(k) for k in ("coverage_left", "coverage_right")]
    cov_known = [float(c) for c in cov_vals if c is not None]
    if cov_known:
        cov = min(cov_known)
        g, a = VERDICT_MINIMA["coverage"]
        judge(
            cov,
            g,
            a,
            True,
            f"the board covered only {100 * cov:.0f} % of the image (below {100 * g:.0f} %):"
            " move it into the corners and edges too.",
        )
    n = quality.get("views_used")
    g, a = VERDICT_MINIMA["views_used"]
    judge(
        n, g, a, True, f"only {n} views were used (below {g:g}): record more, varied board poses."
    )
    verdict = {v: k for k, v in levels.items()}[worst]
    return verdict, reasons

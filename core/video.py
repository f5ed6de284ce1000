"""Video input and output: probing, streaming decode, writing, stereo-pair checks.

Frames are streamed: :func:`iter_frames` decodes in a background thread into a
small bounded queue, so memory does not grow with the length of a video and
decoding overlaps with whatever the caller does with each frame (OpenCV
releases the GIL while it decodes), or, where no core is spare, in the
caller's own thread.

Gray frames come straight from the decoder's luma plane when the stream is
planar YUV or gray (no colour conversion at all). For YUV streams that plane
is in video range (16–235), a fixed affine change of intensity that marker
and board detection do not depend on.

Decoding is OpenCV's for colour frames and for what PyAV does not hand out as
a luma plane; gray frames of 8-bit YUV and gray streams are read-only views of
the luma plane of PyAV's decoder. AV1, which OpenCV's FFmpeg cannot decode, is
PyAV's in colour and gray alike. Both use FFmpeg and release the GIL while
they decode, and give the same pixels and timestamps to the bit; OpenCV
copies every raw frame, which cost a sixth of decoding a 1280x1024 MPEG-4
video (docs/performance.md). What OpenCV cannot tell reliably, PyAV reads
from the container: the number of frames of a Matroska/WebM file (browsers
write none), and whether the packets carry timestamps at all (a raw H.264
stream has none).
Writing H.264, HEVC, VP8 and VP9 with per-frame timestamps (variable frame
rate) is PyAV's too (:class:`VideoWriter`); OpenCV's writer has neither the
encoders nor per-frame timestamps.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import queue
import threading
from collections.abc import Callable, Generator, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import cv2
import numpy as np
from numpy.typing import NDArray

from core.camera import ImageSize, StereoRig
from core.errors import InputError

# Pixel formats whose first plane is the luma (or gray) image of width x height.
_LUMA_FIRST_FORMATS = frozenset(
    {"I420", "IYUV", "YV12", "NV12", "NV21", "Y800", "GREY", "Y42B", "444P", "422P"}
)

_IMAGE_SUFFIXES = frozenset(
    {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}
)

# Codec names for VideoWriter; "lossless" keeps every pixel exactly (FFV1).
_CODECS = {"lossless": ("FFV1", ".mkv"), "mp4v": ("mp4v", ".mp4"), "mjpg": ("MJPG", ".avi")}
# Written through PyAV (encoder, suffix, encoder options): what cameras and browsers record.
_AV_CODECS = {
    "h264": ("libx264", ".mp4", {"crf": "18", "preset": "superfast"}),
    "hevc": (
        "libx265",
        ".mp4",
        {"crf": "14", "preset": "veryfast", "x265-params": "log-level=error"},
    ),
    # crf 20: about 11 Mbit/s for a simulated 1920x1080 60 fps take, below the 37 Mbit/s the
    # capture page asks for (docs/capture.md), so the harder case; 40 % less CPU than crf 12
    "vp9": (
        "libvpx-vp9",
        ".webm",
        {"crf": "20", "b": "0", "deadline": "realtime", "cpu-used": "8"},
    ),
    "vp8": ("libvpx", ".webm", {"crf": "6", "b": "20M", "deadline": "realtime", "cpu-used": "8"}),
    # What newer browsers and phones record; OpenCV's FFmpeg cannot decode it, PyAV's can.
    "av1": ("libsvtav1", ".webm", {"crf": "20", "preset": "12", "svtav1-params": "lp=1"}),
}
CODECS = (*_CODECS, *_AV_CODECS)

# A container may report a frame count that differs a little from what decodes.
_FRAME_COUNT_SLACK = 2
# A stated frame rate within this factor of the packets' own (1 / median interval) is the
# stream's: a 1-ms time base makes a 60-fps stream's median interval 17 ms (58.8 fps).
# Beyond it (FFmpeg's 1000 fps for a browser's WebM, from its 1-ms time base), the
# packets' rate is.
_STATED_RATE_FACTOR = 1.5


def _fourcc_to_str(value: float) -> str:
    v = int(value)
    return "".join(chr((v >> (8 * i)) & 0xFF) for i in range(4)).rstrip("\x00").strip()


@dataclass(frozen=True)
class VideoInfo:
    """What a video file says about itself (after one frame was actually decoded).

    Attributes
    ----------
    path : Path
    fps : float
        Frames per second (Hz) from the container; for a Matroska/WebM file
        whose stated rate is not its packets' (a browser's WebM: FFmpeg states
        1000 fps, its 1-ms time base), ``1 / median interval`` of the packets'
        timestamps.
    frame_count : int
        Number of frames the container reports (a few may be missing at decode
        time in a damaged file; :func:`iter_frames` with ``strict=True`` tells).
    image_size : ImageSize
        ``(width, height)`` in pixels.
    fourcc : str
        Codec four-character code, e.g. ``"FFV1"`` or ``"mp4v"``.
    has_timestamps : bool
        Whether the container's packets carry presentation timestamps (a raw
        H.264/HEVC stream has none).
    rotation_deg : int
        The rotation the container asks for at display (a phone held upright
        stores landscape frames and a 90 or 270 degree display rotation), in
        degrees clockwise; frames are read rotated by it, so ``image_size``
        and every pixel position are those of the upright picture.
    """

    path: Path
    fps: float
    frame_count: int
    image_size: ImageSize
    fourcc: str
    has_timestamps: bool = True
    rotation_deg: int = 0

    @property
    def duration_s(self) -> float:
        return self.frame_count / self.fps


def decoder_threads_for(n_videos: int) -> int:
    """Decoder threads for each of ``n_videos`` videos decoded at the same time: the
    cores this process may use, shared out (at least 1).

    On 2 cores two videos decode fastest with one thread each: FFmpeg's frame
    threads (one per core in each decoder) only hand frames between threads
    there. Measured with analyze on a 10-s 1280x1024 100 fps MPEG-4 pair, 1.45 s
    instead of 1.55 s; 1920x1080 H.264, 7.80 s instead of 8.05 s (docs/performance.md).
    """
    if n_videos < 1:
        raise ValueError(f"n_videos must be >= 1, got {n_videos}")
    return max(1, len(os.sched_getaffinity(0)) // n_videos)


def decode_in_background(n_videos: int) -> bool:
    """Whether each of ``n_videos`` videos, decoded side by side by one thread each that
    also works on its frames, should be decoded ahead in a background thread: only when
    cores are left over. On 2 cores, decoding in the working thread saves the hand-over
    between threads: analyze on a 10-s 1280x1024 100 fps MPEG-4 pair, 1.34 s instead of
    1.44 s; 1080p60 H.264, 7.74 s instead of 7.98 s (docs/performance.md)."""
    if n_videos < 1:
        raise ValueError(f"n_videos must be >= 1, got {n_videos}")
    return len(os.sched_getaffinity(0)) > n_videos


def video_capture(path: str | Path, *, threads: int | None = None) -> cv2.VideoCapture:
    """``cv2.VideoCapture`` of a file through FFmpeg, frames upright.

    The container's display rotation (an MP4/MOV display matrix, a phone held
    upright) is applied to every frame (``CAP_PROP_ORIENTATION_AUTO``, also to
    the raw luma plane that :func:`iter_frames` reads), as a player shows it;
    ``tests/core/test_video_formats.py`` checks it against PyAV's frames and
    rotation. It may not be open: check ``isOpened()``. ``threads``: the
    decoder's threads (None: FFmpeg's choice, one per core).
    """
    if threads is not None and threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    params = [] if threads is None else [cv2.CAP_PROP_N_THREADS, threads]
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG, params)
    if cap.isOpened():
        cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)  # OpenCV's default; said, not assumed
    return cap


def _open_capture(path: Path, threads: int | None = None) -> cv2.VideoCapture:
    cap = video_capture(path, threads=threads)
    if not cap.isOpened():
        cap.release()
        raise InputError(
            f"{path.name} could not be opened as a video; check that it is a complete video file"
            " (for example MP4, AVI or MKV) and not an image, a document or a truncated upload."
        )
    return cap


#: FFmpeg's AVFMT_NOTIMESTAMPS: the format stores no timestamps (raw elementary streams).
_AVFMT_NOTIMESTAMPS = 0x0080
#: A stretch without frames longer than both of these (s, frame intervals) is a hole that
#: no measurement crosses: a damaged file (a demuxer skips what it cannot read) or a stop.
#: The capture page applies the same rule to a take before sending it (app/web/capture.py).
HOLE_S = 0.5
HOLE_FRAMES = 10


def _stated_duration_s(container: Any, stream: Any) -> float | None:
    """The video stream's duration as the container states it (s), or None.

    Read from the stream's own duration (MP4, MOV), else its ``DURATION`` tag
    (what FFmpeg's Matroska muxer writes per track), else the container's
    duration when the video is its only stream (an audio track may be longer).
    A file written live, as a browser's MediaRecorder writes WebM, states none.
    """
    if stream.duration and stream.time_base:
        return float(stream.duration * stream.time_base)
    tag = stream.metadata.get("DURATION") or stream.metadata.get("duration")
    if tag:
        try:
            hours, minutes, seconds = tag.split(":")
            return int(hours) * 3600.0 + int(minutes) * 60.0 + float(seconds)
        except ValueError:
            pass  # an unreadable tag states nothing
    if container.duration and len(container.streams) == 1:
        return float(container.duration) / 1e6  # AV_TIME_BASE: microseconds
    return None


def _count_packets(
    container: Any, stream: Any, *, fps: float | None
) -> tuple[int, bool, float | None, tuple[float, float, float] | None]:
    """Demux every packet of ``stream`` (no decoding).

    Returns the number of packets holding a frame, whether any carries a
    presentation timestamp, the time they cover (s): from the first
    timestamp to the end of the last frame (its packet duration, or one
    frame period when the packet states none), None without timestamps; and
    the longest stretch between two consecutive frames (start, end in s from
    the first frame) with the median interval between frames (s), None with
    fewer than two timestamps. The median interval is the packets' own rate:
    a browser's WebM states none (FFmpeg guesses 1000 fps from its 1-ms time
    base). A damaged file counts what demuxed before the damage.
    """
    import av

    counted = 0
    pts: list[int] = []
    end: int | None = None
    tb = stream.time_base
    one_frame = round(1.0 / (fps * tb)) if fps and tb else 0
    try:
        for packet in container.demux(stream):
            if packet.size == 0:  # the flush packet at the end
                continue
            counted += 1
            if packet.pts is None:
                continue
            pts.append(packet.pts)
            stop = packet.pts + (packet.duration or one_frame)
            end = stop if end is None else max(end, stop)
    except (av.FFmpegError, OSError):
        pass  # damaged part-way: decoding tells the rest
    if not pts or end is None or not tb:
        return counted, bool(pts), None, None
    first = min(pts)
    covered = float((end - first) * tb)
    hole = None
    if len(pts) > 1:
        ordered = np.sort(np.asarray(pts, dtype=np.int64))
        steps = np.diff(ordered)
        k = int(np.argmax(steps))
        hole = (
            float((ordered[k] - first) * tb),
            float((ordered[k + 1] - first) * tb),
            float(np.median(steps) * tb),
        )
    return counted, True, covered, hole


def _container_facts(path: Path) -> tuple[int | None, bool, float | None, float | None]:
    """What the container says, read by PyAV without decoding.

    Returns the number of video frames, whether the packets carry presentation
    timestamps, the stated frame rate (None if none), and the rate of the
    packets' own timestamps (``1 / median interval``; None unless the packets
    were counted and hold two timestamps or more); all None/True when PyAV
    cannot open the file (OpenCV's answer then stands).

    A container that states no frame count (Matroska, WebM) has its packets
    counted. If it states a duration that its packets fall short of by more
    than :data:`_FRAME_COUNT_SLACK` frames, the file was cut off (its header
    was written whole, its frames were not): the frame count returned is the
    one the duration announces, so that the missing end is found by
    :func:`iter_frames` and by decoding the last frames. A file that states
    no duration (a browser's live WebM) is taken as its packets are.
    """
    import av

    try:
        container = av.open(str(path))
    except (av.FFmpegError, OSError, ValueError):
        return None, True, None, None
    try:
        fmt = container.format.name
        if not container.streams.video or fmt == "image2" or fmt.endswith("_pipe"):
            return None, True, None, None  # a still image: OpenCV's answer (no frames) stands
        stream = container.streams.video[0]
        rate = stream.average_rate or stream.base_rate
        fps = float(rate) if rate else None
        if container.format.flags & _AVFMT_NOTIMESTAMPS:
            # A raw stream (H.264, HEVC, MJPEG, MPEG-4 elementary): the demuxer invents
            # timestamps from a default rate; they carry no information.
            count, _, _, _ = _count_packets(container, stream, fps=fps)
            return count, False, fps, None
        if stream.frames:
            has_pts = False
            try:
                for n, packet in enumerate(container.demux(stream)):
                    has_pts = has_pts or packet.pts is not None
                    if has_pts or n >= 8:
                        break
            except (av.FFmpegError, OSError):
                pass  # damaged: decoding tells the rest
            return int(stream.frames), has_pts, fps, None
        stated_s = _stated_duration_s(container, stream)
        count, has_pts, covered_s, hole = _count_packets(container, stream, fps=fps)
        if hole is not None:
            start, stop, interval = hole
            if interval > 0 and stop - start > max(HOLE_S, HOLE_FRAMES * interval):
                raise InputError(
                    f"{path.name} has no frames between {start:.2f} s and {stop:.2f} s (about"
                    f" {round((stop - start) / interval) - 1} frames missing at its"
                    f" {1 / interval:.0f} frames per second): the camera delivered no frames"
                    " for that long (a computer too busy to take them, or a camera that"
                    " paused) or the file is damaged; record it again, or copy or export it"
                    " again."
                )
        if stated_s is not None and covered_s is not None and fps:
            missing = round((stated_s - covered_s) * fps)
            if missing > _FRAME_COUNT_SLACK:
                count += missing
        packet_fps = 1.0 / hole[2] if hole is not None and hole[2] > 0 else None
        return count, has_pts, fps, packet_fps
    finally:
        container.close()


def probe_video(path: str | Path, *, fps_if_none: float | None = None) -> VideoInfo:
    """Open a video, decode its first frame and return what it says about itself.

    Parameters
    ----------
    path : str or Path
    fps_if_none : float, optional
        The frame rate to use when the video states neither a frame rate nor
        frame timestamps (a raw H.264/HEVC/MJPEG stream): the rate of its
        timestamps file, which then gives each frame's time.

    Raises
    ------
    InputError
        The file is missing, is not a video, has no decodable frame, or states
        neither a frame rate nor frame timestamps (and no ``fps_if_none``).
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"the video {p.name} does not exist; check the path.")
    if p.stat().st_size == 0:
        raise InputError(f"the video {p.name} is empty (0 bytes); record or upload it again.")
    version = _file_version(p)
    try:
        cap = _open_capture(p)
    except InputError:
        _remember_opencv_decodes(version, False)
        if not _pyav_decodes(p):
            raise
        cap = None
    ok, frame = False, None
    if cap is not None:
        try:
            fps = float(cap.get(cv2.CAP_PROP_FPS))
            frame_count = round(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            ok, frame = cap.read()
            fourcc = _fourcc_to_str(cap.get(cv2.CAP_PROP_FOURCC))
            rotation = round(cap.get(cv2.CAP_PROP_ORIENTATION_META)) % 360
        finally:
            cap.release()
        # what iter_frames asks before it decodes: no second open and first frame
        _remember_opencv_decodes(version, bool(ok and frame is not None))
    if not ok or frame is None:
        # OpenCV's FFmpeg lacks some decoders (AV1): PyAV's has them.
        first = _pyav_first_frame(p)
        if first is None:
            raise InputError(_undecodable_message(p))
        frame, fps, frame_count, fourcc, rotation = first
    count, has_pts, stated_fps, packet_fps = _container_facts(p)
    if count is not None and count > 0:
        frame_count = count
    if (
        has_pts
        and packet_fps
        and not (1.0 / _STATED_RATE_FACTOR < fps / packet_fps < _STATED_RATE_FACTOR)
    ):
        # A browser's WebM states no rate: OpenCV gives FFmpeg's guess from its 1-ms time
        # base, 1000 fps. The packets' own rate, as their times are read (core.timing).
        fps = packet_fps
    if not has_pts:
        # A raw stream: FFmpeg invents 25 fps unless the bitstream states a rate.
        fps = stated_fps if stated_fps is not None and stated_fps != 25 else 0.0
    if not (fps > 0 and np.isfinite(fps)) and fps_if_none is not None and fps_if_none > 0:
        fps = float(fps_if_none)
    if not (fps > 0 and np.isfinite(fps)) or frame_count <= 0:
        image = _image_message(p)  # an image decodes as one frame: no rate, no frame count
        if image is not None:
            raise InputError(image)
    if not (fps > 0 and np.isfinite(fps)):
        raise InputError(
            f"{p.name} has neither frame timestamps nor a frame rate; give its capture times in"
            " a timestamps file (frame,time_s) or re-export it with a fixed frame rate."
        )
    if frame_count <= 0:
        raise InputError(f"{p.name} reports no frames; the file is corrupt or still being written.")
    return VideoInfo(
        path=p,
        fps=fps,
        frame_count=frame_count,
        image_size=ImageSize.of_image(frame),
        fourcc=fourcc,
        has_timestamps=has_pts,
        rotation_deg=rotation,
    )


class _QuietOpenCV:
    """Raise OpenCV's log level to ERROR while at least one luma reader runs.

    OpenCV warns on every frame that it hands out the raw planar buffer
    ("yuv420p ... treated as 8UC1"), which is exactly what we ask for. The
    level is process-wide, so it is reference-counted across reader threads.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._users = 0
        self._saved = 0

    def __enter__(self) -> None:
        with self._lock:
            if self._users == 0:
                self._saved = cv2.utils.logging.getLogLevel()
                cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
            self._users += 1

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0:
                cv2.utils.logging.setLogLevel(self._saved)


_quiet_opencv = _QuietOpenCV()

# Decoder threads still running. They are stopped at interpreter exit: a
# daemon thread frozen inside OpenCV while Python finalises aborts the process.
_live_readers: dict[threading.Thread, threading.Event] = {}
_live_lock = threading.Lock()


@atexit.register
def _stop_readers() -> None:
    with _live_lock:
        readers = list(_live_readers.items())
    for _, halt in readers:
        halt.set()
    for thread, _ in readers:
        thread.join(timeout=5.0)


def _codec_name(path: Path) -> str | None:
    """The long name of the first video stream's codec, as PyAV reads it (None if none)."""
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                return None
            codec = container.streams.video[0].codec_context.codec
            return str(codec.long_name or codec.name)
    except (av.FFmpegError, OSError, ValueError):
        return None


_IMAGE_SIGNATURES = (
    (0, b"\x89PNG\r\n\x1a\n", "PNG"),
    (0, b"\xff\xd8\xff", "JPEG"),
    (0, b"GIF87a", "GIF"),
    (0, b"GIF89a", "GIF"),
    (8, b"WEBP", "WebP"),
    (0, b"II*\x00", "TIFF"),
    (0, b"MM\x00*", "TIFF"),
    (0, b"BM", "BMP"),
    (8, b"heic", "HEIC"),
    (8, b"heix", "HEIC"),
    (8, b"mif1", "HEIF"),
    (8, b"avif", "AVIF"),
)
"""Where an image file's magic bytes sit, what they are and the format they name."""
#: How far into a file that begins as a JPEG the second picture of an MJPEG stream is
#: looked for (bytes; a 4K JPEG frame is a few MB at most).
_MJPEG_LOOK = 16 << 20


def _image_message(path: Path) -> str | None:
    """The sentence for a still image given as a video (told by its first bytes), or None."""
    try:
        with path.open("rb") as f:
            head = f.read(16)
            # a raw MJPEG stream begins as a JPEG does: its next picture follows the first's
            # end (an EXIF thumbnail's end is followed by the image's next segment instead)
            mjpeg = head.startswith(b"\xff\xd8") and b"\xff\xd9\xff\xd8" in head + f.read(
                _MJPEG_LOOK
            )
    except OSError:
        return None
    if mjpeg:
        return None
    for at, magic, kind in _IMAGE_SIGNATURES:
        if head[at : at + len(magic)] == magic:
            return (
                f"{path.name} is a {kind} image, not a video (renamed or exported as a"
                " picture); give the recorded video file of the camera."
            )
    return None


def _undecodable_message(path: Path) -> str:
    image = _image_message(path)
    if image is not None:
        return image
    codec = _codec_name(path)
    if codec is None:
        return f"no frame of {path.name} could be decoded; the file is corrupt or not a video."
    return (
        f"no frame of {path.name} could be decoded: it holds {codec} video that this installation"
        " cannot decode, or the file is corrupt; re-export it as H.264 (MP4)."
    )


# Whether OpenCV's FFmpeg decodes the first frame, per file version (path, mtime, size):
# probe_video finds out as it reads the first frame, and iter_frames asks again.
_opencv_decodes_known: dict[tuple[str, int, int], bool] = {}
_opencv_decodes_lock = threading.Lock()
_OPENCV_DECODES_KEPT = 64


def _file_version(path: Path) -> tuple[str, int, int]:
    st = path.stat()
    return str(path), st.st_mtime_ns, st.st_size


def _remember_opencv_decodes(version: tuple[str, int, int], decodes: bool) -> None:
    with _opencv_decodes_lock:
        _opencv_decodes_known.pop(version, None)
        _opencv_decodes_known[version] = decodes
        while len(_opencv_decodes_known) > _OPENCV_DECODES_KEPT:
            del _opencv_decodes_known[next(iter(_opencv_decodes_known))]  # the oldest


def _opencv_decodes(path: Path) -> bool:
    """Whether OpenCV's FFmpeg decodes the first frame of the file (cached per file version)."""
    version = _file_version(path)
    with _opencv_decodes_lock:
        known = _opencv_decodes_known.get(version)
    if known is None:
        cap = video_capture(path)
        try:
            known = bool(cap.isOpened() and cap.read()[0])
        finally:
            cap.release()
        _remember_opencv_decodes(version, known)
    return known


def _pyav_decodes(path: Path) -> bool:
    return _pyav_first_frame(path) is not None


def _upright(image: NDArray[Any], frame: Any) -> NDArray[Any]:
    """A PyAV frame's pixels turned as its display matrix says (FFmpeg counts
    counter-clockwise; np.rot90 too)."""
    turn = round(float(getattr(frame, "rotation", 0) or 0) / 90.0) % 4
    return np.ascontiguousarray(np.rot90(image, turn)) if turn else image


def _pyav_first_frame(path: Path) -> tuple[NDArray[np.uint8], float, int, str, int] | None:
    """``(upright BGR frame, fps, frame count, fourcc, rotation_deg)`` decoded by PyAV."""
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                return None
            stream = container.streams.video[0]
            frame = next(container.decode(stream), None)
            if frame is None:
                return None
            rate = stream.average_rate or stream.base_rate
            image = _upright(frame.to_ndarray(format="bgr24"), frame)
            rotation = (-round(float(getattr(frame, "rotation", 0) or 0))) % 360
            name = str(stream.codec_context.codec_tag or stream.codec_context.codec.name)[:4]
            return image, float(rate) if rate else 0.0, int(stream.frames or 0), name, rotation
    except (av.FFmpegError, OSError, ValueError, StopIteration):
        return None


def read_frame(path: str | Path, index: int, *, gray: bool = True) -> NDArray[np.uint8] | None:
    """Frame ``index`` of a video, upright, found by seeking (fast, not frame-exact in every
    container); None where it does not decode."""
    if index < 0:
        raise ValueError(f"index must be >= 0, got {index}")
    p = Path(path)
    if not p.is_file():
        return None
    if _opencv_decodes(p):
        cap = video_capture(p)
        try:
            if not cap.set(cv2.CAP_PROP_POS_FRAMES, float(index)):
                return None
            ok, frame = cap.read()
        finally:
            cap.release()
        if not ok or frame is None or frame.size == 0:
            return None
        image = np.asarray(frame, dtype=np.uint8)
        if gray and image.ndim == 3:
            image = np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
        return image
    return _pyav_read_frame(p, index, gray=gray)


def _pyav_read_frame(path: Path, index: int, *, gray: bool) -> NDArray[np.uint8] | None:
    import av

    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            rate = float(stream.average_rate or stream.base_rate or 0)
            if rate <= 0 or stream.time_base is None:
                return None
            target = index / rate
            container.seek(int(target / float(stream.time_base)), stream=stream, backward=True)
            for frame in container.decode(stream):
                if frame.time is not None and frame.time >= target - 0.5 / rate:
                    image = frame.to_ndarray(format="gray" if gray else "bgr24")
                    return np.asarray(_upright(image, frame), dtype=np.uint8)
    except (av.FFmpegError, OSError, ValueError, IndexError):
        return None
    return None


def decodes_frame(path: str | Path, index: int) -> bool:
    """True if frame ``index`` of the video decodes; seeks, so it is fast on long videos.

    Used to catch truncated files whose header still announces every frame.
    """
    return read_frame(path, index) is not None


#: Decoded frames: a generator, closed to release its decoder.
_Frames = Generator[NDArray[np.uint8], None, None]


def _reader(frames: _Frames, out: queue.Queue[Any], halt: threading.Event) -> None:
    """Hand ``frames`` to ``out``; ends with ``None`` (done) or an exception instance."""
    try:
        try:
            for frame in frames:
                if halt.is_set():
                    break
                _hand_over(out, halt, frame)
        finally:
            frames.close()  # releases the decoder
        out.put(None)
    except BaseException as exc:  # handed to the consumer, which re-raises it
        out.put(exc)
    finally:
        with _live_lock:
            _live_readers.pop(threading.current_thread(), None)


def _decoded(
    path: Path,
    gray: bool,
    start: int,
    stop: int | None,
    times: list[float] | None,
    threads: int | None,
) -> _Frames:
    """The frames ``[start, stop)`` of ``path``, decoded in the thread that iterates."""
    if not _opencv_decodes(path):  # AV1: PyAV's FFmpeg decodes it, OpenCV's cannot
        yield from _decoded_av(_pyav_container(path), gray, start, stop, times, threads)
        return
    if gray:
        container = _luma_container(path)
        if container is not None:
            yield from _decoded_av(container, gray, start, stop, times, threads)
            return
    cap = _open_capture(path, threads)
    try:
        luma = False
        if gray:
            pix = _fourcc_to_str(cap.get(cv2.CAP_PROP_CODEC_PIXEL_FORMAT))
            if pix in _LUMA_FIRST_FORMATS:
                luma = bool(cap.set(cv2.CAP_PROP_CONVERT_RGB, 0))
        if luma:
            with _quiet_opencv:
                yield from _decoded_cv(cap, path, gray, luma, start, stop, times)
        else:
            yield from _decoded_cv(cap, path, gray, luma, start, stop, times)
    finally:
        cap.release()


def _decoded_cv(
    cap: cv2.VideoCapture,
    path: Path,
    gray: bool,
    luma: bool,
    start: int,
    stop: int | None,
    times: list[float] | None,
) -> Generator[Any, None, None]:
    if start > 0:
        # Seeking is not frame-exact in every container: grab instead.
        for _ in range(start):
            if not cap.grab():
                break
    index = start
    width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
    height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    while stop is None or index < stop:
        ok, frame = cap.read()
        if not ok or frame is None:
            break
        if times is not None:
            # The presentation timestamp of the frame just decoded (ms); what
            # PyAV reads from the container (tests/core/test_timing.py).
            times.append(cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
        if gray:
            if luma:
                if frame.ndim != 2 or frame.shape[0] < height or frame.shape[1] != width:
                    raise InputError(
                        f"{path.name} decodes to an unexpected raw layout {frame.shape};"
                        " re-encode it (for example as MP4)."
                    )
                frame = frame[:height]
            elif frame.ndim == 3:
                frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        yield frame
        index += 1


# FFmpeg's names of the 8-bit pixel formats whose first plane is the luma (or gray) image:
# those that OpenCV's raw frames name by one of _LUMA_FIRST_FORMATS (yuvj* are JPEG's
# full-range twins; tests/core/test_video_formats.py checks the list against OpenCV).
_LUMA_FIRST_PIX_FMTS = frozenset(
    {"gray", "yuv420p", "yuvj420p", "yuv422p", "yuvj422p", "yuv444p", "yuvj444p", "nv12", "nv21"}
)


def _luma_container(path: Path) -> Any | None:
    """``path`` opened by PyAV when its video's first plane is the 8-bit luma image (the
    plane OpenCV would hand out raw, see :func:`_decoded`), else None."""
    import av

    try:
        container = av.open(str(path))
    except (av.FFmpegError, OSError, ValueError):
        return None  # OpenCV opens it (checked before): its path says what fails
    try:
        if container.streams.video and (
            container.streams.video[0].codec_context.pix_fmt in _LUMA_FIRST_PIX_FMTS
        ):
            return container
    except (av.FFmpegError, ValueError):
        pass  # no known pixel format before decoding: OpenCV's path
    container.close()
    return None


def _pyav_container(path: Path) -> Any:
    """``path`` opened by PyAV, or :class:`InputError` saying that it does not decode."""
    import av

    try:
        return av.open(str(path))
    except (av.FFmpegError, OSError, ValueError) as exc:
        raise InputError(_undecodable_message(path)) from exc


def _decoded_av(
    container: Any,
    gray: bool,
    start: int,
    stop: int | None,
    times: list[float] | None,
    threads: int | None,
) -> _Frames:
    """:func:`_decoded_cv`'s frames through PyAV's decoder, from an open container (closed
    at the end): gray frames are the luma plane (:func:`_luma_plane`), colour frames BGR.

    Gray frames of the codecs OpenCV decodes too are the same pixels and timestamps (to the
    bit) as OpenCV's raw frames, without OpenCV's copy of each frame, which cost a sixth of
    decoding a 1280x1024 MPEG-4 video. Those of AV1, which OpenCV cannot decode, are its
    luma plane as well, as for every other codec (before algorithm 2026.3: swscale's gray,
    which stretches video range to full range). The frames are read-only views of the
    decoder's picture where they can be (a frame changed in place would be the reference
    of the next ones); one that must change is copied first.
    """
    import av

    try:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        if threads is not None:
            stream.thread_count = threads
        # OpenCV's CAP_PROP_POS_MSEC: (pts - the stream's start) x time base, in ms
        origin = stream.start_time or 0
        tick_s = stream.time_base.numerator / stream.time_base.denominator
        index = 0
        for frame in _frames_of(container, stream):
            if stop is not None and index >= stop:
                break
            if index >= start:
                if times is not None:
                    pts = frame.pts if frame.pts is not None else frame.dts
                    times.append(
                        np.nan if pts is None else (pts - origin) * tick_s * 1000.0 / 1000.0
                    )
                try:
                    image = _luma_plane(frame) if gray else _bgr(frame)
                except av.FFmpegError as exc:
                    raise InputError(
                        f"frame {index} of {Path(container.name).name} decodes but cannot be"
                        f" converted from {frame.format.name}: {exc}; re-encode the video"
                        " (for example as MP4)."
                    ) from exc
                yield image
            index += 1
    finally:
        container.close()


def _frames_of(container: Any, stream: Any) -> Generator[Any, None, None]:
    """The decoded frames of ``stream``, up to the first packet that cannot be read or
    decoded: where OpenCV's reader ends a damaged video too."""
    import av

    with contextlib.suppress(av.FFmpegError):
        yield from container.decode(stream)


def _luma_plane(frame: Any) -> NDArray[np.uint8]:
    """The upright luma plane of a decoded PyAV frame, a read-only view where it can be."""
    if frame.format.name not in _LUMA_FIRST_PIX_FMTS:
        # not 8-bit luma first (10-bit AV1, or a stream that changed format): swscale's
        # gray, stretched to full range as OpenCV's gray of such streams is
        image = frame.to_ndarray(format="gray")
    else:
        plane = frame.planes[0]
        width, height, line = frame.width, frame.height, plane.line_size
        rows = np.frombuffer(plane, np.uint8, count=line * height).reshape(height, line)
        if line == width:
            image = rows
            image.flags.writeable = False
        else:  # rows padded for alignment: a C-contiguous copy, as the detector needs
            image = np.ascontiguousarray(rows[:, :width])
    return _upright(image, frame)


def _bgr(frame: Any) -> NDArray[np.uint8]:
    """The upright BGR image of a decoded PyAV frame."""
    return np.asarray(_upright(frame.to_ndarray(format="bgr24"), frame), dtype=np.uint8)


def _hand_over(out: queue.Queue[Any], halt: threading.Event, item: Any) -> None:
    """Queue ``item`` for the consumer, waiting while the queue is full, unless halted."""
    while not halt.is_set():
        try:
            out.put(item, timeout=0.1)
            return
        except queue.Full:
            continue


def _from_reader(frames: _Frames, name: str, prefetch: int) -> _Frames:
    """``frames`` decoded ahead in a background thread, at most ``prefetch`` of them."""
    out: queue.Queue[Any] = queue.Queue(maxsize=prefetch)
    halt = threading.Event()
    thread = threading.Thread(target=_reader, args=(frames, out, halt), name=name, daemon=True)
    with _live_lock:
        _live_readers[thread] = halt
    thread.start()
    try:
        while True:
            item = out.get()
            if item is None:
                break
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        halt.set()
        # Drain so the reader can see the halt flag and exit.
        while thread.is_alive():
            try:
                out.get(timeout=0.05)
            except queue.Empty:
                pass
        thread.join()


def iter_frames(
    path: str | Path,
    *,
    gray: bool = True,
    start: int = 0,
    stop: int | None = None,
    prefetch: int = 8,
    expected_count: int | None = None,
    times_out: list[float] | None = None,
    decoder_threads: int | None = None,
    background: bool = True,
) -> Iterator[NDArray[np.uint8]]:
    """Stream the frames of a video, decoded in a background thread (or in the caller's).

    Parameters
    ----------
    path : str or Path
    gray : bool
        Yield ``(H, W)`` uint8 gray frames (the luma plane when the codec has
        one); otherwise ``(H, W, 3)`` BGR.
    start, stop : int
        Frame range ``[start, stop)`` of the video.
    prefetch : int
        Frames decoded ahead by the background thread (bounded memory).
    expected_count : int, optional
        If given, raise :class:`InputError` when the video ends more than two
        frames before ``min(stop, expected_count)``: it is truncated (the file ends
        before that frame's bytes) or damaged there (its bytes go on but do not decode).
    times_out : list, optional
        Receives the presentation timestamp (s) of every yielded frame, in
        order (appended by the decoding thread before the frame is handed out).
    decoder_threads : int, optional
        The decoder's own threads (default: FFmpeg's, one per core). Videos
        decoded side by side take :func:`decoder_threads_for` their number.
    background : bool
        Decode in a background thread, ahead of the caller's work on each frame
        (which then runs on another core). False: decode in the caller's thread,
        the faster when every core is busy already (:func:`decode_in_background`).

    Yields
    ------
    ndarray
        One frame at a time; frame ``i`` is at ``i / fps`` seconds. A gray frame may
        be read-only (a view of the decoder's picture): copy it to change it.
    """
    if start < 0 or (stop is not None and stop < start):
        raise ValueError(f"need 0 <= start <= stop, got start={start}, stop={stop}")
    if prefetch < 1:
        raise ValueError(f"prefetch must be >= 1, got {prefetch}")
    if decoder_threads is not None and decoder_threads < 1:
        raise ValueError(f"decoder_threads must be >= 1, got {decoder_threads}")
    p = Path(path)
    frames = _decoded(p, gray, start, stop, times_out, decoder_threads)
    if background:
        frames = _from_reader(frames, f"decode-{p.name}", prefetch)
    n = 0
    try:
        for image in frames:
            n += 1
            yield image
    finally:
        frames.close()
    if expected_count is not None:
        wanted = (expected_count if stop is None else min(stop, expected_count)) - start
        if n < wanted - _FRAME_COUNT_SLACK:
            if _bytes_go_on(p, start + n):
                raise InputError(
                    f"{p.name} could not be decoded after frame {start + n} of {start + wanted}:"
                    " the file is damaged there; copy or export the recording again."
                )
            raise InputError(
                f"{p.name} ends after {start + n} of {start + wanted} frames: the file is truncated;"
                " upload or copy the complete recording."
            )


def _bytes_go_on(path: Path, index: int) -> bool:
    """True if the file holds the bytes of frame ``index``'s packet (the first frame that
    did not decode), so that decoding stopped at damage in the middle of the file; False
    when the file ends before them (truncated), or when PyAV cannot tell."""
    import av

    try:
        size = path.stat().st_size
        with av.open(str(path)) as container:
            packets = (p for p in container.demux(container.streams.video[0]) if p.size)
            for n, packet in enumerate(packets):
                if n == index:
                    return packet.pos is not None and 0 <= packet.pos <= size - packet.size
    except (av.FFmpegError, OSError, ValueError, IndexError):
        pass  # the demuxer stopped there too: the file ends
    return False


def _realtime_threads() -> set[int]:
    """The ids of this process's threads that run under a real-time policy (FIFO or RR)."""
    if not hasattr(os, "sched_getscheduler") or not os.path.isdir("/proc/self/task"):
        return set()
    found = set()
    for name in os.listdir("/proc/self/task"):
        with contextlib.suppress(ProcessLookupError):  # a thread that has ended meanwhile
            if os.sched_getscheduler(int(name)) in (os.SCHED_FIFO, os.SCHED_RR):
                found.add(int(name))
    return found


def _end_realtime_scheduling(before: set[int]) -> None:
    """Put back under the normal policy the threads an encoder made real-time.

    SVT-AV1 (``libsvtav1``) switches the thread that opens it to SCHED_FIFO at the
    highest priority wherever it may (as root, in a container), and its own threads
    inherit that: every later computation of the thread, and anything it starts, then
    runs before everything else on its core. In a test run that turned a pytest worker
    real-time, and a busy-waiting encoder of the same worker, with a browser on the
    other core, stopped the machine's other work for minutes.
    """
    for tid in _realtime_threads() - before:
        with contextlib.suppress(ProcessLookupError):
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))


class VideoWriter:
    """Write frames to a video file, optionally with a capture time per frame.

    ``"lossless"``, ``"mp4v"`` and ``"mjpg"`` go through ``cv2.VideoWriter``
    (constant frame rate); ``"h264"``, ``"hevc"``, ``"vp9"`` and ``"vp8"``
    through PyAV, which also stores per-frame timestamps (variable frame rate:
    pass ``time_s`` to :meth:`write`).

    Parameters
    ----------
    path : str or Path
        Output file. Its suffix should match the codec (see :func:`video_suffix`).
    fps : float
        Frame rate (Hz); frame ``i`` is at ``i / fps`` unless a time is given.
    image_size : ImageSize
    codec : str
        One of :data:`CODECS`: ``"lossless"`` is FFV1 in MKV (every pixel
        kept, large files); ``"mp4v"`` MPEG-4 part 2 (small files, artefacts);
        ``"h264"``/``"hevc"`` in MP4 and ``"vp9"``/``"vp8"``/``"av1"`` in WebM
        are what cameras, phones and browsers record (high quality settings).
    is_color : bool
        Frames are ``(H, W, 3)`` BGR if True, ``(H, W)`` gray otherwise.
    rotation_deg : int
        PyAV codecs: a display rotation (0, 90, 180 or 270 degrees clockwise)
        stored in the container, as a phone held upright records: frames are
        written as given (``image_size``, the sensor's) and shown, and read by
        :func:`iter_frames`, rotated by it.
    encoder_options : mapping of str to str, optional
        PyAV codecs: FFmpeg options of the encoder over the codec's own, for
        example ``{"preset": "ultrafast"}`` for H.264.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        fps: float,
        image_size: ImageSize,
        codec: str = "lossless",
        is_color: bool = False,
        rotation_deg: int = 0,
        encoder_options: Mapping[str, str] | None = None,
    ) -> None:
        if codec not in CODECS:
            raise ValueError(f"codec must be one of {sorted(CODECS)}, got {codec!r}")
        if encoder_options and codec not in _AV_CODECS:
            raise ValueError(f"encoder_options need a PyAV codec, not {codec!r}")
        self._encoder_options = dict(encoder_options or {})
        if rotation_deg % 90 or (rotation_deg % 360 and codec not in _AV_CODECS):
            raise ValueError(
                f"rotation_deg must be a multiple of 90 and needs a PyAV codec, got {rotation_deg}"
            )
        self.rotation_deg = rotation_deg % 360
        if not fps > 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.path = Path(path)
        self.image_size = ImageSize(*image_size)
        self.is_color = is_color
        self.frames_written = 0
        self.fps = float(fps)
        self._av: Any = None
        self._writer: Any = None
        if codec in _AV_CODECS:
            self._open_av(codec)
            return
        fourcc = cv2.VideoWriter.fourcc(*_CODECS[codec][0])
        self._writer = cv2.VideoWriter(
            str(self.path), cv2.CAP_FFMPEG, fourcc, float(fps), tuple(self.image_size), is_color
        )
        if not self._writer.isOpened():
            raise InputError(f"cannot write the video {self.path.name} with codec {codec}.")

    def _open_av(self, codec: str) -> None:
        import fractions

        import av

        encoder, suffix, options = _AV_CODECS[codec]
        try:
            container = av.open(str(self.path), "w")
            # WebM counts in milliseconds; MP4 in 1/90000 s (as cameras write it).
            tb = fractions.Fraction(1, 1000 if suffix == ".webm" else 90000)
            stream: Any = container.add_stream(
                encoder, rate=fractions.Fraction(self.fps).limit_denominator(1001)
            )
            stream.width, stream.height = self.image_size
            stream.pix_fmt = "yuv420p"
            if self.rotation_deg:
                # FFmpeg's display matrix turns counter-clockwise.
                stream.set_display_rotation(-self.rotation_deg)
            stream.time_base = tb
            stream.codec_context.time_base = tb
            stream.options = {**options, **self._encoder_options}
            realtime_before = _realtime_threads()
            stream.codec_context.open()
            _end_realtime_scheduling(realtime_before)
        except (av.FFmpegError, OSError, ValueError) as exc:
            raise InputError(
                f"cannot write the video {self.path.name} with codec {codec}."
            ) from exc
        self._av = (container, stream, tb)
        self._last_pts = -1

    def write(self, frame: NDArray[np.uint8], *, time_s: float | None = None) -> None:
        """Append one uint8 frame of the writer's size.

        ``time_s`` (PyAV codecs only): the frame's presentation time (s), for
        variable frame rate; default ``frame number / fps``.
        """
        expected = (
            (self.image_size.height, self.image_size.width, 3)
            if self.is_color
            else (self.image_size.height, self.image_size.width)
        )
        if frame.shape != expected or frame.dtype != np.uint8:
            raise ValueError(
                f"frame must be uint8 of shape {expected}, got {frame.dtype} {frame.shape}"
            )
        if self._av is None:
            if time_s is not None:
                raise ValueError("per-frame times need a PyAV codec (h264, hevc, vp9, vp8)")
            self._writer.write(frame)
        else:
            import av

            container, stream, tb = self._av
            t = self.frames_written / self.fps if time_s is None else float(time_s)
            pts = round(t / tb)
            if pts <= self._last_pts:
                raise ValueError(
                    f"frame times must increase by at least one tick ({float(tb):g} s), got {t}"
                )
            self._last_pts = pts
            image = av.VideoFrame.from_ndarray(frame, format="bgr24" if self.is_color else "gray")
            image.pts = pts
            image.time_base = tb
            for packet in stream.encode(image):
                container.mux(packet)
        self.frames_written += 1

    def close(self) -> None:
        if self._av is not None:
            container, stream, _ = self._av
            self._av = None
            try:
                for packet in stream.encode():
                    container.mux(packet)
            finally:
                container.close()
        elif self._writer is not None:
            self._writer.release()

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: Encoder options of the browser proxy: H.264 (every browser plays it), a key
#: frame every 10 frames so that stepping and seeking land at once. ``ultrafast``:
#: the proxies were most of a worker's time per trial; on a 10-s 1280x1024 100-fps
#: MPEG-4 video it takes 6.1 s of CPU instead of 9.9 s with ``veryfast`` (2.5 MB
#: instead of 3.4 MB; bench/bench_throughput.py, docs/performance.md).
PROXY_OPTIONS = {"crf": "23", "preset": "ultrafast", "g": "10", "bf": "0"}

#: The widest browser proxy (px). The review view shows the two videos side by
#: side, each at most about half a 1920-px screen; a wider video is reduced by a
#: whole factor (1280x1024 to 640x512, 1920x1080 to 960x540), which cut the two
#: proxies of a 10-s 1280x1024 100-fps trial from 12.7 s of CPU to 7.1 s
#: (bench/bench_throughput.py, load 6-9; decoding the video is now ~1/3 of it).
PROXY_MAX_WIDTH_PX = 960


def proxy_size(image_size: ImageSize) -> ImageSize:
    """The size of a video's browser proxy: reduced by the smallest whole factor that
    makes it at most :data:`PROXY_MAX_WIDTH_PX` wide, then cut to even sizes (H.264 4:2:0)."""
    factor = -(-image_size.width // PROXY_MAX_WIDTH_PX)  # ceil
    width, height = image_size.width // factor, image_size.height // factor
    return ImageSize(width - width % 2, height - height % 2)


class ProxyWriter:
    """A browser-playable copy of a video written frame by frame: H.264 in MP4 with the
    index first (faststart), gray (the luma plane, what the analysis measured).

    Frame ``i`` written is frame ``i`` of the proxy, at ``times_s[i]`` when the
    video's frame times are given (a take of variable frame rate or with lost
    frames: the proxy lasts as long as the take and each frame is shown at its
    time), else at ``i / fps`` (constant frame rate); frames past the end of
    ``times_s`` follow its last at ``1 / fps``. The review view maps a player's
    time to the analysis's frame number through the same times. A video wider than
    :data:`PROXY_MAX_WIDTH_PX` is reduced by a whole factor (pixel areas averaged,
    :func:`proxy_size`); the review view draws its overlay in the video's own pixels
    over whatever size the player shows. An odd width or height loses its last column
    or row (H.264 4:2:0 needs even sizes), which keeps every pixel coordinate.

    Use it as a context manager (:meth:`close` on success, :meth:`abort` on an
    exception), or call those yourself. ``core.pipeline.analyze_recording`` feeds it
    the frames it decodes (``frame_sinks``), so a video is decoded once for both.

    Raises
    ------
    InputError
        The proxy cannot be written (:meth:`write`, :meth:`close`, or opening the
        file); the file is removed then.
    """

    def __init__(
        self,
        target: str | Path,
        image_size: ImageSize,
        fps: float,
        *,
        name: str,
        times_s: NDArray[np.float64] | None = None,
    ) -> None:
        import fractions

        import av

        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        t = None if times_s is None else np.asarray(times_s, dtype=np.float64).reshape(-1)
        if (
            t is not None
            and t.size
            and (not np.all(np.isfinite(t)) or np.any(np.diff(t) < 1.0 / 90000))
        ):
            raise ValueError("times_s must be finite and increase by at least 1/90000 s")
        self._times_s = None if t is None or not t.size else t - t[0]
        self.path = Path(target)
        self.name = name
        self.fps = float(fps)
        self.image_size = image_size
        size = proxy_size(image_size)
        self._width, self._height = size.width, size.height
        self._factor = -(-image_size.width // PROXY_MAX_WIDTH_PX)
        self._tb = fractions.Fraction(1, 90000)
        self.frames = 0
        self._av = av
        self._container: Any = None
        try:
            self._container = av.open(
                str(self.path), "w", format="mp4", options={"movflags": "+faststart"}
            )
            stream: Any = self._container.add_stream(
                "libx264", rate=fractions.Fraction(self.fps).limit_denominator(1001)
            )
            stream.width, stream.height = self._width, self._height
            stream.pix_fmt = "yuv420p"
            stream.time_base = self._tb
            stream.codec_context.time_base = self._tb
            stream.options = dict(PROXY_OPTIONS)
        except (av.FFmpegError, OSError) as exc:
            self._failed(exc)
        self._stream = stream

    def _time_s(self, i: int) -> float:
        """Presentation time (s) of frame ``i`` of the proxy."""
        t = self._times_s
        if t is None:
            return i / self.fps
        if i < len(t):
            return float(t[i])
        return float(t[-1]) + (i - len(t) + 1) / self.fps

    def _failed(self, exc: BaseException) -> NoReturn:
        self.abort()
        raise InputError(f"cannot write a browser copy of {self.name}: {exc}") from exc

    def write(self, gray: NDArray[np.uint8]) -> None:
        """Append one gray ``(H, W)`` frame of the video (``image_size``)."""
        if self._container is None:
            raise RuntimeError(f"the browser copy of {self.name} is closed")
        if gray.shape != (self.image_size.height, self.image_size.width):
            raise ValueError(
                f"frame {self.frames} of {self.name} is {gray.shape[1]}x{gray.shape[0]},"
                f" not {self.image_size.width}x{self.image_size.height}"
            )
        width, height, factor = self._width, self._height, self._factor
        shown = gray[:height, :width]
        if factor > 1:  # pixel areas averaged; cv2 returns the input's dtype
            shown = np.asarray(
                cv2.resize(
                    gray[: height * factor, : width * factor],
                    (width, height),
                    interpolation=cv2.INTER_AREA,
                ),
                dtype=np.uint8,
            )
        image = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(shown), format="gray")
        image.pts = round(self._time_s(self.frames) / self._tb)
        image.time_base = self._tb
        try:
            for packet in self._stream.encode(image):
                self._container.mux(packet)
        except (self._av.FFmpegError, OSError) as exc:
            self._failed(exc)
        self.frames += 1

    def close(self) -> int:
        """Flush the encoder and close the file; the number of frames written."""
        if self._container is None:
            raise RuntimeError(f"the browser copy of {self.name} is closed")
        try:
            for packet in self._stream.encode():
                self._container.mux(packet)
            self._container.close()
        except (self._av.FFmpegError, OSError) as exc:
            self._failed(exc)
        self._container = None
        return self.frames

    def abort(self) -> None:
        """Close without finishing and remove the file (idempotent)."""
        container, self._container = self._container, None
        if container is not None:
            with contextlib.suppress(self._av.FFmpegError, OSError):
                container.close()
        self.path.unlink(missing_ok=True)

    def __enter__(self) -> ProxyWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is not None:
            self.abort()
        elif self._container is not None:
            self.close()


def write_proxy(
    source: str | Path,
    target: str | Path,
    *,
    fps_if_none: float | None = None,
    progress: Callable[[int], None] | None = None,
) -> int:
    """Write a browser-playable copy of a video (:class:`ProxyWriter`) from every frame
    decoded from ``source``, which is only read.

    Parameters
    ----------
    source, target : str or Path
        The original video and the ``.mp4`` file to write.
    fps_if_none : float, optional
        The rate of a video that states neither a frame rate nor frame
        timestamps (a raw stream; :func:`probe_video`): its timestamps file's.
    progress : callable, optional
        ``progress(frames_done)`` after each frame.

    Returns
    -------
    int
        Frames written.

    Raises
    ------
    InputError
        The video cannot be read or the proxy cannot be written.
    """
    info = probe_video(source, fps_if_none=fps_if_none)
    with ProxyWriter(target, info.image_size, info.fps, name=info.path.name) as writer:
        for gray in iter_frames(info.path, gray=True, expected_count=info.frame_count):
            writer.write(gray)
            if progress is not None:
                progress(writer.frames)
    return writer.frames


def video_suffix(codec: str) -> str:
    """The file suffix that goes with a :class:`VideoWriter` codec (``".mkv"``, ``".mp4"``)."""
    if codec in _AV_CODECS:
        return _AV_CODECS[codec][1]
    if codec not in _CODECS:
        raise ValueError(f"codec must be one of {sorted(CODECS)}, got {codec!r}")
    return _CODECS[codec][1]


def check_stereo_videos(
    left: VideoInfo, right: VideoInfo, *, rig: StereoRig | None = None
) -> list[str]:
    """Check that two videos form a usable stereo pair (and fit the rig).

    The two cameras may run at different frame rates (the time model of
    :mod:`core.clock` measures at the left camera's instants) and, with a
    rig, at different resolutions when the rig was calibrated that way.

    Returns
    -------
    list of str
        Warnings that do not stop a measurement (for example slightly
        different lengths).

    Raises
    ------
    InputError
        A size other than the rig's calibration; without a rig, different
        image sizes; lengths too different to be one recording.
    """
    warnings: list[str] = []
    if rig is not None:
        for info, cam in ((left, rig.left), (right, rig.right)):
            if info.image_size != cam.image_size:
                raise InputError(
                    f"the {cam.name} video is {info.image_size.width}x{info.image_size.height} but"
                    f" the rig was calibrated at {cam.image_size.width}x{cam.image_size.height};"
                    " use the calibration made for this camera setting."
                )
    elif left.image_size != right.image_size:
        raise InputError(
            f"the left video is {left.image_size.width}x{left.image_size.height} but the right is"
            f" {right.image_size.width}x{right.image_size.height}; both cameras must record at the"
            " same resolution."
        )
    same_rate = abs(left.fps - right.fps) <= 1e-3 * max(left.fps, right.fps)
    if same_rate:
        diff = abs(left.frame_count - right.frame_count)
        longer = max(left.frame_count, right.frame_count)
        too_different = diff > max(0.2 * longer, 50)
    else:
        diff_s = abs(left.duration_s - right.duration_s)
        too_different = diff_s > max(0.2 * max(left.duration_s, right.duration_s), 1.0)
    if too_different:
        raise InputError(
            f"the left video has {left.frame_count} frames ({left.duration_s:.1f} s) and the right"
            f" {right.frame_count} ({right.duration_s:.1f} s); they cannot be recordings of the"
            " same test — check that the pair belongs together."
        )
    if left.frame_count != right.frame_count and same_rate:
        warnings.append(
            f"the videos have different lengths ({left.frame_count} and {right.frame_count} frames);"
            " only the common part is measured."
        )
    return warnings


def list_images(folder: str | Path) -> list[Path]:
    """The image files of a folder, sorted by file name.

    Raises
    ------
    InputError
        The folder does not exist or holds no image.
    """
    p = Path(folder)
    if not p.is_dir():
        raise InputError(f"the folder {p} does not exist; check the path.")
    files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in _IMAGE_SUFFIXES)
    if not files:
        raise InputError(
            f"the folder {p.name} holds no image (PNG, JPEG, BMP or TIFF); check the path."
        )
    return files


def read_image(path: str | Path, *, gray: bool = True) -> NDArray[np.uint8]:
    """Read one image file; :class:`InputError` if it cannot be decoded."""
    p = Path(path)
    flag = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
    img = cv2.imread(str(p), flag)
    if img is None:
        raise InputError(
            f"the image {p.name} could not be read; check that it is a valid image file."
        )
    return np.asarray(img, dtype=np.uint8)

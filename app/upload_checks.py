"""What an uploaded file holds: videos checked by decoding them, timestamps and rig files read.

The second step of an upload (:mod:`app.uploads` receives the files first):

- :func:`validate_video` / :func:`validate_stereo_pair` decide whether a file
  really is a usable video by decoding it (``core.video.probe_video`` plus
  its first and last frames), never by its name or declared content type;
- :func:`validate_times` reads a timestamps file (``frame,time_s``) against
  its video's decoded frames;
- :func:`validate_rig_file` parses a rig file with ``core.camera.rig_from_dict``;
- :func:`sent_before` warns of an earlier trial of the session that holds the
  same two videos, as the same cameras or the other way round;
- :data:`SAME_FILE_MESSAGE` refuses one recording given as both cameras' (the
  upload compares the received files' SHA-256; ``bradyscope analyze`` uses
  :func:`same_file`).

Each refusal is an :class:`app.uploads.InvalidUpload` (422) or
:class:`app.uploads.UnsupportedUpload` (415) with a sentence for the person
who uploaded the file.
"""

from __future__ import annotations

import filecmp
import json
from collections.abc import Iterable
from pathlib import Path

from app.uploads import InvalidUpload, UnsupportedUpload
from core.camera import StereoRig, rig_from_dict
from core.errors import BradyscopeError, InputError
from core.timing import FrameTimes, read_times_csv
from core.video import VideoInfo, check_stereo_videos, decodes_frame, probe_video


def validate_video(
    path: Path, *, label: str, filename: str = "", fps_if_none: float | None = None
) -> VideoInfo:
    """Decide whether ``path`` is a usable video by decoding it.

    Parameters
    ----------
    path : Path
        The received file.
    label : str
        How the file is named in messages ("The left video").
    filename : str
        The client's file name, shown instead of the temporary file's name.
    fps_if_none : float, optional
        The rate of the video's timestamps file, for a video that states
        neither a frame rate nor frame timestamps (a raw H.264/HEVC/MJPEG
        stream; ``core.video.probe_video``). Without it such a video is refused.

    Returns
    -------
    core.video.VideoInfo
        fps, frame count, image size and codec of the video.

    Raises
    ------
    UnsupportedUpload
        If the file is empty, not a video, has no frames, or its first or last
        frames cannot be decoded (a truncated or corrupt file). A container may
        announce up to two frames more than it holds (``core.video``'s slack);
        such a file is accepted.
    """

    def why(exc: BaseException) -> str:
        return _sentence(exc).replace(path.name, filename or "the file")

    if path.stat().st_size == 0:
        raise UnsupportedUpload(f"{label} is empty (0 bytes); upload the recorded video file.")
    try:
        # Opens the file and decodes its first frame.
        info = probe_video(path, fps_if_none=fps_if_none)
    except BradyscopeError as exc:
        raise UnsupportedUpload(f"{label} is not a usable video: {why(exc)}") from exc
    # The last frame must decode too: a truncated file fails here even when its
    # header looks fine. Up to two frames of slack, as in core.video.
    last = info.frame_count - 1
    if not any(decodes_frame(path, index) for index in range(last, max(-1, last - 3), -1)):
        raise UnsupportedUpload(
            f"{label} is damaged or incomplete: it announces {info.frame_count} frames but its"
            " last frames cannot be decoded; upload the complete recording again."
        )
    return info


MAX_TIMES_BYTES = 16 * 1024 * 1024
"""A timestamps file's size limit: ~30 bytes a frame, so an hour at 120 fps fits."""


def validate_times(path: Path, *, label: str, n_frames: int | None) -> FrameTimes:
    """Read an uploaded timestamps file (``frame,time_s``) for a video of ``n_frames`` frames.

    Parameters
    ----------
    path : Path
        The received file.
    label : str
        How the file is named in messages ("the left timestamps file").
    n_frames : int or None
        The number of frames of its video (decoded count); the file must give
        the time of each (``core.timing.read_times_csv``'s two frames of slack).
        None reads the file alone (its rate, before its video is probed).

    Returns
    -------
    core.timing.FrameTimes
        The capture times (``source="file"``) and the measured frame rate.

    Raises
    ------
    InvalidUpload
        Empty or too large, not a ``frame,time_s`` CSV, times that do not
        increase, or a frame count that does not fit the video.
    """
    size = path.stat().st_size
    if size == 0:
        raise InvalidUpload(f"{_capital(label)} is empty; upload the one recorded with the video.")
    if size > MAX_TIMES_BYTES:
        raise InvalidUpload(
            f"{_capital(label)} is larger than {MAX_TIMES_BYTES // 1024 // 1024} MB; a"
            " timestamps file holds one short line per frame (frame,time_s)."
        )
    try:
        times = read_times_csv(path, n_frames=n_frames)
    except InputError as exc:
        raise InvalidUpload(_capital(_sentence(exc).replace(path.name, label))) from exc
    _refuse_milliseconds(times, label)
    return times


MS_LIKE_INTERVAL_S = (1.0, 1000.0)
"""A median frame interval in this range (s) is a camera's 1000 to 1 frames per second
written in milliseconds: no recording is taken at less than one frame a second."""


def _refuse_milliseconds(times: FrameTimes, label: str) -> None:
    """Refuse a timestamps file whose times look like milliseconds (a frame interval about
    1000 times a camera's): else the pair would be refused for lasting hours."""
    interval = times.interval_s  # the median interval
    low, high = MS_LIKE_INTERVAL_S
    if low <= interval <= high:
        raise InvalidUpload(
            f"{_capital(label)} seems to be written in milliseconds: its frames are"
            f" {interval:.4g} apart, {1000 / interval:.3g} frames per second in milliseconds but"
            f" one frame every {interval:.4g} s in seconds. The column time_s takes seconds:"
            " divide its times by 1000 and upload it again."
        )


def _capital(text: str) -> str:
    return text[:1].upper() + text[1:]


def validate_stereo_pair(
    left: VideoInfo, right: VideoInfo, *, rig: StereoRig | None = None
) -> list[str]:
    """Check that two decoded videos form one stereo recording (same fps and size, rig fit).

    Returns the warnings of ``core.video.check_stereo_videos``; raises
    :class:`InvalidUpload` when the pair cannot be measured.
    """
    try:
        return list(check_stereo_videos(left, right, rig=rig))
    except BradyscopeError as exc:
        raise InvalidUpload(_sentence(exc)) from exc


SAME_FILE_MESSAGE = (
    "The left and right videos are the same file; choose the recording of each camera."
)
"""Said when one recording is given as both cameras' (an upload, ``bradyscope analyze``)."""


def sent_before(
    earlier: Iterable[tuple[int, str, str]], *, left_sha256: str, right_sha256: str
) -> list[str]:
    """Warnings for a trial upload whose two videos an earlier trial of the session holds.

    ``earlier``: ``(trial_id, side, sha256)`` of the session's videos (those with either
    digest are enough). The same two videos as the same cameras were most likely sent
    twice (a retry after a lost answer); the other way round, they were sent again to be
    measured swapped, which "Measure again" does without a second trial.
    """
    held: dict[int, dict[str, str]] = {}
    for trial_id, side, sha256 in earlier:
        held.setdefault(trial_id, {})[side] = sha256
    warnings = []
    for t in sorted(held):
        sides = held[t]
        if sides == {"left": left_sha256, "right": right_sha256}:
            warnings.append(
                f"trial {t} of this session holds the same two videos: if they were sent"
                " twice, hide one of the two trials."
            )
        elif sides == {"left": right_sha256, "right": left_sha256}:
            warnings.append(
                f"trial {t} of this session holds these two videos with the cameras the other"
                f" way round: to measure them swapped, “Measure again” on trial {t} does it"
                " without a second trial; if that is why they were sent, hide one of the two."
            )
    return warnings


def same_file(left: Path, right: Path) -> bool:
    """Whether two paths hold one file, or two copies of it (the same bytes)."""
    try:
        if left.samefile(right):
            return True
        if left.stat().st_size != right.stat().st_size:
            return False
        return filecmp.cmp(left, right, shallow=False)
    except OSError:  # a missing file is said by whoever opens it
        return False


def validate_rig_file(path: Path) -> StereoRig:
    """Parse an uploaded rig file; return the ``StereoRig`` or raise :class:`InvalidUpload`."""
    if path.stat().st_size == 0:
        raise InvalidUpload("The rig file is empty; upload the rig.json written by calibrate.")
    try:
        doc = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidUpload(
            "The rig file is not valid JSON; upload the rig.json written by bradyscope calibrate."
        ) from exc
    except RecursionError as exc:
        raise InvalidUpload(
            "The rig file is nested too deeply to be a rig file; upload the rig.json written by"
            " bradyscope calibrate."
        ) from exc
    try:
        return rig_from_dict(doc, source="the uploaded rig file")
    except BradyscopeError as exc:
        raise InvalidUpload(_sentence(exc)) from exc


def _sentence(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text if text.endswith((".", "!", "?")) else text + "."

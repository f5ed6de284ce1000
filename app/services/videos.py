"""The two videos of an upload (a trial, or a calibration's board recordings).

Checked by decoding (:mod:`app.uploads`), then published into storage and
recorded as :class:`app.models.Video` rows in the use case's transaction. A
trial's video may come with a timestamps file (``left_times`` /
``right_times``: ``frame,time_s``, each frame's capture time on that camera's
clock, as the capture page writes them): it is checked against its video's
frames, stored beside it and referenced by the video's row. Without one, the
quick check (:meth:`CheckedVideo.take`) reads the frame times from the
container's packets, demuxed and not decoded, as the analysis finds them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np
from sqlalchemy.orm import Session

from app.models import Video
from app.storage import Storage
from app.upload_checks import (
    SAME_FILE_MESSAGE,
    validate_stereo_pair,
    validate_times,
    validate_video,
)
from app.uploads import InvalidUpload, ParsedUpload
from core.camera import StereoRig
from core.timing import FrameTimes
from core.video import VideoInfo

SIDES = ("left", "right")
TIMES_FIELDS = {"left": "left_times", "right": "right_times"}


@dataclass(frozen=True)
class CheckedVideo:
    """One decoded video of an upload and, if one came with it, its capture times.

    Attributes
    ----------
    info : core.video.VideoInfo
        What the file says about itself; with a timestamps file, ``fps`` is
        the rate measured from the capture times.
    times : core.timing.FrameTimes or None
        From the uploaded timestamps file.
    container_times : core.timing.FrameTimes or None
        Without a timestamps file: from the container (:func:`container_frame_times`),
        read while the upload is staged (its file moves when published). None: read
        when asked, from ``info.path``.
    """

    info: VideoInfo
    times: FrameTimes | None = None
    container_times: FrameTimes | None = None

    @cached_property
    def frame_times(self) -> FrameTimes:
        """The capture times of the timestamps file if there is one, else those of the
        container's packets (:func:`container_frame_times`: variable frame rate and lost
        frames, as the analysis finds them), else ``i / fps``."""
        if self.times is not None:
            return self.times
        if self.container_times is not None:
            return self.container_times
        return container_frame_times(self.info)

    @property
    def duration_s(self) -> float:
        """From the first frame to the end of the last one (s)."""
        t = self.frame_times
        return float(t.t_s[-1] - t.t_s[0]) + t.interval_s if len(t) else 0.0

    def take(self) -> dict[str, object]:
        """The quick check of this recording: frames, length, rate reached, frames lost."""
        t = self.frame_times
        return {
            "frame_count": len(t),
            "duration_s": round(self.duration_s, 3),
            "fps": round(t.fps, 2),
            "dropped_frames": len(t.dropped_after) if t.variable else None,
            "time_source": t.source,
        }


#: FFmpeg's AVFMT_NOTIMESTAMPS: a raw elementary stream, whose demuxer invents timestamps.
_AVFMT_NOTIMESTAMPS = 0x0080


def _packet_times_s(path: Path) -> list[float]:
    """The presentation time (s) of every frame of the video's first video stream, from
    its packets in display order: demuxed, not decoded (0.1-0.2 s for a 990-MB MP4 of
    900 frames, 0.15 s for 36 000 frames: 10 min at 60 fps). Empty when the packets carry
    no timestamps or the file cannot be read."""
    import av  # here, as in core.video: PyAV is not needed to start the web app

    try:
        with av.open(str(path)) as container:
            if container.format.flags & _AVFMT_NOTIMESTAMPS or not container.streams.video:
                return []
            stream = container.streams.video[0]
            pts = [
                p.pts
                for p in container.demux(stream)
                if p.size and p.pts is not None and not p.is_discard  # discard: an edit list's
            ]
            base = float(stream.time_base) if stream.time_base else 0.0
    except (av.FFmpegError, OSError, ValueError):
        return []  # damaged or gone: the frame rate's times (the decoding checked the file)
    return sorted(t * base for t in pts) if base > 0 else []


def container_frame_times(info: VideoInfo) -> FrameTimes:
    """A video's frame times from its container, by the analysis's rule.

    :func:`core.pipeline.container_frame_times` on the packets' timestamps (the
    analysis takes them from the decoder: the same times, to the time base's
    resolution).
    """
    from core.pipeline import container_frame_times as from_container  # the analysis's rule

    stamps = _packet_times_s(info.path) if info.has_timestamps else []
    return from_container(info, stamps, info.frame_count)


@dataclass(frozen=True)
class VideoPair:
    """The checked left and right videos of an upload and the warnings about them."""

    left: CheckedVideo
    right: CheckedVideo
    warnings: list[str]

    def side(self, side: str) -> CheckedVideo:
        return self.left if side == "left" else self.right


def _checked(upload: ParsedUpload, side: str) -> CheckedVideo:
    """Decode one side's video, with the rate and times of its timestamps file if it has one.

    The timestamps file is read first: a raw stream (no container) states no
    rate of its own, and the file's stands in (as in ``bradyscope analyze
    --left-times``); then the file is checked against the decoded frame count.
    """
    file = upload.require_file(f"{side}_video")
    staged = upload.files.get(TIMES_FIELDS[side])
    label = f"the {side} timestamps file"
    times = None if staged is None else validate_times(staged.path, label=label, n_frames=None)
    info = validate_video(
        file.path,
        label=f"The {side} video",
        filename=file.filename,
        fps_if_none=None if times is None else times.fps,
    )
    if staged is None:
        return CheckedVideo(info, container_times=container_frame_times(info))
    times = validate_times(staged.path, label=label, n_frames=info.frame_count)
    return CheckedVideo(replace(info, fps=times.fps), times)


def check_video_pair(upload: ParsedUpload, *, rig: StereoRig | None = None) -> VideoPair:
    """Decode ``left_video`` and ``right_video`` (and read their timestamps files, if any).

    ``rig`` (when known) is the rig that will measure them: their image size must fit it.
    A video that states neither a frame rate nor frame timestamps (a raw stream) is
    accepted with its timestamps file, which gives both, and refused without one.

    Raises
    ------
    app.uploads.UnsupportedUpload, app.uploads.InvalidUpload
        A file is not a usable video, a timestamps file does not fit its
        video, or the two do not form one recording (of the rig).
    """
    left_file = upload.require_file("left_video")
    right_file = upload.require_file("right_video")
    if left_file.incoming.sha256 == right_file.incoming.sha256:
        raise InvalidUpload(SAME_FILE_MESSAGE)
    pair = (_checked(upload, "left"), _checked(upload, "right"))
    warnings = validate_stereo_pair(pair[0].info, pair[1].info, rig=rig)
    return VideoPair(pair[0], pair[1], warnings)


def _video_row(upload: ParsedUpload, side: str, checked: CheckedVideo) -> Video:
    name = f"{side}_video"
    stored = upload.publish(name)
    staged = upload.files[name]
    info = checked.info
    video = Video(
        side=side,
        path=stored.path,
        original_filename=(staged.filename or None) and staged.filename[:255],
        size_bytes=stored.size_bytes,
        sha256=stored.sha256,
        fps=float(info.fps),
        frame_count=int(info.frame_count),
        width=int(info.image_size.width),
        height=int(info.image_size.height),
        codec=(info.fourcc or None) and str(info.fourcc)[:16],
        duration_s=float(np.round(checked.duration_s, 6)),
    )
    if checked.times is not None:
        times = upload.publish(TIMES_FIELDS[side])
        video.times_path = times.path
        video.times_sha256 = times.sha256
    return video


def times_file(storage: Storage, video: Video) -> Path | None:
    """The stored timestamps file of a video (absolute), or None when it came without one."""
    return storage.absolute(video.times_path) if video.times_path else None


def add_videos(
    db: Session,
    upload: ParsedUpload,
    pair: VideoPair,
    *,
    trial_id: int | None = None,
    calibration_id: int | None = None,
) -> None:
    """Publish the two checked videos (and timestamps files) and add their rows."""
    for side in SIDES:
        video = _video_row(upload, side, pair.side(side))
        video.trial_id = trial_id
        video.calibration_id = calibration_id
        db.add(video)

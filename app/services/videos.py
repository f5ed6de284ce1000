"""The two videos of an upload (a trial, or a calibration's board recordings).

Checked by decoding (:mod:`app.uploads`), then published into storage and
recorded as :class:`app.models.Video` rows in the use case's transaction.
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from app.models import Video
from app.uploads import InvalidUpload, ParsedUpload, validate_stereo_pair, validate_video
from core.camera import StereoRig
from core.video import VideoInfo


def check_video_pair(
    upload: ParsedUpload, *, rig: StereoRig | None = None
) -> tuple[VideoInfo, VideoInfo, list[str]]:
    """Decode ``left_video`` and ``right_video``; ``(left, right, warnings)`` if they fit together.

    ``rig`` (when known) is the rig that will measure them: their image size must fit it.
    """
    left_file = upload.require_file("left_video")
    right_file = upload.require_file("right_video")
    if left_file.incoming.sha256 == right_file.incoming.sha256:
        raise InvalidUpload(
            "The left and right videos are the same file; choose the recording of each camera."
        )
    left = validate_video(left_file.path, label="The left video", filename=left_file.filename)
    right = validate_video(right_file.path, label="The right video", filename=right_file.filename)
    warnings = validate_stereo_pair(left, right, rig=rig)
    return left, right, warnings


def _video_row(upload: ParsedUpload, name: str, info: VideoInfo, side: str) -> Video:
    stored = upload.publish(name)
    staged = upload.files[name]
    return Video(
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
    )


def add_videos(
    db: Session,
    upload: ParsedUpload,
    left: VideoInfo,
    right: VideoInfo,
    *,
    trial_id: int | None = None,
    calibration_id: int | None = None,
) -> None:
    """Publish the two checked videos and add their rows (of a trial or a calibration)."""
    for name, info, side in (("left_video", left, "left"), ("right_video", right, "right")):
        video = _video_row(upload, name, info, side)
        video.trial_id = trial_id
        video.calibration_id = calibration_id
        db.add(video)

"""What the worker's analysis of a trial reads (:func:`analysis_inputs`) and writes back
besides its result (:func:`store_proxies`); the trial's upload and pages are
:mod:`app.services.trials`."""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.errors import InvalidRequestError, NotFoundError
from app.models import Trial, Video
from app.services.calibrations import calibration_for
from app.services.videos import times_file
from app.storage import Storage
from core.camera import StereoRig, rig_from_dict
from core.tasks import DEFAULT_TASK


@dataclass(frozen=True)
class CalibrationUsed:
    """The calibration a trial was measured with (recorded in its ``result.json``)."""

    id: int
    rig_id: int
    rig_name: str
    version: int
    valid_from: datetime
    rms_px: float | None

    def document(self) -> dict[str, object]:
        """The ``calibration`` object of ``result.json``."""
        return {
            "id": self.id,
            "rig_id": self.rig_id,
            "rig_name": self.rig_name,
            "version": self.version,
            "valid_from": self.valid_from.isoformat(),
            "rms_px": self.rms_px,
        }


@dataclass(frozen=True)
class TrialInputs:
    """Everything the analysis of one trial needs: what crosses from the database to ``core``.

    Attributes
    ----------
    trial_id : int
    left, right : Path
        The stored videos (absolute paths; they may be missing on this worker).
    offset_frames : float or None
        Known camera offset (right frame j ~ left frame j + K); None: estimate it.
    calibration : CalibrationUsed
    rig : core.camera.StereoRig
        The rig of that calibration.
    proxies_needed : dict of str to Path
        The stored videos (by side) that have no browser proxy yet.
    video_fps : dict of str to float
        Each stored video's frame rate as checked at upload (by side): its
        timestamps file's rate when it came with one, which stands in for the
        rate a raw stream (no container) does not state.
    left_times, right_times : Path or None
        The stored timestamps files of the videos, if they came with them.
    task : str
        The task recorded (``core.tasks.Task`` value).
    side : str
        The trial's side (its ``hand``: the hand, or the foot for toe tapping).
    """

    trial_id: int
    left: Path
    right: Path
    offset_frames: float | None
    calibration: CalibrationUsed
    rig: StereoRig
    proxies_needed: dict[str, Path] = field(default_factory=dict)
    video_fps: dict[str, float] = field(default_factory=dict)
    left_times: Path | None = None
    right_times: Path | None = None
    task: str = DEFAULT_TASK.value
    side: str = "right"
    names: dict[str, str] = field(default_factory=dict)
    """Stored file name -> what the clinician knows it as ("the left video (take3_l.mp4)")."""

    def described(self, message: str) -> str:
        """``message`` (of core, naming the stored files) in the clinician's words."""
        for stored, known in self.names.items():
            message = message.replace(stored, known)
        return message

    @property
    def files(self) -> tuple[Path, ...]:
        """Every stored file the analysis reads."""
        times = (p for p in (self.left_times, self.right_times) if p is not None)
        return (self.left, self.right, *times)


def analysis_inputs(
    db: Session, storage: Storage, trial_id: int | None, *, offset_frames: float | None = None
) -> TrialInputs:
    """What the worker's analysis of ``trial_id`` needs.

    ``offset_frames`` is the job's (a re-analysis with a given offset); without
    it, the trial's own (given at upload), else None (estimate it).

    Raises
    ------
    NotFoundError
        The trial was deleted.
    InvalidRequestError
        A video is missing from the trial.
    CalibrationMissingError
        No calibration can measure the trial.
    """
    trial = db.get(Trial, trial_id) if trial_id is not None else None
    if trial is None or trial.deleted_at is not None:
        raise NotFoundError(f"trial {trial_id} was deleted; nothing to analyse.")
    videos = {v.side: v for v in trial.videos}
    missing = [side for side in ("left", "right") if side not in videos]
    if missing:
        raise InvalidRequestError(
            f"trial {trial.id} has no {' and no '.join(missing)} video; upload the trial again."
        )
    cal = calibration_for(db, trial.session, trial.rig_id)
    used = CalibrationUsed(
        id=cal.id,
        rig_id=cal.rig_id,
        rig_name=cal.rig.name,
        version=cal.version,
        valid_from=cal.valid_from,
        rms_px=cal.rms_px,
    )
    rig = rig_from_dict(cal.rig_json, source=f"calibration v{cal.version} of rig {cal.rig.name}")
    return TrialInputs(
        trial_id=trial.id,
        left=storage.absolute(videos["left"].path),
        right=storage.absolute(videos["right"].path),
        offset_frames=offset_frames if offset_frames is not None else trial.offset_frames,
        calibration=used,
        rig=rig,
        proxies_needed={
            side: storage.absolute(v.path)
            for side, v in videos.items()
            if not v.proxy_path or not storage.exists(v.proxy_path)
        },
        video_fps={side: float(v.fps) for side, v in videos.items()},
        left_times=times_file(storage, videos["left"]),
        right_times=times_file(storage, videos["right"]),
        task=trial.task,
        side=trial.hand,
        names=_known_names(videos),
    )


def _known_names(videos: dict[str, Video]) -> dict[str, str]:
    """The stored files' names (server-made) as the clinician knows each file."""
    names = {}
    for side, v in videos.items():
        original = f" ({v.original_filename})" if v.original_filename else ""
        names[Path(v.path).name] = f"the {side} video{original}"
        if v.times_path:
            names[Path(v.times_path).name] = f"the {side} video's timestamps file"
    return names


def store_proxies(db: Session, trial_id: int, proxies: dict[str, str]) -> None:
    """Record the browser proxies made for the trial's videos (``side -> stored path``)."""
    for video in db.scalars(select(Video).where(Video.trial_id == trial_id)):
        if video.side in proxies:
            video.proxy_path = proxies[video.side]

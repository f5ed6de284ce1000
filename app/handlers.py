"""What each kind of job does: measure a trial, calibrate a rig, make a trial's PDF report.

The real handlers of the worker (:mod:`app.worker` runs them, each with a
:class:`app.job_context.JobContext`):

- :func:`analyze_trial`: ``core.pipeline.analyze_recording`` on the trial's
  two videos → markers.csv, the review overlay, browser proxies and the next
  ``Result`` revision;
- :func:`calibrate`: ``core.calibration.calibrate_stereo_from_paths`` on a
  rig's two board recordings → a ready ``Calibration``;
- :func:`make_report_pdf`: the PDF report of a trial's current result, and of
  the trials shown beside it, into the report cache, so that the request finds
  it made (``app.reports.pdf_cache``); and the trend plots of the patient's page
  (``app.reports.trend_cache``).

What crosses to ``core`` and back is typed:
:class:`app.services.trial_inputs.TrialInputs` and ``core.pipeline.Analysis``,
:class:`app.services.calibrations.CalibrationInputs` and
``core.calibration.CalibrationResult``; the services read and store the rows.
:data:`STAGES` weighs each job kind's stages for its progress fraction.
"""

from __future__ import annotations

import json
import logging
import os
import re
import uuid
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from sqlalchemy.orm import Session

from app import jobs
from app.job_context import Handler, JobContext, RetryableJobError, default_worker_name
from app.services import calibrations, patients, results, review, revisions, trial_inputs
from app.services.videos import container_frame_times
from core.calibration import calibrate_stereo_from_paths
from core.errors import BradyscopeError, InputError
from core.markers_csv import read_markers_csv
from core.overlay import overlay_document
from core.pipeline import Analysis, FrameSink, analyze_recording, write_markers_csv
from core.timing import FrameTimes, fit_to_frames, read_times_csv
from core.video import ProxyWriter, probe_video

log = logging.getLogger(__name__)


def _require_files(ctx: JobContext, paths: Iterable[Path], *, what: str) -> None:
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise RetryableJobError(
            f"the recorded files of {what} are missing from the data directory "
            f"{ctx.storage.data_dir} on worker {default_worker_name()}; every worker must use "
            "the same data directory (BRADYSCOPE_DATA_DIR)."
        )


def _upload_warnings(ctx: JobContext, document: dict[str, Any]) -> dict[str, Any]:
    """``document`` with the upload's warnings (kept in the job) added to its quality warnings."""
    upload_warnings = [str(w) for w in ctx.job.payload.get("warnings", ()) if w]
    if not upload_warnings:
        return document
    quality = dict(document.get("quality") or {})
    known = list(quality.get("warnings") or [])
    quality["warnings"] = known + [w for w in upload_warnings if w not in known]
    return {**document, "quality": quality}


def _stored_frame_times(inputs: trial_inputs.TrialInputs, side: str) -> FrameTimes:
    """When each frame of the stored ``side`` video was captured, by the analysis's rule
    (``core.pipeline``): its timestamps file, else its container's frame times (variable
    frame rate and lost frames), else ``i / fps``; for its decoded frame count.

    Raises
    ------
    InputError
        The video or its timestamps file cannot be read.
    """
    video = inputs.left if side == "left" else inputs.right
    times_csv = inputs.left_times if side == "left" else inputs.right_times
    info = probe_video(video, fps_if_none=inputs.video_fps.get(side))
    if times_csv is None:
        return container_frame_times(info)
    return fit_to_frames(read_times_csv(times_csv), info.frame_count)


class _ProxiesAlongside:
    """Browser proxies (``core.video.ProxyWriter``) of the videos that have none yet,
    written from the frames the analysis decodes (``analyze_recording(frame_sinks=...)``):
    each video is decoded once, not once more for its proxy.

    Each proxy holds its frames at the video's capture times (:func:`_stored_frame_times`,
    kept by side in :attr:`times` for the review overlay), at its own rate: a browser's
    WebM, whose container states 1000 fps, lost frames and irregular intervals included.
    A proxy that cannot be written (its video cannot be probed, the encoder fails, the
    disk is full) gives a warning, not a failure: the measurement stands without it and
    the review view says so. The files are written in the storage's temporary folder and
    published by :meth:`publish`; :meth:`discard` removes them (an analysis that failed).
    """

    def __init__(self, ctx: JobContext, inputs: trial_inputs.TrialInputs) -> None:
        self._ctx = ctx
        self.warnings: list[str] = []
        self._writers: dict[str, ProxyWriter] = {}
        self.times: dict[str, FrameTimes] = {}
        """Each stored video's frame times (by side), for those that could be read."""
        # An earlier attempt of this job, whose worker was killed, left its proxies
        # half-written: removed here (Storage.cleanup_tmp removes any other after an hour).
        prefix = f"proxy-job{ctx.job.id}-"
        mine = f"{prefix}a{ctx.job.attempts}-"
        for old in ctx.storage.tmp_dir.glob(f"{prefix}*.part"):
            if not old.name.startswith(mine):
                old.unlink(missing_ok=True)
        try:
            for side in ("left", "right"):
                try:
                    self.times[side] = times = _stored_frame_times(inputs, side)
                    source = inputs.proxies_needed.get(side)
                    if source is None:
                        continue
                    info = probe_video(source, fps_if_none=inputs.video_fps.get(side))
                    temp = ctx.storage.tmp_dir / f"{mine}{side}-{uuid.uuid4().hex[:8]}.mp4.part"
                    self._writers[side] = ProxyWriter(
                        temp, info.image_size, times.fps, name=info.path.name, times_s=times.t_s
                    )
                except InputError as exc:
                    if side in inputs.proxies_needed:
                        self._cannot(side, exc)
        except BaseException:
            self.discard()
            raise

    def _cannot(self, side: str, exc: InputError) -> None:
        log.warning("job %d: no proxy of the %s video: %s", self._ctx.job.id, side, exc)
        self.warnings.append(f"{review.PROXY_WARNING.format(side=side)}: {exc}")

    def sink(self, side: str) -> FrameSink | None:
        """What the analysis calls with each frame of the stored ``side`` video."""
        writer = self._writers.get(side)
        if writer is None:
            return None

        def write(frame: NDArray[np.uint8]) -> None:
            if side not in self._writers:
                return  # failed before: the rest of the video is not written
            try:
                writer.write(frame)
            except InputError as exc:  # the file is removed; the analysis goes on
                del self._writers[side]
                self._cannot(side, exc)

        return write

    def publish(self, written: list[str]) -> dict[str, str]:
        """Finish the proxies and move them into storage; the stored paths by side, each
        also appended to ``written`` as soon as it is there (to remove it again if the
        result is not stored)."""
        made: dict[str, str] = {}
        for side in sorted(self._writers):
            writer = self._writers.pop(side)
            try:
                try:
                    writer.close()
                except InputError as exc:  # the file is removed
                    self._cannot(side, exc)
                    continue
                with self._ctx.storage.writing("proxies", ".mp4") as (tmp, path):
                    os.replace(writer.path, tmp)
            except BaseException:
                writer.abort()
                raise
            written.append(path)
            made[side] = path
        return made

    def discard(self) -> None:
        """Remove the proxies not published (idempotent)."""
        for writer in self._writers.values():
            writer.abort()
        self._writers.clear()


def _measure(
    ctx: JobContext, inputs: trial_inputs.TrialInputs, *, swap: bool, proxies: _ProxiesAlongside
) -> Analysis:
    """``core.pipeline.analyze_recording`` on the trial, the ``proxies`` written from its
    frames; ``swap``: the stored right video (and its timestamps) measured as the rig's
    left camera, and the other way round."""
    left, right = (inputs.right, inputs.left) if swap else (inputs.left, inputs.right)
    sides = ("right", "left") if swap else ("left", "right")
    left_times, right_times = (
        (inputs.right_times, inputs.left_times) if swap else (inputs.left_times, inputs.right_times)
    )
    return analyze_recording(
        inputs.rig,
        left,
        right,
        offset_frames=inputs.offset_frames,
        progress=ctx.progress,
        left_times=left_times,
        right_times=right_times,
        task=inputs.task,
        side=inputs.side,
        frame_sinks=(proxies.sink(sides[0]), proxies.sink(sides[1])),
    )


def _review_overlay(
    analysis: Analysis,
    inputs: trial_inputs.TrialInputs,
    *,
    swap: bool,
    times: dict[str, FrameTimes],
) -> dict[str, Any]:
    """The review view's overlay, each rig camera's part naming the stored video it is drawn
    on and, as ``time_s``, when each of that video's frames is shown in its proxy (its
    capture time from its first frame, s): the player maps its time to a frame number
    through them, lost frames and irregular intervals included."""
    overlay = overlay_document(analysis.overlays(inputs.rig), fps=analysis.fps)
    for cam in overlay["cameras"]:
        cam["video"] = {"left": "right", "right": "left"}[cam["camera"]] if swap else cam["camera"]
        own = times.get(cam["video"])
        if own is not None:
            shown = fit_to_frames(own, int(cam["frame_count"]))
            cam["time_s"] = [round(float(t), 6) for t in shown.t_s]
    return overlay


def analyze_trial(ctx: JobContext) -> None:
    """Measure a trial's two videos with the pipeline and store the next result revision.

    The markers CSV, the review overlay and the plots are written under ``files/`` before
    the transaction, and the browser proxies of videos that have none; if the
    transaction is rejected (lease lost, or the database still unreachable after
    :meth:`JobContext.finish`'s tries) those files are removed again. A
    re-analysis (the job's ``offset_frames`` or ``swap_cameras``, asked for
    through :mod:`app.services.revisions`) adds a revision; none is replaced.
    With ``swap_cameras`` the video stored as right is measured as the rig's
    left camera and the other way round.
    """
    payload = ctx.job.payload
    offset = payload.get("offset_frames")
    swap = bool(payload.get("swap_cameras"))
    with ctx.sessions() as db:
        inputs = trial_inputs.analysis_inputs(
            db,
            ctx.storage,
            ctx.job.trial_id,
            offset_frames=float(offset) if offset is not None else None,
        )
    _require_files(ctx, inputs.files, what=f"trial {inputs.trial_id}")
    proxy_files = _ProxiesAlongside(ctx, inputs)
    written: list[str] = []
    try:
        try:
            analysis = _measure(ctx, inputs, swap=swap, proxies=proxy_files)
        except BradyscopeError as exc:  # core names the stored files: say which camera's
            exc.args = (inputs.described(str(exc)), *exc.args[1:])
            raise
        document = dict(analysis.result_document())
        document.setdefault("calibration", inputs.calibration.document())
        if swap:
            document["cameras_swapped"] = True
        document = _upload_warnings(ctx, document)
        overlay = _review_overlay(analysis, inputs, swap=swap, times=proxy_files.times)
        with ctx.storage.writing("results", ".csv") as (tmp_path, markers_path):
            write_markers_csv(analysis, tmp_path)
        written.append(markers_path)
        with ctx.storage.writing("overlays", ".json") as (tmp_path, overlay_path):
            tmp_path.write_text(json.dumps(overlay, allow_nan=False), encoding="utf-8")
        written.append(overlay_path)
        proxies = proxy_files.publish(written)
        if proxy_files.warnings:
            quality = dict(document.get("quality") or {})
            quality["warnings"] = [*(quality.get("warnings") or []), *proxy_files.warnings]
            document["quality"] = quality
        # Drawn once here, so that the result page and the reports only read them.
        table = read_markers_csv(ctx.storage.absolute(markers_path), fps=analysis.fps)
        plots_path = revisions.store_plots(ctx.storage, document, table)
        written.append(plots_path)

        def write(db: Session) -> None:
            revisions.store_analysis(
                db,
                trial_id=inputs.trial_id,
                job_id=ctx.job.id,
                calibration_id=inputs.calibration.id,
                document=document,
                markers_path=markers_path,
                overlay_path=overlay_path,
                request=payload.get("revision_request"),
                plots_path=plots_path,
            )
            trial_inputs.store_proxies(db, inputs.trial_id, proxies)

        ctx.finish(write)
    except BaseException:
        proxy_files.discard()
        for path in written:
            ctx.storage.delete(path)
        raise


_OPTION_WORDS = (
    (re.compile(r"--cols (\d+) --rows (\d+)"), r"Columns \1, Rows \2"),
    (re.compile(r"--cols/--rows/--square-mm"), "Columns, Rows and Square size (mm)"),
    (re.compile(r"--cols/--rows"), "Columns and Rows"),
    (re.compile(r"--cols and --rows"), "Columns and Rows"),
    (re.compile(r"--dictionary"), "ArUco dictionary"),
    (re.compile(r"--square-mm"), "Square size (mm)"),
    (re.compile(r"--marker-mm"), "Marker size (mm)"),
    (re.compile(r"--legacy"), "Printed with OpenCV before 4.6"),
)


def in_form_words(message: str) -> str:
    """A calibration error of ``core`` (worded for ``bradyscope calibrate``) with the
    calibration form's labels (``app.web.rigs.CALIBRATION_FORM_LABELS``) for its options."""
    for pattern, words in _OPTION_WORDS:
        message = pattern.sub(words, message)
    return message


def calibrate(ctx: JobContext) -> None:
    """Calibrate a rig from its two board videos; the calibration becomes ``ready``."""
    with ctx.sessions() as db:
        inputs = calibrations.calibration_inputs(
            db, ctx.storage, ctx.job.calibration_id, board=ctx.job.payload.get("board")
        )
    stored = (inputs.left, inputs.right, inputs.left_times, inputs.right_times)
    _require_files(
        ctx, [p for p in stored if p is not None], what=f"calibration {inputs.calibration_id}"
    )
    try:
        outcome = calibrate_stereo_from_paths(
            inputs.left,
            inputs.right,
            inputs.board,
            progress=ctx.progress,
            left_times=inputs.left_times,
            right_times=inputs.right_times,
        )
    except BradyscopeError as exc:  # core's words name the command line's options
        exc.args = (in_form_words(str(exc)), *exc.args[1:])
        raise
    ctx.finish(lambda db: calibrations.store_calibration(db, inputs.calibration_id, outcome))


def make_report_pdf(ctx: JobContext) -> None:
    """Make the PDF reports of the job's trial (its current result) and of its visit into
    the report cache, unless an analysis of the visit is pending
    (:func:`app.services.results.make_report_pdfs`); then the trend plots of its patient's
    page that are not kept yet (:func:`app.services.patients.draw_trend_plots`).

    Dated in the clinic's time zone (``BRADYSCOPE_TIMEZONE``): a worker must have the
    server's, or its reports are not the ones asked for (they are made again then).
    Nothing is made for a report already there, or a trial hidden or erased meanwhile.
    """
    if ctx.job.trial_id is None:
        raise ValueError(f"the report job {ctx.job.id} names no trial")
    made = results.make_report_pdfs(
        ctx.sessions, ctx.storage, ctx.job.trial_id, timezone=ctx.settings.timezone
    )
    if made is None:
        log.info("job %d: PDF reports left to the visit's pending analysis", ctx.job.id)
    else:
        log.info("job %d: PDF reports made for trials %s", ctx.job.id, made or "none (all kept)")
    drawn = patients.draw_trend_plots(
        ctx.sessions, ctx.storage, ctx.job.trial_id, timezone=ctx.settings.timezone
    )
    log.info("job %d: %d trend plots drawn for the patient page", ctx.job.id, drawn)


HANDLERS: dict[str, Handler] = {
    "analyze_trial": analyze_trial,
    "calibrate": calibrate,
    jobs.REPORT_PDF: make_report_pdf,
}


STAGES: dict[str, tuple[tuple[str, float], ...]] = {
    # core.pipeline.analyze_recording's stages and their rough share of the run time.
    "analyze_trial": (
        ("detection", 0.85),
        ("synchronisation", 0.04),
        ("triangulation", 0.04),
        ("tracking", 0.04),
        ("metrics", 0.03),
    ),
    # core.calibration.calibrate_stereo_from_paths's stages.
    "calibrate": (("detection", 0.7), ("calibration", 0.3)),
}
"""Ordered ``(stage, weight)`` per job kind: the job's progress fraction spans all stages.
Stages not listed report their own fraction."""

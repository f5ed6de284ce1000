"""`bradyscope analyze`: a stereo recording and a rig to markers.csv + result.json (INTERFACES.md)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from core.tasks import TASKS


def add_times_arguments(p: argparse.ArgumentParser) -> None:
    """``--left-times`` and ``--right-times``: each frame's capture time (``analyze``,
    ``calibrate``)."""
    p.add_argument(
        "--left-times",
        type=Path,
        metavar="CSV",
        help="capture time of each left frame (frame,time_s), e.g. from the capture page",
    )
    p.add_argument(
        "--right-times",
        type=Path,
        metavar="CSV",
        help="capture time of each right frame (frame,time_s)",
    )


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "analyze",
        help="measure thumb and index trajectories and tapping metrics from two videos",
        description=(
            "Detect the finger markers in both videos, synchronise the cameras, triangulate,"
            " track thumb and index, and write markers.csv and result.json into OUTDIR."
        ),
    )
    p.add_argument("--rig", required=True, type=Path, help="rig file (bradyscope.rig/1 JSON)")
    p.add_argument("--left", required=True, type=Path, help="left camera video")
    p.add_argument("--right", required=True, type=Path, help="right camera video")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="OUTDIR",
                   help="output folder (created if needed)")  # fmt: skip
    sync = p.add_mutually_exclusive_group()
    sync.add_argument(
        "--offset-frames",
        type=float,
        metavar="K",
        help="right frame j was taken with left frame j + K (default: estimated from the motion)",
    )
    sync.add_argument(
        "--auto-sync",
        action="store_true",
        help="estimate the frame offset from the marker motion (the default)",
    )
    add_times_arguments(p)
    p.add_argument(
        "--task",
        choices=TASKS,
        default=TASKS[0],
        help="the examination task recorded (MDS-UPDRS 3.4-3.8; default finger_tapping):"
        " its marker protocol and cycle metrics (docs/protocols.md)",
    )
    p.add_argument(
        "--side",
        choices=("right", "left"),
        default="right",
        help="the side examined (default right): gives the direction of supination"
        " (pronation_supination)",
    )
    p.add_argument(
        "--swap-labels",
        action="store_true",
        help="exchange the automatic thumb/index labels",
    )
    p.add_argument(
        "--max-gap-s",
        type=float,
        default=0.1,
        metavar="S",
        help="fill gaps up to this long (s) by interpolation; longer ones stay missing (0.1)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.cli.progress import progress_bar
    from app.upload_checks import SAME_FILE_MESSAGE, same_file
    from core.camera import read_rig
    from core.errors import InputError
    from core.pipeline import analyze_recording, write_analysis

    if same_file(args.left, args.right):  # as the server refuses it: at once
        raise InputError(SAME_FILE_MESSAGE)
    if not (math.isfinite(args.max_gap_s) and args.max_gap_s >= 0):
        raise InputError("--max-gap-s must be zero or positive.")
    if args.offset_frames is not None and not math.isfinite(args.offset_frames):
        raise InputError("--offset-frames must be a number of frames.")
    rig = read_rig(args.rig)
    with progress_bar() as progress:
        analysis = analyze_recording(
            rig,
            args.left,
            args.right,
            offset_frames=args.offset_frames,
            max_gap_s=args.max_gap_s,
            swap_labels=args.swap_labels,
            progress=progress,
            left_times=args.left_times,
            right_times=args.right_times,
            task=args.task,
            side=args.side,
        )
    try:
        write_analysis(analysis, args.output)
    except OSError as exc:
        raise InputError(
            f"cannot write the results into {args.output}: {exc.strerror}; choose another folder."
        ) from exc
    for warning in analysis.warnings:
        print(f"bradyscope analyze: warning: {warning}", file=sys.stderr)
    return 0

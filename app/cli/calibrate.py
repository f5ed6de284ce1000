"""`bradyscope calibrate` (INTERFACES.md): board recordings -> rig.json with quality."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.cli.analyze import add_times_arguments

if TYPE_CHECKING:
    from core.boards import BoardSpec


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate a stereo rig from two board recordings",
        description=(
            "Calibrate both cameras and their relative pose from recordings of a chessboard or"
            " ChArUco board (two videos, synchronous or free-running: their time offset is found"
            " from the board's motion; or two folders of images paired in file-name order)."
            " Writes the rig file with its quality figures."
        ),
    )
    p.add_argument("--left", required=True, type=Path, help="left video or image folder")
    p.add_argument("--right", required=True, type=Path, help="right video or image folder")
    p.add_argument("--board", required=True, choices=("chessboard", "charuco"))
    p.add_argument(
        "--cols",
        required=True,
        type=int,
        help="chessboard: inner corners per row; charuco: squares per row",
    )
    p.add_argument(
        "--rows",
        required=True,
        type=int,
        help="chessboard: inner corners per column; charuco: squares per column",
    )
    p.add_argument("--square-mm", required=True, type=float, help="square side (mm), as printed")
    p.add_argument("--marker-mm", type=float, default=None, help="charuco: marker side (mm)")
    p.add_argument(
        "--dictionary", default=None, help="charuco: ArUco dictionary (default DICT_4X4_1000)"
    )
    p.add_argument(
        "--legacy",
        action="store_true",
        help="charuco: a board printed with OpenCV before 4.6 (its layout with an even number"
        " of rows)",
    )
    p.add_argument(
        "--max-views", type=int, default=40, help="stereo views used in the fit at most (40)"
    )
    add_times_arguments(p)
    p.add_argument("-o", "--output", required=True, type=Path, help="rig file to write (JSON)")
    p.set_defaults(func=run)


def _board(args: argparse.Namespace) -> BoardSpec:
    from core.boards import BoardSpec
    from core.errors import InputError

    if args.board == "chessboard" and (
        args.marker_mm is not None or args.dictionary is not None or args.legacy
    ):
        raise InputError(
            "--marker-mm, --dictionary and --legacy describe ChArUco boards; drop them for a"
            " chessboard."
        )
    try:
        return BoardSpec(
            kind=args.board,
            cols=args.cols,
            rows=args.rows,
            square_mm=args.square_mm,
            marker_mm=args.marker_mm,
            dictionary=args.dictionary,
            legacy=args.legacy,
        )
    except ValueError as exc:
        raise InputError(f"the board description is invalid: {exc}.") from exc


def run(args: argparse.Namespace) -> int:
    from app.cli.progress import progress_bar
    from core.calibration import calibrate_stereo_from_paths, quality_verdict
    from core.camera import write_rig
    from core.errors import InputError

    board = _board(args)
    if args.max_views < 6:
        raise InputError(f"--max-views must be at least 6, got {args.max_views}.")
    out = Path(args.output)
    if out.parent and not out.parent.exists():
        raise InputError(f"the folder of the output file {out} does not exist; create it first.")
    with progress_bar() as progress:
        result = calibrate_stereo_from_paths(
            args.left,
            args.right,
            board,
            max_views=args.max_views,
            progress=progress,
            left_times=args.left_times,
            right_times=args.right_times,
        )
    write_rig(result.rig, out)
    q = result.quality
    verdict, reasons = quality_verdict(q)
    print(
        f"wrote {out}: {q['views_used']} views, RMS {q['rms_px']:.3f} px,"
        f" epipolar {q['epipolar_px_mean']:.3f} px, baseline {q['baseline_mm']:.2f} mm"
        f" — {verdict}",
    )
    for reason in reasons:
        print(f"  {reason}")
    sync_line = _sync_line(q.get("sync") or {})
    if sync_line:
        print(sync_line)
    for warning in q.get("warnings") or []:
        print(f"bradyscope calibrate: warning: {warning}", file=sys.stderr)
    return 0


def _sync_line(sync: dict[str, Any]) -> str | None:
    """One line on how the two videos were paired in time (None for image folders)."""
    method = sync.get("method")
    offset_s, frames = sync.get("offset_s"), sync.get("offset_frames")
    if method == "estimated" and offset_s is not None and frames is not None:
        when = "after" if offset_s >= 0 else "before"
        return (
            f"time offset: the right video starts {abs(offset_s):.3f} s ({abs(frames):.2f} frames)"
            f" {when} the left; views were paired at common instants"
        )
    if method == "synchronous":
        measured = f" (measured offset {frames:+.2f} frames)" if frames is not None else ""
        return f"time offset: none, the two videos are synchronous{measured}"
    return None

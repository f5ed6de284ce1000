"""Benchmark stereo calibration on a simulated board video pair (default 60 s).

Prints, for one run on this machine:

- the time of ``calibrate_stereo_from_paths`` (decode + sampled detection +
  selection + fit + quality) against two baselines measured in the same run:
  decoding the two videos only, and detection only (``collect_views``);
- the accuracy of the rig against the truth used to render the videos;
- the accuracy of the two chessboard corner detectors (``classic`` =
  findChessboardCorners + cornerSubPix, ``sb`` = findChessboardCornersSB) on
  rendered views with known corners, and their time per image.

Usage::

    python bench/bench_calibration.py [--duration-s 60] [--fps 15] [--board chessboard|charuco]
                                      [--width 1280 --height 1024] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from core.boards import BoardSpec, detect_board
from core.calibration import calibrate_stereo_from_paths, collect_views, quality_verdict
from core.camera import ImageSize, read_rig
from core.simulation.boards import (
    DEFAULT_CHESSBOARD,
    board_texture,
    example_rig,
    random_board_poses,
    render_board_view,
    write_board_recordings,
)
from core.video import iter_frames


def _rotation_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.rad2deg(np.arccos(np.clip(c, -1.0, 1.0))))


def bench_detectors(size: ImageSize, n_views: int = 12) -> None:
    rig = example_rig(image_size=size)
    board = DEFAULT_CHESSBOARD
    tex = board_texture(board)
    poses = random_board_poses(rig, board, n_views, rng=np.random.default_rng(7))
    sq: dict[str, list[float]] = {"classic": [], "sb": []}
    dt: dict[str, float] = {"classic": 0.0, "sb": 0.0}
    for k, (R, t) in enumerate(poses):
        img = render_board_view(rig.left, tex, R, t, board=board, rng=np.random.default_rng(k))
        truth = rig.left.project(board.object_points() @ R.T + t)
        for method in sq:
            t0 = time.perf_counter()
            det = detect_board(img, board, method=method)  # type: ignore[arg-type]
            dt[method] += time.perf_counter() - t0
            if det is None:
                continue
            e = min(
                float(np.sum((det.corners_px - truth) ** 2)),
                float(np.sum((det.corners_px[::-1] - truth) ** 2)),
            )
            sq[method].append(e / len(truth))
    print(f"corner detectors on {n_views} rendered {size.width}x{size.height} views (truth known):")
    for method in sq:
        rms = np.sqrt(np.mean(sq[method])) if sq[method] else float("nan")
        print(
            f"  {method:8s} corner RMS {rms:.4f} px, found {len(sq[method])}/{n_views},"
            f" {1000 * dt[method] / n_views:.1f} ms/image"
        )
    ratio = np.sqrt(np.mean(sq["sb"])) / np.sqrt(np.mean(sq["classic"]))
    print(f"  sb / classic corner RMS ratio: {ratio:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration-s", type=float, default=60.0)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--board", choices=("chessboard", "charuco"), default="chessboard")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=1024)
    ap.add_argument("--pose-interval-s", type=float, default=2.0)
    ap.add_argument("--keep", type=Path, default=None, help="write/reuse the videos in this folder")
    args = ap.parse_args()
    size = ImageSize(args.width, args.height)

    bench_detectors(size)

    out = args.keep or Path(tempfile.mkdtemp(prefix="bench-calibration-"))
    left = out / f"{args.board}_left.mkv"
    right = out / f"{args.board}_right.mkv"
    if not (left.exists() and right.exists()):
        t0 = time.perf_counter()
        write_board_recordings(
            example_rig(image_size=size),
            out,
            seed=11,
            board=args.board,
            duration_s=args.duration_s,
            fps=args.fps,
            pose_interval_s=args.pose_interval_s,
            supersample=2,
        )
        print(
            f"rendered {args.duration_s:g} s at {args.fps:g} fps in {time.perf_counter() - t0:.1f} s"
        )
    board = BoardSpec.from_dict(json.loads((out / f"{args.board}.json").read_text()))
    true = read_rig(out / "rig_true.json")
    try:
        t0 = time.perf_counter()
        n = sum(1 for _ in zip(iter_frames(left), iter_frames(right), strict=False))
        t_decode = time.perf_counter() - t0

        t0 = time.perf_counter()
        collection = collect_views(left, right, board)
        t_detect = time.perf_counter() - t0

        t0 = time.perf_counter()
        result = calibrate_stereo_from_paths(left, right, board)
        t_cal = time.perf_counter() - t0
    finally:
        if args.keep is None:
            shutil.rmtree(out, ignore_errors=True)

    q = result.quality
    rig = result.rig
    print(
        f"video pair: {n} frames of {size.width}x{size.height} per camera"
        f" ({args.duration_s:g} s at {args.fps:g} fps), {args.board}"
    )
    print(f"  decode only (both videos):        {t_decode:7.2f} s")
    print(
        f"  detection only (collect_views):   {t_detect:7.2f} s"
        f"  ({collection.frames_tried} frame pairs searched)"
    )
    print(
        f"  full calibration:                 {t_cal:7.2f} s"
        f"  = {t_cal / t_detect:.2f} x detection, {t_cal / t_decode:.2f} x decode"
    )
    print(
        f"  views: {q['views_both_detected']} detected in both, {q['views_used']} used,"
        f" {q['views_rejected']} rejected, {q['views_duplicate']} near-duplicates,"
        f" {q['views_blurred']} blurred, {q['views_held_out']} held out"
    )
    for e, t in zip(rig.cameras, true.cameras, strict=True):
        f_err = 100 * (np.array([e.K[0, 0] / t.K[0, 0], e.K[1, 1] / t.K[1, 1]]) - 1)
        pp = e.K[:2, 2] - t.K[:2, 2]
        print(
            f"  {e.name:5s} focal error {f_err[0]:+.4f} % / {f_err[1]:+.4f} %,"
            f" principal point error ({pp[0]:+.3f}, {pp[1]:+.3f}) px"
        )
    print(f"  baseline error {rig.baseline_mm - true.baseline_mm:+.4f} mm")
    rot = _rotation_deg(rig.R_right_from_left, true.R_right_from_left)
    print(f"  relative rotation error {rot:.4f} deg")
    print(
        f"  RMS {q['rms_px']} px, epipolar {q['epipolar_px_mean']} px, square error"
        f" {q['square_error_mm_mean']} mm mean / {q['square_error_mm_rms']} mm RMS"
        f" ({q['square_check_method']}), verdict {quality_verdict(q)[0]}"
    )


if __name__ == "__main__":
    main()

"""Benchmark stereo calibration on a simulated board video pair (default 60 s).

Prints, for one run on this machine:

- the time of ``calibrate_stereo_from_paths`` (decode + sampled detection +
  selection + fit + quality) against two baselines measured in the same run:
  decoding the two videos only (in parallel: the floor), and detection only
  (``collect_views``); its ratio to the floor (issue 17's target: <= 2 for the
  60-s pair), as wall and as CPU time (steadier on a shared machine), with the
  load average;
- the accuracy of the rig against the truth used to render the videos;
- the accuracy of the two chessboard corner detectors (``classic`` =
  findChessboardCorners + cornerSubPix, ``sb`` = findChessboardCornersSB) on
  rendered views with known corners, and their time per image.

Usage::

    python bench/bench_calibration.py [--duration-s 60] [--fps 15] [--board chessboard|charuco]
                                      [--width 1280 --height 1024] [--keep DIR]
                                      [--start-s 0.3]   (free-running cameras)
"""

from __future__ import annotations

import argparse
import json
import os
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
from core.simulation.timing import CameraTiming
from core.video import decoder_threads_for, iter_frames


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


def bundle_adjust(rig0, board, pairs):
    """Peer of the joint refinement: scipy least squares over both cameras and every board pose.

    Minimises the same reprojection error as ``cv2.stereoCalibrate`` (intrinsics,
    5 distortion coefficients per camera, the right camera's pose, one board
    pose per view), started from ``rig0``'s per-camera intrinsics.
    """
    import cv2
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    from core.camera import Camera, StereoRig, distort_normalized

    obj, img_l, img_r, poses = [], [], [], []
    for dl, dr in pairs:
        ids = np.intersect1d(dl.ids, dr.ids)
        o = board.object_points()[ids]
        pl = dl.corners_px[np.isin(dl.ids, ids)]
        pr = dr.corners_px[np.isin(dr.ids, ids)]
        _ok, rv, tv = cv2.solvePnP(o, pl, rig0.left.K, rig0.left.dist)
        obj.append(o)
        img_l.append(pl)
        img_r.append(pr)
        poses.append(np.concatenate([rv.ravel(), tv.ravel()]))
    n_views = len(obj)
    counts = [len(o) for o in obj]

    def cam_params(c):
        return [c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], *c.dist[:5]]

    x0 = np.concatenate(
        [
            cam_params(rig0.left),
            cam_params(rig0.right),
            rig0.right.rvec,
            rig0.right.t_cam_from_world_mm,
            *poses,
        ]
    )

    def project(p, pts_cam):
        xy = pts_cam[:, :2] / pts_cam[:, 2:3]
        d = distort_normalized(xy, np.asarray(p[4:9]))
        return np.column_stack([d[:, 0] * p[0] + p[2], d[:, 1] * p[1] + p[3]])

    def rodrigues(rv):
        """Rotation matrices (V, 3, 3) of rotation vectors (V, 3)."""
        theta = np.linalg.norm(rv, axis=1)
        safe = np.where(theta > 1e-12, theta, 1.0)
        k = rv / safe[:, None]
        K = np.zeros((len(rv), 3, 3))
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
        K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
        s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
        return np.eye(3) + s * K + (1 - c) * (K @ K)

    view_of_point = np.repeat(np.arange(n_views), counts)
    obj_all = np.concatenate(obj)
    img_l_all = np.concatenate(img_l)
    img_r_all = np.concatenate(img_r)

    def residuals(x):
        pl, pr = x[0:9], x[9:18]
        R_rl = rodrigues(x[18:21][None])[0]
        t_rl = x[21:24]
        vp = x[24:].reshape(n_views, 6)
        Rv = rodrigues(vp[:, :3])[view_of_point]
        X = np.einsum("nij,nj->ni", Rv, obj_all) + vp[view_of_point, 3:]
        rl = (project(pl, X) - img_l_all).reshape(-1)
        rr = (project(pr, X @ R_rl.T + t_rl) - img_r_all).reshape(-1)
        return np.concatenate([rl, rr])

    n_pts = sum(counts)
    sparsity = lil_matrix((4 * n_pts, len(x0)), dtype=int)
    sparsity[0 : 2 * n_pts, 0:9] = 1
    sparsity[2 * n_pts :, 9:24] = 1
    for v in range(n_views):
        idx = np.flatnonzero(view_of_point == v)
        rows = np.concatenate([2 * idx, 2 * idx + 1])
        for base in (0, 2 * n_pts):
            sparsity[(base + rows)[:, None], np.arange(24 + 6 * v, 30 + 6 * v)[None, :]] = 1
    sol = least_squares(
        residuals, x0, jac_sparsity=sparsity, x_scale="jac", method="trf", xtol=1e-10, ftol=1e-10
    )
    x = sol.x

    def camera(name, p, R=np.eye(3), t=np.zeros(3)):
        K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1]])
        return Camera(name, rig0.left.image_size, K, p[4:9], R, t)

    rig = StereoRig(
        camera("left", x[0:9]), camera("right", x[9:18], cv2.Rodrigues(x[18:21])[0], x[21:24])
    )
    rms = float(np.sqrt(np.mean(sol.fun.reshape(-1, 2) ** 2) * 2))
    return rig, rms


def report_errors(name, rig, true):
    f_err = max(
        abs(e.K[i, i] / t.K[i, i] - 1)
        for e, t in zip(rig.cameras, true.cameras, strict=True)
        for i in (0, 1)
    )
    pp = max(
        float(np.max(np.abs(e.K[:2, 2] - t.K[:2, 2])))
        for e, t in zip(rig.cameras, true.cameras, strict=True)
    )
    rot = _rotation_deg(rig.R_right_from_left, true.R_right_from_left)
    print(
        f"  {name:34s} focal {100 * f_err:.4f} %, principal point {pp:.3f} px,"
        f" baseline {rig.baseline_mm - true.baseline_mm:+.4f} mm, rotation {rot:.4f} deg"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration-s", type=float, default=60.0)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--board", choices=("chessboard", "charuco"), default="chessboard")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=1024)
    ap.add_argument("--pose-interval-s", type=float, default=2.0)
    ap.add_argument("--keep", type=Path, default=None, help="write/reuse the videos in this folder")
    ap.add_argument("--skip-detectors", action="store_true", help="skip the detector comparison")
    ap.add_argument(
        "--start-s",
        type=float,
        default=0.0,
        help="free-running cameras: the right one starts this much later (s), 100 ppm faster",
    )
    args = ap.parse_args()
    size = ImageSize(args.width, args.height)

    if not args.skip_detectors:
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
            timing=(
                (CameraTiming(), CameraTiming(start_s=args.start_s, drift_ppm=100.0))
                if args.start_s
                else None
            ),
        )
        print(
            f"rendered {args.duration_s:g} s at {args.fps:g} fps in {time.perf_counter() - t0:.1f} s"
        )
    board = BoardSpec.from_dict(json.loads((out / f"{args.board}.json").read_text()))
    true = read_rig(out / "rig_true.json")
    load = os.getloadavg()[0]
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        threads = decoder_threads_for(2)  # as calibration decodes the pair
        n = sum(
            1
            for _ in zip(
                iter_frames(left, decoder_threads=threads),
                iter_frames(right, decoder_threads=threads),
                strict=False,
            )
        )
        t_decode, c_decode = time.perf_counter() - t0, time.process_time() - c0

        t0 = time.perf_counter()
        collection = collect_views(left, right, board)
        t_detect = time.perf_counter() - t0

        t0, c0 = time.perf_counter(), time.process_time()
        result = calibrate_stereo_from_paths(left, right, board)
        t_cal, c_cal = time.perf_counter() - t0, time.process_time() - c0
    finally:
        if args.keep is None:
            shutil.rmtree(out, ignore_errors=True)

    q = result.quality
    rig = result.rig
    print(
        f"video pair: {n} frames of {size.width}x{size.height} per camera"
        f" ({args.duration_s:g} s at {args.fps:g} fps), {args.board}"
    )
    print(f"  decode only (both, in parallel):  {t_decode:7.2f} s  CPU {c_decode:6.2f} s")
    print(
        f"  detection only (collect_views):   {t_detect:7.2f} s"
        f"  ({collection.frames_tried} frame pairs searched)"
    )
    print(
        f"  full calibration:                 {t_cal:7.2f} s  CPU {c_cal:6.2f} s"
        f"  = {t_cal / t_detect:.2f} x detection"
    )
    print(
        f"  calibration / decode only (the floor): {t_cal / t_decode:.2f} wall,"
        f" {c_cal / c_decode:.2f} CPU (target <= 2); load average {load:.1f}"
        f" on {os.cpu_count()} cores"
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
    sync = q["sync"]
    print(
        f"  time offset: {sync['method']}, {sync['offset_s']:+.5f} s"
        f" ({sync['offset_frames']:+.3f} frames; true {args.start_s:+.5f} s at the start)"
    )
    rot = _rotation_deg(rig.R_right_from_left, true.R_right_from_left)
    print(f"  relative rotation error {rot:.4f} deg")
    # Peer of the joint refinement: a scipy bundle adjustment on the same views.
    from core.calibration import _best_numbering, _calibrate_camera

    by_frame = {v.frame: v for v in collection.views}
    frames = [pv["frame"] for pv in q["per_view"]]
    pairs = [
        (by_frame[f].left, _best_numbering(rig, board, by_frame[f].left, by_frame[f].right))
        for f in frames
    ]
    from core.camera import Camera, StereoRig

    _, K_l, d_l, *_ = _calibrate_camera([p[0] for p in pairs], size)
    _, K_r, d_r, *_ = _calibrate_camera([p[1] for p in pairs], size)
    start = StereoRig(
        Camera("left", size, K_l, d_l),
        Camera("right", size, K_r, d_r, rig.R_right_from_left, rig.t_right_from_left_mm),
    )
    t0 = time.perf_counter()
    ba_rig, ba_rms = bundle_adjust(start, board, pairs)
    t_ba = time.perf_counter() - t0
    print(f"  joint refinement peers on the same {len(pairs)} views (errors against the truth):")
    report_errors(f"cv2.stereoCalibrate (RMS {q['rms_px']:.4f} px)", rig, true)
    report_errors(f"scipy bundle adjustment (RMS {ba_rms:.4f} px, {t_ba:.1f} s)", ba_rig, true)
    print(
        f"  RMS {q['rms_px']} px, epipolar {q['epipolar_px_mean']} px, square error"
        f" {q['square_error_mm_mean']} mm mean / {q['square_error_mm_rms']} mm RMS"
        f" ({q['square_check_method']}), verdict {quality_verdict(q)[0]}"
    )


if __name__ == "__main__":
    main()

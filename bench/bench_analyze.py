"""Speed and memory of ``analyze`` against decoding alone and a plain OpenCV peer pipeline.

Usage::

    python bench/bench_analyze.py                       # the three kinds below, one after the other
    python bench/bench_analyze.py --kind lab-mp4v       # 1280x1024 100 fps, MPEG-4 Part 2
    python bench/bench_analyze.py --kind lab-ffv1       # 1280x1024 100 fps, lossless FFV1
    python bench/bench_analyze.py --kind consumer-h264  # 1920x1080 60 fps, H.264
    python bench/bench_analyze.py --kind free-running-h264  # the same, free-running cameras
    python bench/bench_analyze.py --dir DIR             # an existing session (left.*, right.*, rig.json)

Each kind simulates a 5-s and a 10-s pair (``--keep DIR`` keeps them for the
next run) and prints, measured in the same run on the same files:

- the floor: both videos decoded in parallel (one thread each, and the
  decoders' own threads and background reading as analyze sets them:
  ``core.video.decoder_threads_for``, ``decode_in_background``), and nothing else;
- analyze: ``core.pipeline.analyze_recording`` (detection, sync, triangulation,
  tracking, metrics) and its ratio to the floor (issue 17's target: <= 1.15 as
  the median of 5 alternating runs on an idle 2-core machine); both also as CPU
  time (of this process), the steadier figure when other jobs share the
  machine; ``--repeat`` alternating pairs of runs (default 5) and their median
  ratio, since a shared machine's speed drifts;
- peer: a plain OpenCV pipeline (fixed threshold, ``connectedComponentsWithStats``
  centroids, the two largest blobs sorted by image row, ``cv2.undistortPoints``,
  ``cv2.triangulatePoints``), its ratio to decoding, and both pipelines' 3D RMS
  error against the simulator's truth when a ``truth.json`` is there;
- with ``--breakdown``, where analyze's time above the floor goes: decoding with
  the per-frame bookkeeping (the detector's answers replayed), the marker detector,
  and the stages after detection (time model, triangulation, tracking, metrics);
- peak memory (max RSS of a fresh process running analyze) for the 5-s and
  the 10-s clip: it must not grow with the length of the video.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _videos(d: Path) -> tuple[Path, Path]:
    left = next(p for p in sorted(d.glob("left.*")))
    right = next(p for p in sorted(d.glob("right.*")))
    return left, right


#: Recording kinds: (codec, (width, height) px, fps).
KINDS: dict[str, tuple[str, tuple[int, int], float]] = {
    "lab-mp4v": ("mp4v", (1280, 1024), 100.0),
    "lab-ffv1": ("lossless", (1280, 1024), 100.0),
    "consumer-h264": ("h264", (1920, 1080), 60.0),
    # Free-running cameras (issue 11, docs/sync.md): the right one starts 0.237 s late, runs
    # 300 ppm fast and loses three frames that its timestamps do not show.
    "free-running-h264": ("h264", (1920, 1080), 60.0),
}


def simulate(out: Path, seconds: float, kind: str) -> Path:
    from core.camera import ImageSize
    from core.simulation.kinematics import TappingScenario
    from core.simulation.session import ImagingScenario, simulate_session
    from core.simulation.timing import CameraTiming

    codec, size, fps = KINDS[kind]
    right = CameraTiming()
    if kind == "free-running-h264":
        n = round(seconds * fps)
        drops = (round(0.25 * n), round(0.52 * n), round(0.76 * n))  # 150, 312, 456 in 10 s
        right = CameraTiming(start_s=0.237, drift_ppm=300.0, drop_after=drops)
    simulate_session(
        out,
        seed=7,
        tapping=TappingScenario(duration_s=seconds, fps=fps),
        imaging=ImagingScenario(
            codec=codec,
            image_size=ImageSize(*size),
            distractors_static=2,
            distractors_moving=1,
            right_timing=right,
        ),
    )
    return out


def decode_only(left: Path, right: Path) -> float:
    from core.video import decode_in_background, decoder_threads_for, iter_frames

    # as analyze decodes: the fastest on 2 cores (docs/performance.md)
    decoder_threads = decoder_threads_for(2)
    background = decode_in_background(2)
    errors: list[BaseException] = []

    def run(path: Path) -> None:
        try:
            for _ in iter_frames(
                path, gray=True, decoder_threads=decoder_threads, background=background
            ):
                pass
        except BaseException as exc:  # re-raised below: a failed decode is no floor
            errors.append(exc)

    t0 = time.perf_counter()
    threads = [threading.Thread(target=run, args=(p,)) for p in (left, right)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    return time.perf_counter() - t0


def peer_pipeline(d: Path) -> tuple[float, np.ndarray]:
    """Threshold + connected components + cv2.triangulatePoints; (seconds, (T, 2, 3) mm)."""
    import cv2

    from core.camera import read_rig
    from core.video import decode_in_background, decoder_threads_for, iter_frames

    rig = read_rig(d / "rig.json")
    left, right = _videos(d)
    results: dict[int, list[np.ndarray]] = {0: [], 1: []}
    decoding = {"decoder_threads": decoder_threads_for(2), "background": decode_in_background(2)}

    def run(k: int, path: Path) -> None:
        for img in iter_frames(path, gray=True, **decoding):
            _, binary = cv2.threshold(img, 100, 255, cv2.THRESH_BINARY)
            _n, _, stats, centroids = cv2.connectedComponentsWithStats(binary, connectivity=8)
            order = np.argsort(-stats[1:, cv2.CC_STAT_AREA])[:2] + 1
            pts = centroids[order]
            pts = pts[np.argsort(-pts[:, 1])] if len(pts) == 2 else np.full((2, 2), np.nan)
            results[k].append(pts)  # [lower (thumb), upper (index)]

    t0 = time.perf_counter()
    threads = [threading.Thread(target=run, args=(k, p)) for k, p in enumerate((left, right))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    n = min(len(results[0]), len(results[1]))
    lp = np.concatenate(results[0][:n]).reshape(-1, 1, 2)
    rp = np.concatenate(results[1][:n]).reshape(-1, 1, 2)
    ln = cv2.undistortPoints(lp, rig.left.K, rig.left.dist).reshape(-1, 2)
    rn = cv2.undistortPoints(rp, rig.right.K, rig.right.dist).reshape(-1, 2)
    h = cv2.triangulatePoints(
        rig.left.projection_matrix_normalized, rig.right.projection_matrix_normalized, ln.T, rn.T
    )
    pts = (h[:3] / h[3]).T.reshape(n, 2, 3)
    return time.perf_counter() - t0, pts


def analyze_in_child(d: Path) -> tuple[float, float]:
    """Run analyze in a fresh process; (seconds, its peak RSS in MB)."""
    code = (
        f"import sys, time; sys.path.insert(0, {str(ROOT)!r})\n"
        "from pathlib import Path\n"
        "from core.camera import read_rig\n"
        "from core.pipeline import analyze_recording\n"
        f"d = Path({str(d)!r})\n"
        "left = sorted(d.glob('left.*'))[0]; right = sorted(d.glob('right.*'))[0]\n"
        "t = time.perf_counter()\n"
        "analyze_recording(read_rig(d / 'rig.json'), left, right)\n"
        "t = time.perf_counter() - t\n"
        "import resource\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n"
        "print(t)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    if proc.returncode != 0:
        raise SystemExit(f"analyze failed on {d}")
    lines = proc.stdout.strip().splitlines()
    return float(lines[-1]), float(lines[-2]) / 1024.0


def accuracy(d: Path, positions_mm: np.ndarray) -> float | None:
    truth_path = d / "truth.json"
    if not truth_path.exists():
        return None
    truth = np.asarray(json.loads(truth_path.read_text())["positions_mm"], dtype=float)[:, :2]
    n = min(len(truth), len(positions_mm))
    err = np.linalg.norm(positions_mm[:n] - truth[:n], axis=2)
    return float(np.sqrt(np.nanmean(err**2)))


def _cpu_s() -> float:
    """CPU time (s) of this process, all threads."""
    me = resource.getrusage(resource.RUSAGE_SELF)
    return me.ru_utime + me.ru_stime


def breakdown(d: Path, repeat: int) -> None:
    """Where analyze's time above the floor goes, median of ``repeat`` alternating runs:

    - decoding with the per-frame bookkeeping (search windows, set-aside blobs, image
      patches) but no marker search: the detector's answers, recorded in a first run,
      are replayed;
    - the marker detector itself (analyze minus the replay, to the end of detection);
    - the stages after detection (time model, triangulation, tracking, metrics), which
      run on one core.
    """
    from core.camera import read_rig
    from core.pipeline import analyze_recording

    sys.path.insert(0, str(ROOT / "tests"))
    from detector_replay import RecordedDetector

    left, right = _videos(d)
    rig = read_rig(d / "rig.json")
    detections = RecordedDetector()  # the replay checks each call asks for the same search
    analyze_recording(rig, left, right, detector=detections.record)
    rows: dict[str, list[float]] = {"floor": [], "replay": [], "detector": [], "after": []}
    for _ in range(repeat):
        rows["floor"].append(decode_only(left, right))
        ends = {}
        detections.rewind()
        for name, detector in (("replay", detections.replay), ("real", None)):
            marks: list[float] = []

            def progress(stage: str, done: int, total: int, marks: list[float] = marks) -> None:
                if stage == "detection" and done == total and not marks:
                    marks.append(time.perf_counter())

            t0 = time.perf_counter()
            analyze_recording(rig, left, right, detector=detector, progress=progress)
            ends[name] = (marks[0] - t0, time.perf_counter() - marks[0])
        rows["replay"].append(ends["replay"][0])
        rows["detector"].append(ends["real"][0] - ends["replay"][0])
        rows["after"].append(ends["real"][1])
    med = {k: float(np.median(v)) for k, v in rows.items()}
    floor = med["floor"]
    print(
        f"  where the time goes (median of {repeat}, share of the floor):"
        f" floor {floor:.2f} s; decoding + per-frame bookkeeping, detector replayed"
        f" {med['replay']:.2f} s ({med['replay'] / floor:.2f}); + the marker detector"
        f" {med['detector']:.2f} s ({med['detector'] / floor:.2f}); + the stages after detection"
        f" {med['after']:.2f} s ({med['after'] / floor:.2f})"
    )


def bench(d: Path, repeat: int) -> None:
    from core.camera import read_rig
    from core.pipeline import analyze_recording

    left, right = _videos(d)
    rig = read_rig(d / "rig.json")
    ratios, cpu_ratios = [], []
    analysis = None
    for r in range(repeat):  # alternating, so that a slow spell of the machine hits both
        c0 = _cpu_s()
        t_dec = decode_only(left, right)
        c_dec = _cpu_s() - c0
        c0, t0 = _cpu_s(), time.perf_counter()
        analysis = analyze_recording(rig, left, right)
        t_ana = time.perf_counter() - t0
        c_ana = _cpu_s() - c0
        n = len(analysis.frame_numbers)
        if r == 0:
            print(f"{d.name}: {n} frames of {left.name} + {right.name}")
        print(
            f"  run {r + 1}: parallel decode {t_dec:6.2f} s  CPU {c_dec:5.2f} s |"
            f" analyze {t_ana:6.2f} s  CPU {c_ana:5.2f} s | ratio {t_ana / t_dec:4.2f}"
            f"  CPU ratio {c_ana / c_dec:4.2f}"
        )
        ratios.append(t_ana / t_dec)
        cpu_ratios.append(c_ana / c_dec)
    assert analysis is not None
    print(
        f"  analyze / parallel decode (the floor): median {float(np.median(ratios)):.2f}"
        f" (range {min(ratios):.2f}-{max(ratios):.2f}) wall, median"
        f" {float(np.median(cpu_ratios)):.2f} CPU over {repeat} alternating runs"
        f" (target <= 1.15 wall); load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    t_dec = decode_only(left, right)
    t_peer, peer_pts = peer_pipeline(d)
    print(
        f"  peer (threshold+CC+triangulatePoints) {t_peer:7.2f} s  ratio to decode"
        f" {t_peer / t_dec:5.2f} (decode {t_dec:.2f} s, just before)"
    )
    acc_ours = accuracy(d, analysis.positions_mm)
    acc_peer = accuracy(d, peer_pts)
    if acc_ours is not None:
        print(f"  3D RMS error vs truth: analyze {acc_ours:.4f} mm, peer {acc_peer:.4f} mm")
    sync = analysis.sync
    truth_path = d / "truth.json"
    if "offset_s" in sync and truth_path.exists():
        truth = json.loads(truth_path.read_text())
        right = truth["cameras"]["right"]
        print(
            f"  time model: offset {sync['offset_s']:.6f} s, drift {sync['drift_ppm']:.1f} ppm,"
            f" lost frames right {sync['dropped_frames_right']} (simulated"
            f" {right['dropped_after']}), left {sync['dropped_frames_left']}; confidence"
            f" {sync['confidence']:.2f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--dir", type=Path, help="an existing session folder (left.*, right.*, rig.json)"
    )
    ap.add_argument(
        "--kind", choices=(*KINDS, "all"), default="all", help="recording kind (default: all)"
    )
    ap.add_argument(
        "--repeat", type=int, default=5, help="alternating decode/analyze runs (median ratio)"
    )
    ap.add_argument(
        "--seconds", type=float, default=10.0, help="length of the timed clip (s; default 10)"
    )
    ap.add_argument("--no-memory", action="store_true", help="skip the peak-memory runs")
    ap.add_argument(
        "--breakdown",
        action="store_true",
        help="also time the parts above the floor (per-frame bookkeeping, detector, later stages)",
    )
    ap.add_argument(
        "--keep", type=Path, help="simulate into this folder (default: a temporary one)"
    )
    args = ap.parse_args()
    if args.dir is not None:
        bench(args.dir, args.repeat)
        if args.breakdown:
            breakdown(args.dir, args.repeat)
        t, rss = analyze_in_child(args.dir)
        print(f"  peak RSS of a fresh analyze process: {rss:.0f} MB ({t:.1f} s)")
        return
    kinds = list(KINDS) if args.kind == "all" else [args.kind]
    lengths = [args.seconds] if args.no_memory else sorted({args.seconds / 2, args.seconds})
    with tempfile.TemporaryDirectory() as tmp:
        base = args.keep if args.keep is not None else Path(tmp)
        for kind in kinds:
            dirs = {}
            for seconds in lengths:
                d = base / f"session_{seconds:g}s_{kind}"
                if not (d / "rig.json").exists():
                    print(f"simulating {seconds:g} s ({kind}) into {d} ...", flush=True)
                    simulate(d, seconds, kind)
                dirs[seconds] = d
            print(f"{kind}:")
            bench(dirs[args.seconds], args.repeat)
            if args.breakdown:
                breakdown(dirs[args.seconds], args.repeat)
            if not args.no_memory:
                for seconds, d in dirs.items():
                    t, rss = analyze_in_child(d)
                    print(f"  peak RSS of analyze, {seconds:4g}-s clip: {rss:6.0f} MB ({t:.1f} s)")


if __name__ == "__main__":
    main()

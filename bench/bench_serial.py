"""CPU and wall time of ``analyze``'s serial part: everything after detection.

Usage::

    python bench/bench_serial.py DIR [DIR ...] [--repeat 5] [--profile]
    python bench/bench_serial.py DIR --save OUT.npz     # keep the results to compare later
    python bench/bench_serial.py DIR --compare OUT.npz  # the largest differences to a saved run

Each ``DIR`` is a session (``left.*``, ``right.*``, ``rig.json``), e.g. one that
``bench/bench_analyze.py --keep DIR`` simulated. Both videos are decoded and
searched once (:func:`core.pipeline._detect_videos`); then ``analyze_recording``
runs ``--repeat`` times on those detections, and each run's serial part
(synchronisation, triangulation, tracking, metrics: from the end of detection
to the return) is timed as CPU of this process (all threads) and as wall time.
The best of the runs is printed: the serial part runs while one core idles, so
its wall time adds to the analysis one for one (issue 17).

``--save`` writes the positions, statuses, reprojection errors, frame times and
``result.json`` (without its ``software`` object) of the last run; ``--compare``
prints the largest difference of each to a saved file, and whether
``result.json`` is the same text.
"""

from __future__ import annotations

import argparse
import copy
import cProfile
import json
import os
import pstats
import resource
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _cpu_s() -> float:
    """CPU time (s) of this process, all threads."""
    me = resource.getrusage(resource.RUSAGE_SELF)
    return me.ru_utime + me.ru_stime


def _result_text(analysis: Any) -> str:
    doc = analysis.result_document()
    doc.pop("software", None)
    return json.dumps(doc, indent=2, allow_nan=False, sort_keys=True)


def run(d: Path, repeat: int, profile: bool) -> Any:
    import core.pipeline as pipeline
    from core.camera import read_rig

    left = sorted(d.glob("left.*"))[0]
    right = sorted(d.glob("right.*"))[0]
    rig = read_rig(d / "rig.json")

    detect = pipeline._detect_videos
    cached: dict[str, Any] = {}
    mark: dict[str, float] = {}

    def detect_once(*args: Any, **kwargs: Any) -> Any:
        stamps = kwargs.get("timestamps")
        if not cached:
            out = detect(*args, **kwargs)
            cached["out"] = copy.deepcopy(out)
            cached["stamps"] = copy.deepcopy(stamps)
        elif stamps is not None:
            for k in (0, 1):
                stamps[k].extend(cached["stamps"][k])
        mark["cpu"], mark["wall"] = _cpu_s(), time.perf_counter()
        left_px, right_px, info, patches = copy.deepcopy(cached["out"])
        return left_px, right_px, info, patches

    pipeline._detect_videos = detect_once  # type: ignore[assignment]
    try:
        analysis = pipeline.analyze_recording(rig, left, right)  # detection, warm-up
        cpu, wall = [], []
        prof = cProfile.Profile() if profile else None
        for _ in range(repeat):
            if prof is not None:
                prof.enable()
            analysis = pipeline.analyze_recording(rig, left, right)
            c1, w1 = _cpu_s(), time.perf_counter()
            if prof is not None:
                prof.disable()
            cpu.append(c1 - mark["cpu"])
            wall.append(w1 - mark["wall"])
    finally:
        pipeline._detect_videos = detect  # type: ignore[assignment]
    print(
        f"{d.name}: serial part CPU best {min(cpu):.3f} s (median {np.median(cpu):.3f}),"
        f" wall best {min(wall):.3f} s (median {np.median(wall):.3f}), {repeat} runs,"
        f" load {os.getloadavg()[0]:.1f}",
        flush=True,
    )
    if prof is not None:
        pstats.Stats(prof).sort_stats("cumulative").print_stats(40)
    return analysis


def save(analysis: Any, path: Path) -> None:
    np.savez(
        path,
        positions_mm=analysis.positions_mm,
        status=analysis.status.astype(str),
        reprojection_px=analysis.reprojection_px,
        time_s=analysis.time_s,
        result=np.array(_result_text(analysis)),
    )


def compare(analysis: Any, path: Path) -> None:
    ref = np.load(path)

    def worst(a: np.ndarray, b: np.ndarray) -> str:
        if a.shape != b.shape:
            return f"shapes differ {a.shape} vs {b.shape}"
        if not np.array_equal(np.isnan(a), np.isnan(b)):
            return "NaN at other places"
        d = np.abs(a - b)
        return f"{np.nanmax(d) if np.any(np.isfinite(d)) else 0.0:.3g}"

    same_status = np.array_equal(analysis.status.astype(str), ref["status"])
    same_result = _result_text(analysis) == str(ref["result"])
    print(
        f"  vs {path.name}: positions {worst(analysis.positions_mm, ref['positions_mm'])} mm,"
        f" reprojection {worst(analysis.reprojection_px, ref['reprojection_px'])} px,"
        f" frame times {worst(analysis.time_s, ref['time_s'])} s,"
        f" status {'same' if same_status else 'DIFFERENT'},"
        f" result.json {'same' if same_result else 'DIFFERENT'}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dirs", nargs="+", type=Path)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--profile", action="store_true", help="cProfile the timed runs")
    ap.add_argument("--save", type=Path, help="with one DIR: keep its results in this .npz")
    ap.add_argument("--compare", type=Path, help="with one DIR: compare with this .npz")
    args = ap.parse_args()
    if (args.save or args.compare) and len(args.dirs) != 1:
        ap.error("--save and --compare take one DIR")
    for d in args.dirs:
        analysis = run(d, args.repeat, args.profile)
        if args.save:
            save(analysis, args.save)
        if args.compare:
            compare(analysis, args.compare)


if __name__ == "__main__":
    main()

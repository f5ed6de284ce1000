"""Accuracy of a take as the capture page records it, with and without its timestamps files.

Usage::

    python bench/bench_browser_take.py                 # simulate the take into a temporary folder
    python bench/bench_browser_take.py --dir DIR       # keep (or reuse) the simulated take in DIR

The take is of the kind ``tests/app/test_browser_recordings.py`` measures (whose take
lasts 7 s, its frames lost earlier): two VP9 WebM files (1920x1080, 60 fps, 10 s) whose
timestamps are rounded to 1 ms, as Chromium's
MediaRecorder writes them, from two cameras with capture jitter (1 ms), lost frames in
both and two clocks (the right one 43 ms later, 250 ppm fast). The capture page's
timestamps files (``frame,time_s``: each frame's capture time, µs, on its camera's
clock; the file's 1-ms time for the 4 % of frames the page did not show) are written
beside them. ``core.pipeline.analyze_recording`` measures the take twice, with the
timestamps files and from the WebM files' own timestamps alone (an MP4 take, or one
whose frames the page could not pair), and prints for each the 3D RMS error and the
thumb–index distance RMS error against the simulator's truth, the share of frames
measured, the errors of the estimated offset and drift, and the CPU time of the
analysis (this process).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CLOCK_ORIGIN_S = {"left": 8123.456789, "right": 91234.125}
UNSHOWN = 0.04


def simulate(out: Path) -> None:
    from core.camera import ImageSize
    from core.simulation.kinematics import TappingScenario
    from core.simulation.session import ImagingScenario, simulate_session
    from core.simulation.timing import CameraTiming

    simulate_session(
        out,
        seed=13,
        tapping=TappingScenario(duration_s=10.0, fps=60.0, hesitations=(6,), halts=((14, 0.8),)),
        imaging=ImagingScenario(
            image_size=ImageSize(1920, 1080),
            codec="vp9",
            left_timing=CameraTiming(jitter_s=0.001, vfr=True, drop_after=(120, 380)),
            right_timing=CameraTiming(
                start_s=0.043, drift_ppm=250.0, jitter_s=0.001, vfr=True, drop_after=(200, 201, 455)
            ),
        ),
    )


def write_times(out: Path, truth: dict) -> dict[str, Path]:
    rng = np.random.default_rng(4)
    paths = {}
    for side in ("left", "right"):
        stamps = np.asarray(truth["cameras"][side]["timestamps_s"])
        shown = rng.random(len(stamps)) >= UNSHOWN
        shown[[0, -1]] = True
        times = CLOCK_ORIGIN_S[side] + np.where(shown, stamps, np.round(stamps, 3))
        paths[side] = out / f"{side}_times.csv"
        paths[side].write_text(
            "frame,time_s\n" + "".join(f"{i},{t:.6f}\n" for i, t in enumerate(times))
        )
    return paths


def measure(out: Path, truth: dict, times: dict[str, Path] | None) -> dict[str, float]:
    from core.camera import read_rig
    from core.pipeline import analyze_recording

    kw = {} if times is None else {"left_times": times["left"], "right_times": times["right"]}
    cpu = time.process_time()
    a = analyze_recording(read_rig(out / "rig.json"), out / "left.webm", out / "right.webm", **kw)
    cpu = time.process_time() - cpu
    true_mm = np.asarray(truth["positions_mm"])[:, :2]
    measured = a.status == "measured"
    both = measured.all(axis=1)
    err = np.linalg.norm(a.positions_mm - true_mm, axis=2)
    d = np.linalg.norm(a.positions_mm[:, 0] - a.positions_mm[:, 1], axis=1)
    d_true = np.linalg.norm(true_mm[:, 0] - true_mm[:, 1], axis=1)
    return {
        "rms_mm": float(np.sqrt(np.mean(err[measured] ** 2))),
        "distance_rms_mm": float(np.sqrt(np.mean((d - d_true)[both] ** 2))),
        "measured": float(np.mean(both)),
        "offset_error_ms": 1000 * (a.sync["offset_s"] - truth["clock"]["offset_s"]),
        "drift_error_ppm": a.sync["drift_ppm"] - truth["clock"]["drift_ppm"],
        "cpu_s": cpu,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dir", type=Path, help="folder of the simulated take (made if empty)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = args.dir or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        if not (out / "truth.json").exists():
            print("simulating the take ...", flush=True)
            simulate(out)
        truth = json.loads((out / "truth.json").read_text())
        times = write_times(out, truth)
        for label, given in (("with the timestamps files", times), ("container times only", None)):
            figures = measure(out, truth, given)
            print(f"{label}: " + ", ".join(f"{k} {v:.4f}" for k, v in figures.items()), flush=True)


if __name__ == "__main__":
    main()

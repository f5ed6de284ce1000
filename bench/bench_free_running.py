"""Accuracy of ``analyze`` on free-running cameras, per case of issue 11 (docs/sync.md).

Usage::

    python bench/bench_free_running.py                       # every case (about 5 min each)
    python bench/bench_free_running.py --cases vfr,fps120    # some of them
    python bench/bench_free_running.py --keep DIR            # keep the simulations for next time

The cases are those of ``tests/core/test_free_running.py``, here all 10 s long (1920x1080
60-fps H.264 recordings from the simulator, hesitation and halt included, seed
11; here with the simulator's own x264 preset, ``superfast``, about 50 Mbit/s,
where the tests use ``ultrafast``, about 16 Mbit/s): ``drift`` (the right
camera 0.237 s late, 300 ppm fast), ``drops`` (three
frames lost in the right camera, constant timestamps), ``vfr`` (variable frame
rate timestamps with 0.5-ms jitter, a lost left frame and two lost right
frames, -150 ppm), ``rolling`` (15-ms readout in both cameras, the right one
pitched 6 degrees; also measured without ``readout_ms``: the uncompensated
error) and ``fps120`` (a 120-fps left camera with a 60-fps right one).

Prints per case: 3D RMS and thumb–index distance RMS against the truth (frames
measured by both cameras), the share of frames measured, the time model found
(offset, drift, lost frames) against the simulated one, and the metrics against
the truth: tap count, mean amplitude, frequency, and the mean peak opening and
closing speeds against the same tapping sampled evenly (``compute_metrics`` on
the truth's trajectories at ``i / fps``).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "core"))
BENCH_SECONDS = 10.0  # s, every case (the tests shorten all but the drift case)


def _report(  # type: ignore[no-untyped-def]
    name: str, session, analysis, seconds: float, *, label: str | None = None, what: str = "analyze"
) -> None:
    import test_free_running as cases

    from core.metrics import compute_metrics
    from core.simulation.kinematics import simulate_tapping

    rms, d_rms, both = cases._errors(session, analysis)
    truth, sync = session.truth, analysis.sync
    print(f"{label or name}: {what} {seconds:.0f} s (wall, load average {os.getloadavg()[0]:.1f})")
    print(
        f"  3D RMS {rms:.3f} mm, thumb-index distance RMS {d_rms:.3f} mm,"
        f" measured by both cameras {100 * both:.1f} % of the frames"
    )
    clock = truth["clock"]
    cams = truth["cameras"]
    print(
        f"  offset {sync['offset_s']:.6f} s (simulated {clock['offset_s']:.6f}),"
        f" drift {sync['drift_ppm']:.1f} ppm (simulated {clock['drift_ppm']:.1f}),"
        f" confidence {sync['confidence']:.2f}"
    )
    print(
        f"  lost frames found: left {sync['dropped_frames_left']} right"
        f" {sync['dropped_frames_right']} (simulated: left {cams['left']['dropped_after']}"
        f" right {cams['right']['dropped_after']}); time source {sync['time_source']}"
    )
    if analysis.metrics is None:
        print("  no metrics")
        return
    got = analysis.metrics.metrics
    tapping = cases.tapping(name, BENCH_SECONDS)
    even = compute_metrics(
        simulate_tapping(tapping, seed=11).positions_mm[:, :2], tapping.fps
    ).metrics
    amp = 100 * (got["amplitude_mm_mean"] / truth["amplitude_mm_mean"] - 1)
    freq = 100 * (got["frequency_hz"] / truth["frequency_hz"] - 1)
    vo = 100 * (got["opening_velocity_mm_s_max"] / even["opening_velocity_mm_s_max"] - 1)
    vc = 100 * (got["closing_velocity_mm_s_max"] / even["closing_velocity_mm_s_max"] - 1)
    print(
        f"  taps {got['tap_count']} (true {truth['tap_count']}), hesitations"
        f" {got['hesitation_count']} halts {got['halt_count']} (true {len(truth['hesitations'])},"
        f" {len(truth['halts'])}); mean amplitude {amp:+.2f} %, frequency {freq:+.2f} %,"
        f" mean peak opening speed {vo:+.2f} %, closing {vc:+.2f} %"
    )


def _session(out: Path):  # type: ignore[no-untyped-def]
    """The simulated session already in ``out`` (its truth.json names the videos)."""
    import json

    from core.simulation.session import SimulatedSession

    truth = json.loads((out / "truth.json").read_text())
    videos = truth["videos"]
    return SimulatedSession(
        out / videos["left"], out / videos["right"], out / "rig.json", out / "truth.json", truth
    )


def main() -> None:
    import test_free_running as cases

    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--cases", default=",".join(cases.SCENARIOS), help="comma-separated cases")
    ap.add_argument("--keep", type=Path, help="simulate into this folder and reuse it")
    args = ap.parse_args()
    names = [n for n in args.cases.split(",") if n]
    unknown = sorted(set(names) - set(cases.SCENARIOS))
    if unknown:
        raise SystemExit(f"unknown cases {unknown}; choose from {sorted(cases.SCENARIOS)}")

    from core.camera import StereoRig, read_rig
    from core.pipeline import analyze_recording

    with tempfile.TemporaryDirectory() as tmp:
        base = args.keep if args.keep is not None else Path(tmp)
        for name in names:
            out = base / name
            if (out / "truth.json").exists():
                session = _session(out)
                what = "analyze"
                t0 = time.perf_counter()
                analysis = analyze_recording(
                    read_rig(session.rig_path), session.left_video, session.right_video
                )
            else:
                out.mkdir(parents=True, exist_ok=True)
                print(f"simulating {name} into {out} ...", flush=True)
                t0 = time.perf_counter()
                # the simulator's own H.264 (superfast), not the tests' faster preset
                session, analysis = cases._simulate_and_analyze(
                    name, out, encoder_options=(), duration_s=BENCH_SECONDS
                )
                what = "simulate and analyze"
            _report(name, session, analysis, time.perf_counter() - t0, what=what)
            if name == "rolling":
                rig = read_rig(session.rig_path)
                plain = StereoRig(
                    replace(rig.left, readout_ms=0.0), replace(rig.right, readout_ms=0.0)
                )
                t0 = time.perf_counter()
                analysis = analyze_recording(plain, session.left_video, session.right_video)
                seconds = time.perf_counter() - t0
                _report(name, session, analysis, seconds, label="rolling, without readout_ms")
            sys.stdout.flush()


if __name__ == "__main__":
    main()

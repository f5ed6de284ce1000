"""Accuracy, robustness and speed of the tapping metrics on simulated recordings.

Run from the repository root::

    python bench/bench_metrics.py           # about 20 s on one idle core
    python bench/bench_metrics.py --quick   # fewer recordings
    python bench/bench_metrics.py --e2e     # plus videos through core.pipeline (~1 min more)

Ground truth: ``core.simulation.kinematics.simulate_tapping`` (C2 taps whose
aperture is exact, rhythm jitter, decrement, hand drift). Printed figures:

1. Accuracy per fps without and with 0.2 mm white marker noise (per
   coordinate): worst per-tap amplitude error, mean-amplitude, frequency and
   decrement-slope relative errors, mean peak-opening-speed error.
2. Cut-off choice: per-tap peak opening speed error for a 15 Hz and a 20 Hz
   filter, and the amplitude error if extremes were read on the filtered
   signal instead of the raw one (the choice made in core/taps.py).
3. Robustness: recordings with a 0.25-s hesitation and a 0.5-s halt, 1.5 / 3 /
   5 Hz, 60 / 100 / 200 fps, 0.2 mm noise: share with the exact tap count and
   exactly the inserted events; and false events in regular tapping with
   5-15 % rhythm jitter.
4. Speed: ms per second of recording for ``compute_metrics``, with the time of
   merely low-pass filtering the aperture (the baseline) in the same run.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from core.aperture import aperture_signal
from core.metrics import compute_metrics
from core.simulation.kinematics import TappingScenario, simulate_tapping
from core.taps import segment_taps


def _true_peak_speeds(truth) -> np.ndarray:
    t = np.arange(0.0, truth.t_s[-1], 1e-4)
    v = np.gradient(truth.model.aperture_mm(t), t)
    return np.array([v[(t >= k.t_start_s) & (t <= k.t_max_aperture_s)].max() for k in truth.taps])


def accuracy(n_seeds: int) -> None:
    print("1. accuracy (3 Hz, 50 mm, -0.8 mm/tap, 5 % jitter, hesitation + halt)")
    print("   fps  noise  worst-tap-amp-mm  mean-amp-%  freq-%  decrement-%  peak-speed-%")
    for fps in (60.0, 100.0, 200.0):
        for noise in (0.0, 0.2):
            rows = []
            for seed in range(n_seeds):
                truth = simulate_tapping(
                    TappingScenario(
                        fps=fps,
                        decrement_mm_per_tap=-0.8,
                        rhythm_jitter=0.05,
                        hesitations=(8,),
                        halts=((18, 0.5),),
                    ),
                    seed=seed,
                )
                rng = np.random.default_rng(seed)
                pos = truth.positions_mm + rng.normal(0, noise, truth.positions_mm.shape)
                r = compute_metrics(pos, fps)
                m = r.metrics
                amps = np.array([k.amplitude_mm for k in truth.taps])
                if m["tap_count"] != len(amps):
                    rows.append([np.nan] * 5)
                    continue
                got = np.array([k.amplitude_mm for k in r.taps])
                rows.append(
                    [
                        np.abs(got - amps).max(),
                        100 * (m["amplitude_mm_mean"] / amps.mean() - 1),
                        100 * (m["frequency_hz"] / truth.frequency_hz - 1),
                        100
                        * (m["amplitude_decrement_mm_per_tap"] / truth.decrement_mm_per_tap - 1),
                        100
                        * (m["opening_velocity_mm_s_max"] / _true_peak_speeds(truth).mean() - 1),
                    ]
                )
            a = np.array(rows)
            worst = np.nanmax(np.abs(a), axis=0)
            print(
                f"   {fps:4.0f}  {noise:4.1f}   {worst[0]:8.3f}        {worst[1]:6.2f}"
                f"   {worst[2]:6.2f}   {worst[3]:6.2f}       {worst[4]:6.2f}"
                f"   (worst of {len(a)}; miscounted: {int(np.isnan(a[:, 0]).sum())})"
            )


def cutoff_choice() -> None:
    print("2. cut-off: per-tap peak opening speed error, worst |%| and mean %")
    for cutoff in (15.0, 20.0):
        errs, amp_filtered = [], []
        for fps in (60.0, 100.0, 200.0):
            for f_hz, amp in ((1.5, 60.0), (3.0, 50.0), (5.0, 30.0)):
                truth = simulate_tapping(
                    TappingScenario(fps=fps, frequency_hz=f_hz, amplitude_mm=amp, duration_s=8),
                    seed=1,
                )
                ap = aperture_signal(truth.positions_mm, fps, cutoff_hz=cutoff)
                taps = segment_taps(ap)
                if len(taps) != len(truth.taps):
                    continue
                peaks = _true_peak_speeds(truth)
                errs += [
                    t.opening_velocity_mm_s_max / p - 1 for t, p in zip(taps, peaks, strict=True)
                ]
                for t, k in zip(taps, truth.taps, strict=True):
                    i0 = round(k.t_start_s * fps)
                    amp_f = ap.filtered_mm[t.i_max] - ap.filtered_mm[max(i0 - 3, 0) : i0 + 4].min()
                    amp_filtered.append(amp_f - k.amplitude_mm)
        e = 100 * np.array(errs)
        af = np.array(amp_filtered)
        print(
            f"   {cutoff:4.0f} Hz: speed worst {np.abs(e).max():5.2f} %, mean {e.mean():+5.2f} %;"
            f" amplitude read on the filtered signal: mean {af.mean():+.2f} mm,"
            f" worst {np.abs(af).max():.2f} mm (raw reading: see 1.)"
        )


def robustness(n_seeds: int) -> None:
    print("3. robustness, 0.2 mm noise")
    ok = total = 0
    for fps in (60.0, 100.0, 200.0):
        for seed in range(n_seeds):
            for f_hz, amp, dec in ((3.0, 50.0, -0.8), (1.5, 40.0, -1.5), (5.0, 30.0, -0.3)):
                truth = simulate_tapping(
                    TappingScenario(
                        fps=fps,
                        frequency_hz=f_hz,
                        amplitude_mm=amp,
                        decrement_mm_per_tap=dec,
                        rhythm_jitter=0.08,
                        hesitations=(4,),
                        halts=((8, 0.5),),
                        drift_mm=10,
                    ),
                    seed=seed,
                )
                rng = np.random.default_rng(seed + 100)
                r = compute_metrics(
                    truth.positions_mm + rng.normal(0, 0.2, truth.positions_mm.shape), fps
                )
                ev = [(e["kind"], e["tap_index"]) for e in r.events]
                total += 1
                ok += r.metrics["tap_count"] == len(truth.taps) and ev == [
                    ("hesitation", 4),
                    ("halt", 8),
                ]
    print(f"   exact tap count and exactly the inserted events: {ok} of {total} recordings")
    for jitter in (0.05, 0.10, 0.15):
        false = total = 0
        for seed in range(n_seeds * 3):
            for f_hz in (1.5, 3.0, 5.0):
                truth = simulate_tapping(
                    TappingScenario(
                        frequency_hz=f_hz,
                        rhythm_jitter=jitter,
                        amplitude_jitter=0.1,
                        decrement_mm_per_tap=-0.5,
                    ),
                    seed=seed,
                )
                rng = np.random.default_rng(seed)
                r = compute_metrics(
                    truth.positions_mm + rng.normal(0, 0.2, truth.positions_mm.shape), 100.0
                )
                false += r.metrics["hesitation_count"] + r.metrics["halt_count"]
                total += 1
        print(
            f"   regular tapping, {100 * jitter:.0f} % jitter: {false} false events in {total} recordings"
        )


def speed() -> None:
    print("4. speed")
    for fps in (60.0, 200.0):
        truth = simulate_tapping(TappingScenario(duration_s=60.0, fps=fps), seed=0)
        pos = truth.positions_mm
        t0 = time.perf_counter()
        for _ in range(3):
            aperture_signal(pos, fps)
        base = (time.perf_counter() - t0) / 3
        t0 = time.perf_counter()
        for _ in range(3):
            compute_metrics(pos, fps)
        full = (time.perf_counter() - t0) / 3
        print(
            f"   {fps:3.0f} fps, 60 s: compute_metrics {1000 * full / 60:.2f} ms per recorded second;"
            f" aperture filtering alone {1000 * base / 60:.2f} ms/s (ratio {full / base:.1f})"
        )


def end_to_end() -> None:
    """Simulated videos -> core.pipeline.analyze_recording -> metrics, against truth.json."""
    import json
    import tempfile
    from pathlib import Path

    from app.cli import main as cli_main
    from core.camera import read_rig
    from core.pipeline import analyze_recording

    print("5. end to end: bradyscope simulate (6 s, 100 fps, 640x512) -> analyze_recording")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        status = cli_main(
            [
                "simulate",
                "-o",
                str(out),
                "--seed",
                "3",
                "--duration",
                "6",
                "--fps",
                "100",
                "--decrement",
                "-1",
                "--hesitation-taps",
                "5",
                "--halts",
                "11:0.5",
                "--size",
                "640x512",
            ]
        )
        assert status == 0, "bradyscope simulate failed"
        left = next(out.glob("left.*"))
        right = next(out.glob("right.*"))
        doc = analyze_recording(read_rig(out / "rig.json"), left, right).result_document()
        truth = json.loads((out / "truth.json").read_text())
    m = doc["metrics"]
    print(f"   taps {m['tap_count']} (truth {truth['tap_count']})")
    print(f"   frequency {m['frequency_hz']:.4f} Hz (truth {truth['frequency_hz']:.4f})")
    print(
        f"   mean amplitude {m['amplitude_mm_mean']:.3f} mm (truth {truth['amplitude_mm_mean']:.3f})"
    )
    print(
        f"   decrement {m['amplitude_decrement_mm_per_tap']:.4f} mm/tap"
        f" (truth {truth['decrement_mm_per_tap']:.4f})"
    )
    if len(doc["taps"]) == len(truth["taps"]):
        err = max(
            abs(a["amplitude_mm"] - b["amplitude_mm"])
            for a, b in zip(doc["taps"], truth["taps"], strict=True)
        )
        print(f"   worst per-tap amplitude error {err:.3f} mm")
    print(
        f"   events {[(e['kind'], e['tap_index']) for e in doc.get('events', [])]}"
        " (truth: hesitation before tap 5, halt before tap 11)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer recordings")
    parser.add_argument(
        "--e2e", action="store_true", help="also run videos through the pipeline (~1 min)"
    )
    args = parser.parse_args()
    n = 2 if args.quick else 5
    accuracy(n)
    cutoff_choice()
    robustness(n)
    speed()
    if args.e2e:
        end_to_end()


if __name__ == "__main__":
    main()

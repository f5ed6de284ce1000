"""Speed and accuracy of the stereo-session simulator (prints figures; not a test).

Run: ``python bench/bench_simulate.py [--seconds 2] [--size 1280x1024] [--skin 57]``
(``--skin``: with the IR-lit hand of ``core/simulation/hand.py``).

Measures, in one run on the same machine:

1. baseline: encoding pre-rendered noisy frames with FFV1 (both cameras, one
   thread) — the cost of writing a lossless video at all;
2. rendering only (both cameras, no encoding), stereo pairs per second;
3. the full ``simulate_session`` (render + encode in writer threads), lossless
   and mp4v, with the ratio to the baseline;
4. the centroid error of isolated noise-free markers against the projection
   of their 3D centres, over the whole image of both default cameras.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from core.camera import ImageSize
from core.simulation.kinematics import TappingScenario, simulate_tapping
from core.simulation.render import SphereLayer, draw_spheres, intensity_centroid, to_uint8
from core.simulation.rig import default_rig
from core.simulation.session import ImagingScenario, StereoRenderer, simulate_session
from core.video import VideoWriter


def _size(text: str) -> ImageSize:
    w, h = (int(v) for v in text.lower().split("x"))
    return ImageSize(w, h)


def centroid_errors(n: int = 400) -> np.ndarray:
    rig = default_rig()
    rng = np.random.default_rng(0)
    errs = []
    for cam in rig.cameras:
        w, h = cam.image_size
        for _ in range(n // 2):
            px = np.array([[rng.uniform(15, w - 16), rng.uniform(15, h - 16)]])
            centre = cam.backproject_depth(px, rng.uniform(350, 700))[0]
            truth = cam.project(centre[None])[0]
            x0, y0 = int(truth[0]) - 25, int(truth[1]) - 25
            canvas = np.zeros((51, 51), np.float32)
            # Draw into a window by shifting the principal point is not possible with
            # a Camera; draw on a full frame instead (cheap: only a patch is touched).
            full = np.zeros((h, w), np.float32)
            draw_spheres(full, cam, SphereLayer(centre[None, None], 2.5, 230.0))
            canvas = full[max(y0, 0) : y0 + 51, max(x0, 0) : x0 + 51]
            c = intensity_centroid(to_uint8(canvas), x0=max(x0, 0), y0=max(y0, 0))
            errs.append(np.linalg.norm(c - truth))
    return np.asarray(errs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0, help="simulated duration (s)")
    ap.add_argument("--size", type=_size, default=ImageSize(1280, 1024))
    ap.add_argument("--skin", type=float, default=0.0, help="draw the IR-lit hand at this level")
    args = ap.parse_args()
    size = args.size
    fps = 100.0
    tapping = TappingScenario(duration_s=args.seconds, fps=fps)
    imaging = ImagingScenario(
        image_size=size, distractors_static=2, distractors_moving=1, skin_level=args.skin
    )
    rig = default_rig(image_size=size)
    n = round(args.seconds * fps)
    print(
        f"simulator bench: {size.width}x{size.height} at {fps:g} fps, {n} stereo pairs"
        + (f", IR-lit hand (skin {args.skin:g})" if args.skin else "")
    )

    truth = simulate_tapping(tapping, seed=1)
    renderer = StereoRenderer(truth, rig=rig, imaging=imaging, seed=1)
    t0, c0 = time.perf_counter(), time.process_time()
    sample = []
    for j in range(n):
        left, right = renderer.render(j)
        if j < 20:
            sample.append((left, right))
    render = (n / (time.perf_counter() - t0), n / (time.process_time() - c0))

    with tempfile.TemporaryDirectory() as tmp:
        t0, c0 = time.perf_counter(), time.process_time()
        for cam in ("left", "right"):
            with VideoWriter(Path(tmp) / f"{cam}.mkv", fps=fps, image_size=size) as w:
                for j in range(n):
                    w.write(sample[j % len(sample)][0 if cam == "left" else 1])
        encode = (n / (time.perf_counter() - t0), n / (time.process_time() - c0))

    results = {}
    for codec in ("lossless", "mp4v"):
        with tempfile.TemporaryDirectory() as tmp:
            t0, c0 = time.perf_counter(), time.process_time()
            s = simulate_session(
                tmp,
                seed=1,
                tapping=tapping,
                imaging=ImagingScenario(
                    image_size=size,
                    distractors_static=2,
                    distractors_moving=1,
                    codec=codec,
                    skin_level=args.skin,
                ),
                rig=rig,
            )
            speed = (n / (time.perf_counter() - t0), n / (time.process_time() - c0))
            mb = (s.left_video.stat().st_size + s.right_video.stat().st_size) / 1e6
            results[codec] = (speed, mb / n)

    print("stereo pairs per wall-clock second / per CPU-second (the latter is load-independent):")

    def line(label: str, speed: tuple[float, float], extra: str = "") -> None:
        print(
            f"  {label:44s} {speed[0]:6.1f} pairs/s  {speed[1]:6.1f} pairs/CPU-s"
            f"  = {speed[1] / encode[1]:5.2f} x baseline (CPU){extra}"
        )

    line("baseline: FFV1 encoding only, sequential", encode)
    line("render only (both cameras, no encoding)", render)
    for codec, (speed, mb_per_pair) in results.items():
        line(f"simulate_session {codec} (render + encode)", speed, f", {mb_per_pair:.2f} MB/pair")
    errs = centroid_errors()
    print(
        f"centroid error, isolated noise-free 5 mm markers, 8-bit, both cameras, n={len(errs)}:"
        f" median {np.median(errs):.4f} px, max {errs.max():.4f} px"
    )


if __name__ == "__main__":
    main()

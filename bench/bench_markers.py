"""Accuracy and speed of core.markers.detect_markers against ground truth and peers.

Run from the repository root::

    python bench/bench_markers.py            # a few minutes (renders a 3 s simulated trial)
    python bench/bench_markers.py --quick    # fewer frames
    python bench/bench_markers.py --speed-only   # only the speed table (~1 min)

Accuracy: discs rendered at known sub-pixel centres (supersampled, see
``tests/core/test_markers.py::render_discs``), diameters 8-20 px, in five
scenarios; every centre estimator of ``core.markers`` and the plain OpenCV
peer (global threshold + ``cv2.connectedComponentsWithStats`` centroids) are
scored on the same images.  Then markers drawn by ``core.simulation.render``
one effect at a time, and a simulated tapping trial (``StereoRenderer``, both
cameras, distractors, lossless and mp4v, with and without
``estimate_background``).  Errors are Euclidean centre errors (px).

Speed: a 1280x1024 mp4v clip with three moving markers, noise and two glints
is written with ``cv2.VideoWriter`` and decoded with ``cv2.VideoCapture`` (the
baseline, measured in the same run); detection is timed on the decoded frames
(full frame, and windowed around the true positions plus a 2 px prediction
error) and reported in ms/frame and as a ratio to the decode time.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "core"))

from test_markers import mp4v_roundtrip, random_centres, render_discs  # noqa: E402

from core.markers import (  # noqa: E402
    CENTRE_METHODS,
    MarkerParams,
    detect_markers,
    estimate_background,
)

PEER_THRESHOLD = 60  # gray levels: half way between the background (~12) and dim markers


def peer_detect(image: np.ndarray) -> np.ndarray:
    """Plain OpenCV: fixed global threshold, connected components, binary centroids."""
    _, binary = cv2.threshold(image, PEER_THRESHOLD, 255, cv2.THRESH_BINARY)
    _n, _, stats, centroids = cv2.connectedComponentsWithStats(binary, connectivity=8)
    area = stats[1:, cv2.CC_STAT_AREA]
    keep = (area >= 5) & (area <= 1500)
    return centroids[1:][keep]


def add_glints(img: np.ndarray, rng: np.random.Generator, n: int) -> np.ndarray:
    """Distractors: Gaussian glints (small and round), thin line glints, a big glare."""
    out = img.astype(np.float64)
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w]
    for _ in range(n):
        cx, cy = rng.uniform(20, w - 20), rng.uniform(20, h - 20)
        s = rng.uniform(0.8, 1.2)
        out += rng.uniform(60, 150) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    out = np.clip(out, 0, 255).astype(np.uint8)
    for _ in range(n):
        x0, y0 = int(rng.uniform(0, w)), int(rng.uniform(0, h))
        ang = rng.uniform(0, np.pi)
        x1, y1 = int(x0 + 60 * math.cos(ang)), int(y0 + 60 * math.sin(ang))
        cv2.line(out, (x0, y0), (x1, y1), int(rng.uniform(120, 250)), 2)
    cv2.circle(out, (int(rng.uniform(60, w - 60)), int(rng.uniform(60, h - 60))), 35, 255, -1)
    return out


def scenario_frames(
    name: str, n_frames: int, n_markers: int, size: tuple[int, int]
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    truths, frames = [], []
    for i in range(n_frames):
        truth = random_centres(rng, n_markers, size)
        diam = rng.uniform(8, 20, n_markers)
        kw: dict = {"blur_sigma_px": 0.6}
        if name == "noisy":
            kw = {"peak": rng.uniform(80, 200, n_markers), "blur_sigma_px": 0.8, "noise_sigma": 4}
        elif name == "motion blur":
            kw = {"blur_sigma_px": 1.2, "noise_sigma": 2,
                  "streak_xy_px": rng.uniform(-12, 12, (n_markers, 2))}  # fmt: skip
        elif name == "mp4v":
            kw = {"peak": 190, "blur_sigma_px": 0.8, "noise_sigma": 2}
        elif name == "mp4v+blur+noise+glints":
            kw = {"peak": rng.uniform(100, 200, n_markers), "blur_sigma_px": 1.0,
                  "noise_sigma": 3, "streak_xy_px": rng.uniform(-8, 8, (n_markers, 2))}  # fmt: skip
        img = render_discs(size, truth, diam, seed=i, **kw)
        if "glints" in name:
            img = add_glints(img, rng, 4)
        truths.append(truth)
        frames.append(img)
    if name.startswith("mp4v"):
        frames = mp4v_roundtrip(frames)
    return frames, truths


def score(found: list[np.ndarray], truths: list[np.ndarray], tol_px: float = 3.0) -> dict:
    errs, n_true, n_false = [], 0, 0
    for xy, truth in zip(found, truths, strict=True):
        n_true += len(truth)
        if len(xy) == 0:
            continue
        d = np.linalg.norm(xy[None, :, :] - truth[:, None, :], axis=2)
        hit = d.min(axis=1) < tol_px
        errs.extend(d.min(axis=1)[hit].tolist())
        n_false += int(np.sum(d.min(axis=0) >= tol_px))
    e = np.array(errs) if errs else np.array([np.nan])
    return {
        "found": len(errs) / n_true,
        "false": n_false / len(truths),
        "rms": math.sqrt(float(np.mean(e**2))),
        "p95": float(np.percentile(e, 95)),
        "max": float(e.max()),
    }


def accuracy(n_frames: int) -> None:
    size = (640, 512)
    print(f"\n## Accuracy: {n_frames} frames x 24 markers (640x512, d = 8-20 px) per scenario")
    print("error = |found - true| (px), found = share of true markers within 3 px,")
    print("false = detections per frame farther than 3 px from every true marker\n")
    print(f"| {'scenario':24s} | {'method':9s} | found | false/frame | RMS px | P95 px | max px |")
    print("|---|---|---|---|---|---|---|")
    for name in ("clean", "noisy", "motion blur", "mp4v", "mp4v+blur+noise+glints"):
        frames, truths = scenario_frames(name, n_frames, 24, size)
        methods: dict[str, Callable[[np.ndarray], np.ndarray]] = {
            m: (lambda img, m=m: detect_markers(img, params=MarkerParams(centre_method=m)).xy_px)
            for m in CENTRE_METHODS
        }
        methods["peer"] = peer_detect
        for m, fn in methods.items():
            s = score([fn(f) for f in frames], truths)
            print(f"| {name:24s} | {m:9s} | {s['found']:.3f} | {s['false']:.2f} "
                  f"| {s['rms']:.4f} | {s['p95']:.4f} | {s['max']:.4f} |")  # fmt: skip


def accuracy_simulator(n_frames: int) -> None:
    """Markers drawn by core.simulation.render (if present) at known 3D positions."""
    try:
        from core.simulation import render
        from core.simulation.rig import default_rig
    except ImportError:
        print("\n(core.simulation.render not available: simulator scenario skipped)")
        return
    from core.camera import ImageSize
    from core.markers import params_for

    size = ImageSize(1280, 1024)
    cam = default_rig(image_size=size).left
    focal_px = float(cam.K[0, 0])
    print(
        f"\n## Accuracy on core.simulation.render frames: {n_frames} frames x 8 markers, 1280x1024"
    )
    print(f"5 mm spheres at 420-580 mm, f = {focal_px:.0f} px (d ~ 9-12 px), peak 230, psf 0.5 px;")
    print("markers closer than 30 px to another are left out of the score\n")
    print(f"| {'effects':44s} | {'method':9s} | found | RMS px | P95 px | max px |")
    print("|---|---|---|---|---|---|")
    cases: dict[str, dict[str, float]] = {
        "none": {"texture": 0.0, "noise": 0.0, "shot": 0.0, "motion_mm": 0.0},
        "background texture 5": {"texture": 5.0, "noise": 0.0, "shot": 0.0, "motion_mm": 0.0},
        "shot noise (gain 0.025)": {"texture": 0.0, "noise": 0.0, "shot": 0.025, "motion_mm": 0.0},
        "read noise sigma 2": {"texture": 0.0, "noise": 2.0, "shot": 0.0, "motion_mm": 0.0},
        "motion 3.6 mm in the exposure": {
            "texture": 0.0,
            "noise": 0.0,
            "shot": 0.0,
            "motion_mm": 3.6,
        },
        "all (simulator defaults)": {"texture": 5.0, "noise": 2.0, "shot": 0.025, "motion_mm": 3.6},
        "all, background= median of 9 marker-free frames": {
            "texture": 5.0,
            "noise": 2.0,
            "shot": 0.025,
            "motion_mm": 3.6,
            "median_background": 9,
        },
    }
    for label, c in cases.items():
        frames, truths, backgrounds = [], [], []
        for seed in range(n_frames):
            rng = np.random.default_rng(seed)
            centres = np.column_stack((rng.uniform(-80, 80, 8), rng.uniform(-60, 60, 8),
                                       rng.uniform(420, 580, 8)))  # fmt: skip
            steps = np.linspace(-0.5, 0.5, 9)[:, None, None]
            motion = steps * c["motion_mm"] * np.array([[[0.83, -0.55, 0.0]]])
            layer = render.SphereLayer(centres_mm=centres[None] + motion, radius_mm=2.5, peak=230.0)
            canvas = render.make_background(size, rng=rng, texture=c["texture"])
            n_bg = int(c.get("median_background", 0))
            if n_bg:  # what a pipeline can estimate: a per-pixel median of noisy frames
                stack = []
                for _ in range(n_bg):
                    f = canvas.copy()
                    render.SensorNoise(size, sigma=c["noise"], rng=rng).add_to(f)
                    stack.append(render.to_uint8(f))
                backgrounds.append(estimate_background(stack))
            else:
                backgrounds.append(None)
            shot = (rng, c["shot"]) if c["shot"] > 0 else None
            render.draw_spheres(canvas, cam, layer, psf_sigma_px=0.5, shot_noise=shot)
            render.SensorNoise(size, sigma=c["noise"], rng=rng).add_to(canvas)
            truth = cam.project(centres)
            dd = np.linalg.norm(truth[:, None] - truth[None], axis=2) + 1e9 * np.eye(8)
            frames.append(render.to_uint8(canvas))
            truths.append((truth, dd.min(axis=1) > 30))
        for m in CENTRE_METHODS:
            p = params_for(5.0, focal_px, (400.0, 600.0), centre_method=m)
            found = [
                detect_markers(f, params=p, background=b).xy_px
                for f, b in zip(frames, backgrounds, strict=True)
            ]
            s = score([xy for xy in found], [t[ok] for t, ok in truths])
            print(f"| {label:44s} | {m:9s} | {s['found']:.3f} "
                  f"| {s['rms']:.4f} | {s['p95']:.4f} | {s['max']:.4f} |")  # fmt: skip


def accuracy_session(duration_s: float) -> None:
    """Frames of a simulated tapping trial (core.simulation.session.StereoRenderer)."""
    try:
        from core.simulation.kinematics import TappingScenario, simulate_tapping
        from core.simulation.rig import default_rig
        from core.simulation.session import ImagingScenario, StereoRenderer
    except ImportError:
        print("\n(core.simulation.session not available: trial scenario skipped)")
        return
    from core.markers import params_for

    rig = default_rig()
    truth = simulate_tapping(TappingScenario(duration_s=duration_s), seed=4)
    imaging = ImagingScenario(distractors_static=4, distractors_moving=2)
    renderer = StereoRenderer(truth, rig=rig, imaging=imaging, seed=4)
    n = renderer.n_frames
    raw = [renderer.render(j) for j in range(n)]
    truths = {
        c: [cam.project(renderer.model.positions_mm(np.array([renderer.times[c][j]]))[0])
            for j in range(n)]
        for c, cam in (("left", rig.left), ("right", rig.right))
    }  # fmt: skip
    print(f"\n## Accuracy on a simulated trial: {n} frames ({duration_s} s at 100 fps) x 2 cameras")
    print("1280x1024, simulator defaults (texture 5, noise 2, 3 ms exposure) + 4 static and")
    print("2 moving distractors; thumb and index markers; params_for(5 mm, f, (350, 700) mm)\n")
    print("| video | method | found | false/frame | RMS px | P95 px | max px |")
    print("|---|---|---|---|---|---|---|")
    for video in ("lossless", "mp4v"):
        frames = {"left": [p[0] for p in raw], "right": [p[1] for p in raw]}
        if video == "mp4v":
            frames = {c: mp4v_roundtrip(f) for c, f in frames.items()}
        for m in CENTRE_METHODS:
            found, tru = [], []
            for c, cam in (("left", rig.left), ("right", rig.right)):
                p = params_for(5.0, float(cam.K[0, 0]), (350.0, 700.0), centre_method=m)
                found += [detect_markers(f, params=p).xy_px for f in frames[c]]
                tru += truths[c]
            s = score(found, tru)
            print(f"| {video} | {m} | {s['found']:.4f} | {s['false']:.2f} "
                  f"| {s['rms']:.4f} | {s['p95']:.4f} | {s['max']:.4f} |")  # fmt: skip
        for m in ("centroid", "disc_fit"):
            found, tru = [], []
            for c, cam in (("left", rig.left), ("right", rig.right)):
                bg = estimate_background(frames[c][::20])
                p = params_for(5.0, float(cam.K[0, 0]), (350.0, 700.0), centre_method=m)
                found += [detect_markers(f, params=p, background=bg).xy_px for f in frames[c]]
                tru += truths[c]
            s = score(found, tru)
            print(f"| {video} | {m}, background = estimate_background(every 20th frame) "
                  f"| {s['found']:.4f} | {s['false']:.2f} "
                  f"| {s['rms']:.4f} | {s['p95']:.4f} | {s['max']:.4f} |")  # fmt: skip


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    """Best wall-clock and best process-CPU time (s) of ``repeat`` runs after a warm-up.

    On a shared machine the CPU time is the steadier figure (other processes
    do not count); decoding may use several threads, which it sums.
    """
    fn()
    best_wall = best_cpu = math.inf
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        best_wall = min(best_wall, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return best_wall, best_cpu


def speed(n_frames: int) -> None:
    size = (1280, 1024)
    rng = np.random.default_rng(11)
    t = np.arange(n_frames) / 100.0
    base = np.array([[500.0, 400.0], [700.0, 450.0], [620.0, 700.0]])
    truths = [base + 60 * np.column_stack((np.sin(2 * np.pi * 3 * ti + np.arange(3)),
                                          np.cos(2 * np.pi * 2 * ti + np.arange(3))))
              for ti in t]  # fmt: skip
    frames = []
    for i, truth in enumerate(truths):
        img = render_discs(size, truth, 14.0, peak=180, blur_sigma_px=0.8, noise_sigma=2,
                           streak_xy_px=(4.0, 2.0), seed=i)  # fmt: skip
        cv2.circle(img, (200, 150), 2, 160, -1)  # static glints
        cv2.circle(img, (1000, 800), 3, 140, -1)
        frames.append(img)
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "speed.mp4")
        writer = cv2.VideoWriter(path, cv2.VideoWriter.fourcc(*"mp4v"), 100.0, size)
        for f in frames:
            writer.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
        writer.release()

        def decode() -> list[np.ndarray]:
            cap = cv2.VideoCapture(path)
            out = []
            while True:
                ok, frame = cap.read()
                if not ok:
                    break
                out.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
            cap.release()
            return out

        decoded = decode()
        t_decode = tuple(v / len(decoded) for v in timed(decode, 3))
    assert len(decoded) == n_frames
    preds = [tr + rng.uniform(-2, 2, tr.shape) for tr in truths]
    radius = 1.5 * 14 + 12  # px, what the pipeline asks for with 14 px markers

    def run(fn: Callable[[np.ndarray, int], object]) -> tuple[float, ...]:
        wall, cpu = timed(lambda: [fn(f, i) for i, f in enumerate(decoded)], 3)
        return wall / len(decoded), cpu / len(decoded)

    rows = [("decode mp4v 1280x1024 (cv2.VideoCapture + gray)", t_decode)]
    rows.append(
        ("peer: threshold + connectedComponentsWithStats", run(lambda f, i: peer_detect(f)))
    )
    for m in CENTRE_METHODS:
        p = MarkerParams(centre_method=m)
        rows.append((f"detect_markers full frame, {m}",
                     run(lambda f, i, p=p: detect_markers(f, params=p))))  # fmt: skip
        rows.append((f"detect_markers windowed (3 markers), {m}",
                     run(lambda f, i, p=p: detect_markers(f, params=p, search_xy_px=preds[i],
                                                          search_radius_px=radius))))  # fmt: skip
    n_found = np.mean([len(detect_markers(f, search_xy_px=preds[i], search_radius_px=radius))
                       for i, f in enumerate(decoded)])  # fmt: skip
    print(f"\n## Speed: {n_frames}-frame 1280x1024 mp4v clip, 3 moving 14 px markers + 2 glints")
    print(
        f"(best of 3 passes, wall clock and process CPU time; windowed search radius {radius:.0f} px; "
        f"{n_found:.2f} markers found per frame)\n"
    )
    print("| step | wall ms/frame | x decode | CPU ms/frame | x decode |")
    print("|---|---|---|---|---|")
    for label, (wall, cpu) in rows:
        print(f"| {label} | {1e3 * wall:.3f} | {wall / t_decode[0]:.2f} "
              f"| {1e3 * cpu:.3f} | {cpu / t_decode[1]:.2f} |")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    ap.add_argument("--speed-only", action="store_true", help="only the speed table")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f"OpenCV {cv2.__version__}, numpy {np.__version__}, cv2 threads 1")
    if args.speed_only:
        speed(30 if args.quick else 100)
        return
    accuracy(2 if args.quick else 6)
    accuracy_simulator(3 if args.quick else 10)
    accuracy_session(0.3 if args.quick else 3.0)
    speed(30 if args.quick else 100)


if __name__ == "__main__":
    main()

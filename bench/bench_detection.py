"""CPU a frame of the per-frame marker detection, frames in memory, and its output.

Run from the repository root, on a pair kept by ``bench_analyze.py --keep DIR``::

    python bench/bench_detection.py /tmp/speedkeep/session_10s_lab-mp4v
    python bench/bench_detection.py DIR --save /tmp/det.pkl      # keep what it found
    python bench/bench_detection.py DIR --compare /tmp/det.pkl   # the same, to the bit?
    python bench/bench_detection.py DIR --against /path/to/other/checkout

The first ``--frames`` frames of one camera (``--camera left``) are decoded once;
then ``core.markers._CameraDetections.process`` with the default detector (as
``analyze`` runs it: windowed searches, full-frame searches, set-aside blobs,
image patches) goes over them ``--repeat`` times, and the CPU time a frame is
printed (best and median). ``--compare`` checks the frames' detections, the image
patches, the counts and the running diameter against a ``--save``d run, exactly.
``--against`` loads another checkout's ``core/markers.py`` and its built
``core/_blobs`` into this process and alternates the two, pass by pass, so that
both meet the same machine load: the ratio of the pairs is the figure to quote on
a shared machine.
"""

from __future__ import annotations

import argparse
import glob
import importlib.util
import itertools
import pickle
import statistics
import sys
import time
import types
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import core.markers as markers  # noqa: E402
from core.video import iter_frames  # noqa: E402


def _other_markers(tree: Path) -> Any:
    """``core/markers.py`` of another checkout, bound to that checkout's built ``_blobs``."""
    built = glob.glob(str(tree / "core" / "_blobs.cpython*.so"))
    if not built:
        raise SystemExit(
            f"{tree}/core has no built _blobs: run `python setup.py build_ext -i` there"
        )
    spec = importlib.util.spec_from_file_location("core._blobs", built[0])
    assert spec is not None and spec.loader is not None
    blobs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(blobs)
    module = types.ModuleType("other_markers")
    module.__file__ = str(tree / "core" / "markers.py")
    sys.modules["other_markers"] = module  # dataclasses look their module up
    exec(
        compile((tree / "core" / "markers.py").read_text(), module.__file__, "exec"),
        module.__dict__,
    )
    module._blobs = blobs
    return module


def _run(module: Any, frames: list[np.ndarray]) -> tuple[float, Any]:
    state = module._CameraDetections(module._default_detector(None))
    t = time.process_time()
    for image in frames:
        state.process(image)
    return (time.process_time() - t) / len(frames), state


def _found(state: Any) -> dict[str, Any]:
    patches = {
        k: [(p.x0, p.y0, p.pixels, p.points_px, p.detections, p.diameter_px) for p in v]
        for k, v in state.patches.items()
    }
    return {
        "frames": state.frames,
        "patches": patches,
        "counts": (state.n_full, state.n_set_aside),
        "diameter": state.diameter_px,
    }


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return bool(np.shape(a) == np.shape(b) and np.array_equal(a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return bool(a == b)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", type=Path, help="a session kept by bench_analyze.py --keep")
    ap.add_argument("--camera", choices=("left", "right"), default="left")
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--repeat", type=int, default=6)
    ap.add_argument("--save", type=Path)
    ap.add_argument("--compare", type=Path)
    ap.add_argument("--against", type=Path, help="another checkout, alternated with this one")
    args = ap.parse_args()
    video = sorted(args.dir.glob(f"{args.camera}.*"))[0]
    frames = [f.copy() for f in itertools.islice(iter_frames(video, gray=True), args.frames)]
    variants = {"this tree": markers}
    if args.against is not None:
        variants[str(args.against)] = _other_markers(args.against.resolve())
    times: dict[str, list[float]] = {name: [] for name in variants}
    states: dict[str, Any] = {}
    for r in range(args.repeat):
        order = list(variants.items())
        for name, module in order if r % 2 == 0 else order[::-1]:
            seconds, states[name] = _run(module, frames)
            times[name].append(seconds * 1e6)
    print(f"{video}: {len(frames)} frames, {args.repeat} passes")
    for name, t in times.items():
        print(f"  {name}: CPU a frame best {min(t):.1f} us, median {statistics.median(t):.1f} us")
    if args.against is not None:
        pairs = [a / b for a, b in zip(times["this tree"], times[str(args.against)], strict=True)]
        print(f"  this tree / other: median of the pairs {statistics.median(pairs):.3f}")
        same = _same(_found(states["this tree"]), _found(states[str(args.against)]))
        print(f"  the two trees' detections: {'the same' if same else 'DIFFERENT'}")
    found = _found(states["this tree"])
    if args.save is not None:
        args.save.write_bytes(pickle.dumps(found))
    if args.compare is not None:
        same = _same(found, pickle.loads(args.compare.read_bytes()))
        print(
            f"  {'the same detections as' if same else 'DIFFERENT detections from'} {args.compare}"
        )
        if not same:
            raise SystemExit(1)


if __name__ == "__main__":
    main()

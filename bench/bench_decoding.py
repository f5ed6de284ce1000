"""CPU time of reading gray frames, by codec, against PyAV's decoding alone (the floor).

Usage::

    python bench/bench_decoding.py                    # mp4v, h264, av1; 1280x1024, 300 frames
    python bench/bench_decoding.py --codec av1 --frames 500 --repeat 7

For each codec a clip is written (a textured background with a moving bright
square), then read on one decoder thread in the calling thread, as ``analyze``
reads on 2 cores, in alternating runs:

- floor: PyAV's decoder alone, no frame handed out;
- ``iter_frames``: the gray frames the analysis gets (the luma plane, a view
  where it can be: ``core.video._luma_plane``);
- OpenCV's raw luma (codecs OpenCV decodes): what ``iter_frames`` did before
  ca9bacd, a copy of each raw frame;
- swscale's gray (``to_ndarray(format="gray")``): what AV1 got before algorithm
  2026.3, video range stretched to full range.

Prints the median CPU time a frame (ms) of each and its ratio to the floor.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def write_clip(path: Path, codec: str, n: int) -> None:
    from core.camera import ImageSize
    from core.video import VideoWriter

    base = np.random.default_rng(0).integers(30, 80, (1024, 1280)).astype(np.uint8)
    with VideoWriter(path, fps=100.0, image_size=ImageSize(1280, 1024), codec=codec) as w:
        for i in range(n):
            frame = base.copy()
            frame[400:430, 300 + 2 * i % 900 : 330 + 2 * i % 900] = 230
            w.write(frame)


def _pyav(path: Path, convert: Callable[[object], object] | None) -> int:
    import av

    n = 0
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        stream.thread_count = 1
        for frame in container.decode(stream):
            if convert is not None:
                convert(frame)
            n += 1
    return n


def readers(path: Path, opencv_decodes: bool) -> dict[str, Callable[[], int]]:
    import core.video as video

    def read() -> int:
        return sum(1 for _ in video.iter_frames(path, decoder_threads=1, background=False))

    def opencv_raw() -> int:
        real = video._luma_container
        video._luma_container = lambda path: None  # OpenCV's raw frames instead
        try:
            return read()
        finally:
            video._luma_container = real

    out = {
        "floor (decoding alone)": lambda: _pyav(path, None),
        "iter_frames": read,
        "swscale gray": lambda: _pyav(path, lambda f: f.to_ndarray(format="gray")),  # type: ignore[attr-defined]
    }
    if opencv_decodes:
        out["OpenCV raw luma"] = opencv_raw
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--codec", choices=("mp4v", "h264", "av1"), action="append")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=5, help="alternating runs (default 5)")
    args = ap.parse_args()
    from core.video import _opencv_decodes

    with tempfile.TemporaryDirectory() as tmp:
        for codec in args.codec or ["mp4v", "h264", "av1"]:
            path = Path(tmp) / f"clip-{codec}.{'webm' if codec == 'av1' else 'mp4'}"
            write_clip(path, codec, args.frames)
            runs = readers(path, _opencv_decodes(path))
            ms: dict[str, list[float]] = {name: [] for name in runs}
            for _ in range(args.repeat):  # alternating, so that a slow spell hits all
                for name, run in runs.items():
                    t = time.process_time()
                    n = run()
                    ms[name].append((time.process_time() - t) / n * 1000.0)
            floor = float(np.median(ms["floor (decoding alone)"]))
            print(f"{codec} 1280x1024, {args.frames} frames, one decoder thread:")
            for name, values in ms.items():
                med = float(np.median(values))
                print(
                    f"  {name:24s} {med:5.2f} ms CPU a frame (median of {args.repeat};"
                    f" {min(values):.2f}-{max(values):.2f}), {med / floor:4.2f}x the floor"
                )


if __name__ == "__main__":
    main()

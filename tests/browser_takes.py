"""A browser's take, simulated: the WebM files Chromium's recorder writes, for the app
and browser tests (``tests/app/test_browser_take_review.py``, ``tests/browser/``).

Chromium's MediaRecorder writes WebM with 1-ms timestamps and no frame rate; FFmpeg,
and so OpenCV, states 1000 fps for it. The camera's frames come at irregular intervals
(here 3 ms of capture jitter at 30 fps) and some are lost (left: one after each of the
frames 20, 21, 22 and 50; right: one after frame 35).
"""

from __future__ import annotations

import fractions
from collections.abc import Callable
from pathlib import Path
from typing import Any

import av
import numpy as np

from core.camera import ImageSize
from core.simulation.kinematics import TappingScenario
from core.simulation.session import ImagingScenario
from core.simulation.timing import CameraTiming

FPS = 30.0  # Hz, a webcam's
LEFT = CameraTiming(jitter_s=0.003, vfr=True, drop_after=(20, 21, 22, 50))
RIGHT = CameraTiming(start_s=0.011, jitter_s=0.003, vfr=True, drop_after=(35,))


def as_chromium_writes(source: Path, target: Path) -> None:
    """``source``'s packets in a live WebM that states 1000 fps (its 1-ms time base), as
    Chromium's recorder leaves it to FFmpeg to guess."""
    with av.open(str(source)) as src, av.open(str(target), "w", format="webm") as out:
        stream = src.streams.video[0]
        copy = out.add_stream_from_template(stream)
        copy.time_base = fractions.Fraction(1, 1000)
        copy.codec_context.framerate = fractions.Fraction(1000)
        for packet in src.demux(stream):
            if packet.size:
                packet.stream = copy
                out.mux(packet)


def packet_times_s(path: Path) -> np.ndarray:
    """Each frame's presentation time (s) from the file's packets, from the first."""
    with av.open(str(path)) as c:
        stream = c.streams.video[0]
        pts = sorted(p.pts for p in c.demux(stream) if p.size and p.pts is not None)
        t = np.asarray(pts, dtype=np.float64) * float(stream.time_base)
    return t - t[0]


def chromium_take(
    simulated_session: Callable[..., Any], out: Path, *, duration_s: float = 2.5
) -> tuple[Any, dict[str, Path]]:
    """A simulated take (the ``simulated_session`` fixture's) as Chromium writes it: the
    simulation and the two WebM files in ``out`` by side."""
    sim = simulated_session(
        seed=11,
        tapping=TappingScenario(duration_s=duration_s, fps=FPS),
        imaging=ImagingScenario(
            image_size=ImageSize(640, 512), codec="vp8", left_timing=LEFT, right_timing=RIGHT
        ),
    )
    videos = {}
    for side, path in (("left", sim.left_video), ("right", sim.right_video)):
        videos[side] = out / f"{side}.webm"
        as_chromium_writes(path, videos[side])
    return sim, videos

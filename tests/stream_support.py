"""Raw elementary video streams for the tests (imported by tests/core and tests/app).

A raw stream has no container: no frame rate and no timestamps of its own, as some
cameras write it; its timestamps file gives both.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
from numpy.typing import NDArray


def write_raw_h264(
    path: Path,
    frames: Iterable[NDArray[np.uint8]],
    *,
    size: tuple[int, int],
    rate: int,
    options: Mapping[str, str],
) -> int:
    """Gray ``(H, W)`` frames of ``size`` (width, height) as a raw H.264 stream (x264 with
    ``options``, frames numbered from 0 at ``rate``); returns how many were written."""
    import av

    n = 0
    with av.open(str(path), "w", format="h264") as out:
        stream = out.add_stream("libx264", rate=rate)
        stream.width, stream.height = size
        stream.pix_fmt = "yuv420p"
        stream.options = dict(options)
        for image in frames:
            frame = av.VideoFrame.from_ndarray(image, format="gray")
            frame.pts = n
            n += 1
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return n

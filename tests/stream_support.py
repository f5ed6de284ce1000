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


def raw_h264_from_mp4(src: Path, dst: Path) -> int:
    """The H.264 stream of the MP4 ``src`` taken out of its container as it is (Annex B
    start codes, as a camera writes a raw stream): the same frames, no rate and no
    timestamps; returns how many frames were written."""
    import av
    from av.bitstream import BitStreamFilterContext

    n = 0
    with av.open(str(src)) as inp, open(dst, "wb") as out:
        stream = inp.streams.video[0]
        annex_b = BitStreamFilterContext("h264_mp4toannexb", stream)
        for packet in inp.demux(stream):
            for raw in annex_b.filter(None if packet.size == 0 else packet):
                out.write(bytes(raw))
                n += 1
    return n

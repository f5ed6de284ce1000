"""A video damaged in the middle is not called truncated (review of failures, finding 8).

A file whose bytes go on past the frame where decoding stopped is damaged there; one
that ends before that frame's bytes is truncated. Each says so, with the frame.
"""

from __future__ import annotations

from pathlib import Path

import av
import numpy as np
import pytest

from core.camera import ImageSize
from core.errors import InputError
from core.video import VideoWriter, iter_frames, probe_video

SIZE = ImageSize(160, 128)
N = 90  # frames
FPS = 30.0


@pytest.fixture
def whole(tmp_path: Path) -> Path:
    """An MPEG-4 video (index at the end of the file) of a moving dot on noise."""
    rng = np.random.default_rng(5)
    path = tmp_path / "whole.mp4"
    with VideoWriter(path, fps=FPS, image_size=SIZE, codec="mp4v") as writer:
        for i in range(N):
            frame = rng.integers(0, 120, (SIZE.height, SIZE.width), dtype=np.uint8)
            frame[40:60, 10 + i : 30 + i] = 250
            writer.write(frame)
    return path


def _packets(path: Path) -> list[tuple[int, int]]:
    with av.open(str(path)) as container:
        return [(p.pos, p.size) for p in container.demux(video=0) if p.size]


@pytest.mark.parametrize("background", [True, False])
def test_a_video_damaged_in_the_middle_is_said_damaged_not_truncated(
    whole: Path, tmp_path: Path, background: bool
) -> None:
    packets = _packets(whole)
    assert len(packets) == N
    data = bytearray(whole.read_bytes())
    first, last = packets[N // 3][0], packets[2 * N // 3][0]  # the middle third's bytes
    data[first:last] = np.random.default_rng(1).integers(0, 256, last - first, np.uint8).tobytes()
    damaged = tmp_path / "corruptmid_left.mp4"
    damaged.write_bytes(bytes(data))
    info = probe_video(damaged)  # first and last frames decode: the upload's checks pass
    assert info.frame_count == N
    with pytest.raises(InputError) as caught:
        list(iter_frames(damaged, expected_count=N, background=background))
    message = str(caught.value)
    # before: "corruptmid_left.mp4 ends after 30 of 90 frames: the file is truncated"
    assert "truncated" not in message, message
    stopped = int(message.split("after frame ")[1].split(" ")[0])
    assert N // 3 - 3 <= stopped <= 2 * N // 3, message  # frames: where the damage is
    assert message.startswith(f"corruptmid_left.mp4 could not be decoded after frame {stopped}")
    assert f"of {N}: the file is damaged there" in message


def test_a_video_cut_short_is_still_said_truncated(whole: Path, tmp_path: Path) -> None:
    """The same frames in Matroska (no index needed to read it), cut in the middle: the
    file ends before the frames its header announces."""
    mkv = tmp_path / "whole.mkv"
    with av.open(str(whole)) as source, av.open(str(mkv), "w") as out:
        stream = out.add_stream_from_template(source.streams.video[0])
        for packet in source.demux(video=0):
            if packet.size:
                packet.stream = stream
                out.mux(packet)
    packets = _packets(mkv)
    cut = tmp_path / "cut_left.mkv"
    cut.write_bytes(mkv.read_bytes()[: packets[N // 2][0]])
    info = probe_video(cut)
    with pytest.raises(InputError, match=r"ends after \d+ of \d+ frames: the file is truncated"):
        list(iter_frames(cut, expected_count=info.frame_count))

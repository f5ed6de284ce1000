"""Per-frame capture times (core.timing) and what the decoder and the container say about them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.camera import ImageSize
from core.errors import InputError
from core.timing import (
    FROM_CONTAINER,
    FROM_FILE,
    FROM_FPS,
    FrameTimes,
    fit_to_frames,
    frame_times_from_timestamps,
    read_times_csv,
)
from core.video import VideoWriter, iter_frames, probe_video

SIZE = ImageSize(160, 128)


def _frames(n: int) -> list[np.ndarray]:
    out = []
    for k in range(n):
        img = np.full((SIZE.height, SIZE.width), 20, np.uint8)
        img[40:60, 10 + 3 * k : 30 + 3 * k] = 220
        out.append(img)
    return out


def _jittered(n: int, fps: float, *, drop_after: tuple[int, ...] = (), seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fps + rng.normal(0, 0.0004, n)
    for i in drop_after:
        t[i + 1 :] += 1 / fps
    return t - t[0]


def test_constant_timestamps_give_index_over_fps():
    ft = frame_times_from_timestamps(np.arange(50) / 30.0 + 7.0, fps=30.0)
    assert ft.source == FROM_FPS and not ft.variable
    np.testing.assert_allclose(ft.t_s, np.arange(50) / 30.0, atol=1e-12)
    assert ft.dropped_after == []


def test_variable_timestamps_are_kept_and_show_lost_frames():
    t = _jittered(120, 60.0, drop_after=(30, 80, 80))
    ft = frame_times_from_timestamps(t, fps=59.4)
    assert ft.source == FROM_CONTAINER and ft.variable
    np.testing.assert_allclose(ft.t_s, t, atol=1e-12)
    assert ft.dropped_after == [30, 80, 80]
    assert abs(ft.fps - 60.0) < 0.5  # Hz: the median interval, not the container average
    assert ft.gap_after[30] and ft.gap_after[80] and not ft.gap_after[31]


def test_no_timestamps_and_no_frame_rate_is_one_sentence():
    with pytest.raises(InputError, match="neither frame timestamps nor a frame rate"):
        frame_times_from_timestamps([], fps=None, name="left.h264")
    # Timestamps alone are enough; a frame rate alone too.
    assert frame_times_from_timestamps(np.arange(10) / 25, fps=None).fps == pytest.approx(25)
    assert len(frame_times_from_timestamps([np.nan] * 10, fps=25.0)) == 10


def test_frame_times_checks_and_fit():
    with pytest.raises(ValueError, match="increase"):
        FrameTimes(np.array([0.0, 0.1, 0.1]), 10.0)
    ft = FrameTimes(np.array([0.0, 0.1, 0.2]), 10.0, FROM_FILE)
    assert len(fit_to_frames(ft, 2)) == 2
    longer = fit_to_frames(ft, 5)
    np.testing.assert_allclose(longer.t_s, [0, 0.1, 0.2, 0.3, 0.4])


def test_read_times_csv(tmp_path: Path):
    t = _jittered(40, 30.0, drop_after=(10,))
    good = tmp_path / "left_times.csv"
    good.write_text("frame,time_s\n" + "".join(f"{i},{v + 100:.6f}\n" for i, v in enumerate(t)))
    ft = read_times_csv(good, n_frames=40)
    assert ft.source == FROM_FILE and ft.dropped_after == [10]
    np.testing.assert_allclose(ft.t_s, t, atol=2e-6)  # s: 6 decimals in the file
    bad_header = tmp_path / "a.csv"
    bad_header.write_text("i,t\n0,0\n1,0.1\n")
    with pytest.raises(InputError, match="frame,time_s"):
        read_times_csv(bad_header)
    backwards = tmp_path / "b.csv"
    backwards.write_text("frame,time_s\n0,0.0\n1,0.2\n2,0.1\n")
    with pytest.raises(InputError, match="increase"):
        read_times_csv(backwards)
    with pytest.raises(InputError, match="its video has 100"):
        read_times_csv(good, n_frames=100)
    with pytest.raises(InputError, match="cannot read"):
        read_times_csv(tmp_path / "missing.csv")


@pytest.mark.parametrize("codec", ["h264", "vp9"])
def test_decoder_timestamps_agree_with_the_container(tmp_path: Path, codec: str):
    """OpenCV's per-frame CAP_PROP_POS_MSEC (what analyze reads while decoding) is the
    container's presentation timestamp, which PyAV reads without decoding."""
    import av

    t = _jittered(30, 30.0, drop_after=(12,))
    path = tmp_path / f"vfr.{'webm' if codec == 'vp9' else 'mp4'}"
    with VideoWriter(path, fps=30.0, image_size=SIZE, codec=codec) as w:
        for frame, ts in zip(_frames(30), t, strict=True):
            w.write(frame, time_s=float(ts))
    decoded: list[float] = []
    frames = list(iter_frames(path, times_out=decoded))
    assert len(frames) == 30 and len(decoded) == 30
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        pts = sorted(
            float(p.pts * stream.time_base) for p in container.demux(stream) if p.pts is not None
        )
    np.testing.assert_allclose(decoded, pts, atol=1e-6)  # s
    tick = 1e-3 if codec == "vp9" else 1 / 90000  # s: the container's time base
    np.testing.assert_allclose(np.array(decoded) - decoded[0], t, atol=tick)
    ft = frame_times_from_timestamps(decoded, fps=30.0)
    assert ft.source == FROM_CONTAINER and ft.dropped_after == [12]


def test_webm_without_a_frame_count_is_counted(tmp_path: Path):
    path = tmp_path / "browser.webm"
    with VideoWriter(path, fps=30.0, image_size=SIZE, codec="vp8") as w:
        for frame in _frames(25):
            w.write(frame)
    info = probe_video(path)
    assert info.frame_count == 25 and info.has_timestamps
    assert len(list(iter_frames(path, expected_count=info.frame_count))) == 25


def test_raw_stream_without_timestamps_is_refused(tmp_path: Path):
    import av

    path = tmp_path / "left.h264"
    with av.open(str(path), "w", format="h264") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.width, stream.height = SIZE
        stream.pix_fmt = "yuv420p"
        stream.options = {"x264-params": "force-cfr=0"}
        for frame in _frames(10):
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="gray")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    info_or_error: object
    try:
        info_or_error = probe_video(path)
    except InputError as exc:
        info_or_error = exc
    if isinstance(info_or_error, InputError):
        assert "neither frame timestamps nor a frame rate" in str(info_or_error)
        assert str(info_or_error).count(". ") == 0  # one sentence
    else:  # the bitstream states a rate: usable, without timestamps
        assert not info_or_error.has_timestamps  # type: ignore[attr-defined]

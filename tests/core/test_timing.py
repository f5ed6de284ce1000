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
    grid_slots,
    lost_after,
    lost_frame_gaps,
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


PERIOD_S = 0.0337  # s: a browser take's nominal interval (29.7 Hz)


def _take(
    n: int, lost: tuple[int, ...], jitter: float, kind: str, *, seed: int, ppm: float = 300.0
) -> np.ndarray:
    """Capture times (s) of ``n`` frames on a grid of ``PERIOD_S`` (its clock ``ppm`` off),
    a frame lost after each frame in ``lost`` (repeated: several), each frame moved by
    ``jitter`` periods: the standard deviation (``"gauss"``) or the half-width
    (``"uniform"``)."""
    rng = np.random.default_rng(seed)
    slots = np.arange(n) + np.searchsorted(np.sort(lost), np.arange(n), side="left")
    e = rng.normal(0, jitter, n) if kind == "gauss" else rng.uniform(-jitter, jitter, n)
    return (slots + e) * PERIOD_S * (1 + ppm * 1e-6)


def _lost_truth(n: int, seed: int) -> tuple[int, ...]:
    """Six single lost frames and a gap of three, at seeded places."""
    at = np.random.default_rng(1000 + seed).choice(np.arange(5, n - 5), size=7, replace=False)
    return tuple(sorted([*at.tolist(), int(at[0]), int(at[0])]))


def test_a_late_frame_then_an_early_one_is_not_a_lost_frame():
    # A trial's intervals: 53 ms then 14 ms at 33.7 ms; a gap of two periods is one lost.
    steps = [33.7] * 20 + [53.0, 14.4] + [33.7] * 20 + [67.4] + [33.7] * 20  # ms
    t = np.concatenate([[0.0], np.cumsum(steps)]) / 1000
    times = FrameTimes(t, 1 / PERIOD_S, FROM_FILE)
    assert times.dropped_after == [42]
    assert np.flatnonzero(times.gap_after).tolist() == [42]
    np.testing.assert_array_equal(lost_after(t, 1 / PERIOD_S), times.gap_after.astype(int))
    # Three in a row late by 0.6, 0.6 and 0.55 periods, then back on time: none lost.
    late = np.arange(40.0)
    late[10:13] += [0.6, 0.6, 0.55]
    assert FrameTimes(late * PERIOD_S, 1 / PERIOD_S, FROM_FILE).dropped_after == []


@pytest.mark.parametrize(
    ("kind", "jitter", "heavy"),
    [
        ("uniform", 0.10, False),
        ("uniform", 0.25, False),
        ("uniform", 0.40, True),
        ("gauss", 0.10, False),
        ("gauss", 0.15, True),
    ],
)
def test_lost_frames_in_jitter_are_the_true_ones(kind: str, jitter: float, heavy: bool):
    """Ground truth: 300 frames, six single lost frames and a gap of three, every frame
    moved by jitter (uniform up to ±40 % of a period, Gaussian up to σ = 15 %) and a
    clock 300 ppm slow; the fps given is the median interval's, as read from a file.
    Beyond (σ = 20 %: a frame next to a gap moved by over half a period is nearer the
    other slot) the count holds in most takes and a gap may be placed a frame off."""
    false_candidates = 0
    for seed in range(20):
        truth = _lost_truth(300, seed)
        t = _take(300, truth, jitter, kind, seed=seed)
        assert np.all(np.diff(t) > 0)
        times = FrameTimes(t, 1 / float(np.median(np.diff(t))), FROM_FILE)
        assert times.dropped_after == list(truth), seed
        # intervals of 1.5 periods or more that hold no lost frame: late-then-early pairs
        gaps = {i for i, _ in lost_frame_gaps(truth)}
        long = np.flatnonzero(np.diff(t) * times.fps >= 1.5)
        false_candidates += len(set(long.tolist()) - gaps)
    if heavy:  # intervals of 1.5 periods held no lost frame (353 and 47 over the 20 takes)
        assert false_candidates > 20


@pytest.mark.parametrize(("kind", "jitter"), [("uniform", 0.25), ("gauss", 0.15)])
def test_one_lost_frame_in_heavy_jitter_is_found(kind: str, jitter: float):
    for seed in range(20):
        at = 40 + 7 * seed
        t = _take(250, (at,), jitter, kind, seed=seed, ppm=-2000.0)
        times = FrameTimes(t, 1 / float(np.median(np.diff(t))), FROM_FILE)
        assert times.dropped_after == [at], seed


def test_grid_slots_checks_shapes_and_scale():
    assert grid_slots(np.array([]), 30.0).shape == (0,)
    assert grid_slots(np.array([5.0]), 30.0).tolist() == [0]
    with pytest.raises(ValueError, match="fps"):
        grid_slots(np.arange(5) / 30, 0.0)
    t = _take(120, (30, 80, 80), 0.2, "uniform", seed=3)
    slots = grid_slots(t, 1 / PERIOD_S)
    assert slots[0] == 0 and slots[-1] == 122 and np.all(np.diff(slots) >= 1)
    # Convention: the same take in ms at a rate in kHz, or starting at 100 s, has the same slots.
    np.testing.assert_array_equal(grid_slots(t * 1000, 1 / (PERIOD_S * 1000)), slots)
    np.testing.assert_array_equal(grid_slots(t + 100.0, 1 / PERIOD_S), slots)
    # A nominal rate 8 % off (a median interval of jittered times) finds the same grid.
    np.testing.assert_array_equal(grid_slots(t, 1.08 / PERIOD_S), slots)
    np.testing.assert_array_equal(grid_slots(t, 0.92 / PERIOD_S), slots)


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

"""Video probing, streaming decode, writing and stereo-pair checks on real encoded files."""

from __future__ import annotations

import numpy as np
import pytest

from core.camera import Camera, ImageSize, StereoRig
from core.errors import InputError
from core.video import (
    VideoInfo,
    VideoWriter,
    check_stereo_videos,
    decodes_frame,
    iter_frames,
    list_images,
    probe_video,
    proxy_size,
    read_image,
    video_suffix,
    write_proxy,
)

SIZE = ImageSize(320, 240)


def _frames(n: int) -> list[np.ndarray]:
    """Frames with a bright square that moves one pixel per frame, so each frame is identifiable."""
    out = []
    for i in range(n):
        img = np.full((SIZE.height, SIZE.width), 20, np.uint8)
        img[100:120, 10 + i : 30 + i] = 220
        out.append(img)
    return out


def _write(path, frames, codec="lossless", fps=100.0):
    with VideoWriter(path, fps=fps, image_size=SIZE, codec=codec) as w:
        for f in frames:
            w.write(f)
    return path


@pytest.fixture(scope="module")
def lossless(tmp_path_factory):
    path = tmp_path_factory.mktemp("video") / f"clip{video_suffix('lossless')}"
    return _write(path, _frames(40))


# Decoded in a background thread, and in the caller's (core.pipeline on 2 cores).
BOTH_WAYS = pytest.mark.parametrize("background", [True, False], ids=["background", "in-thread"])


@BOTH_WAYS
def test_lossless_round_trip_is_exact(lossless, background):
    info = probe_video(lossless)
    assert info.fps == pytest.approx(100.0)
    assert info.frame_count == 40
    assert info.image_size == SIZE
    frames = list(iter_frames(lossless, expected_count=info.frame_count, background=background))
    assert len(frames) == 40
    for got, want in zip(frames, _frames(40), strict=True):
        assert got.shape == (SIZE.height, SIZE.width) and got.dtype == np.uint8
        np.testing.assert_array_equal(got, want)


@BOTH_WAYS
def test_mp4v_gray_frames_keep_geometry(tmp_path, background):
    path = _write(tmp_path / "clip.mp4", _frames(10), codec="mp4v")
    frames = list(iter_frames(path, background=background))
    assert len(frames) == 10
    # The square's left edge is at column 10 + i; compression may change levels, not positions.
    for i, f in enumerate(frames):
        cols = np.flatnonzero(f[110] > 120)
        assert cols[0] == 10 + i and cols[-1] == 29 + i


@BOTH_WAYS
def test_color_and_range(lossless, background):
    frames = list(iter_frames(lossless, gray=False, start=5, stop=8, background=background))
    assert len(frames) == 3 and frames[0].shape == (SIZE.height, SIZE.width, 3)
    np.testing.assert_array_equal(frames[0][..., 0], _frames(40)[5])


@BOTH_WAYS
def test_early_close_stops_the_decoder(lossless, background):
    import threading

    it = iter_frames(lossless, prefetch=2, background=background)
    next(it)
    readers = [t for t in threading.enumerate() if t.name == f"decode-{lossless.name}"]
    assert len(readers) == (1 if background else 0)  # in-thread: no thread of its own
    it.close()  # must not hang or leak the thread
    assert not any(t.is_alive() for t in readers)
    last = list(iter_frames(lossless, start=39, background=background))
    assert len(last) == 1


@BOTH_WAYS
def test_truncated_lossless_video_is_reported(tmp_path, lossless, background):
    data = lossless.read_bytes()
    cut = tmp_path / f"cut{lossless.suffix}"
    cut.write_bytes(data[: len(data) // 2])
    info = probe_video(cut)  # the header still claims 40 frames (or the file is unreadable)
    with pytest.raises(InputError, match="truncated"):
        list(iter_frames(cut, expected_count=40, background=background))
    assert info.image_size == SIZE


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (b"", "empty"),
        (b"not a video at all" * 100, "could not be opened"),
        (None, "does not exist"),
    ],
)
def test_probe_errors(tmp_path, content, match):
    path = tmp_path / "upload.mp4"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError, match=match):
        probe_video(path)


@pytest.mark.parametrize(("ext", "kind"), [(".png", "PNG"), (".jpg", "JPEG"), (".bmp", "BMP")])
def test_an_image_named_mp4_is_told_to_be_an_image(tmp_path, ext, kind):
    """A photo renamed .mp4 was "reports no frames; the file is corrupt or still being
    written": it is said to be an image, by its first bytes."""
    import cv2

    path = tmp_path / "photo.mp4"
    _, buf = cv2.imencode(ext, _frames(1)[0])
    path.write_bytes(buf.tobytes())
    with pytest.raises(InputError, match=rf"^photo\.mp4 is a {kind} image, not a video"):
        probe_video(path)


def _info(fps=100.0, n=100, size=SIZE) -> VideoInfo:
    from pathlib import Path

    return VideoInfo(Path("x.mkv"), fps, n, size, "FFV1")


def test_check_stereo_videos():
    assert check_stereo_videos(_info(), _info()) == []
    # Different frame rates are measured at the left camera's instants (core.clock).
    assert check_stereo_videos(_info(fps=100), _info(fps=60)) == []
    with pytest.raises(InputError, match="same resolution"):
        check_stereo_videos(_info(), _info(size=ImageSize(240, 320)))
    warnings = check_stereo_videos(_info(n=100), _info(n=98))
    assert len(warnings) == 1 and "different lengths" in warnings[0]
    with pytest.raises(InputError, match="belongs together"):
        check_stereo_videos(_info(n=1000), _info(n=100))
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    rig = StereoRig(Camera("left", ImageSize(640, 480), K), Camera("right", ImageSize(640, 480), K))
    with pytest.raises(InputError, match="calibrated at 640x480"):
        check_stereo_videos(_info(), _info(), rig=rig)


def test_writer_rejects_wrong_frames(tmp_path):
    with VideoWriter(tmp_path / "a.mkv", fps=30, image_size=SIZE) as w:
        with pytest.raises(ValueError, match="shape"):
            w.write(np.zeros((SIZE.width, SIZE.height), np.uint8))  # transposed: (W, H)
    with pytest.raises(ValueError, match="codec"):
        VideoWriter(tmp_path / "a.mkv", fps=30, image_size=SIZE, codec="h265")


def test_writer_encoder_options_reach_the_encoder(tmp_path):
    """Options of a PyAV encoder go over the codec's own: x264's ultrafast preset writes
    Constrained Baseline H.264 where the default (superfast) writes High; an OpenCV codec
    takes none."""
    import av

    for options, profile in ((None, "High"), ({"preset": "ultrafast"}, "Constrained Baseline")):
        path = tmp_path / "clip.mp4"
        with VideoWriter(
            path, fps=30.0, image_size=ImageSize(64, 48), codec="h264", encoder_options=options
        ) as w:
            for i in range(5):
                w.write(np.full((48, 64), 40 + 10 * i, np.uint8))
        with av.open(str(path)) as container:
            assert container.streams.video[0].codec_context.profile == profile
    with pytest.raises(ValueError, match="need a PyAV codec"):
        VideoWriter(
            tmp_path / "x.mp4",
            fps=30.0,
            image_size=ImageSize(64, 48),
            codec="mp4v",
            encoder_options={"preset": "ultrafast"},
        )


def test_images_folder(tmp_path):
    import cv2

    for name in ("b.png", "a.png", "notes.txt"):
        if name.endswith(".png"):
            cv2.imwrite(str(tmp_path / name), _frames(1)[0])
        else:
            (tmp_path / name).write_text("x")
    files = list_images(tmp_path)
    assert [f.name for f in files] == ["a.png", "b.png"]
    assert read_image(files[0]).shape == (SIZE.height, SIZE.width)
    with pytest.raises(InputError, match="holds no image"):
        list_images(_empty(tmp_path))
    (tmp_path / "broken.png").write_bytes(b"garbage")
    with pytest.raises(InputError, match="could not be read"):
        read_image(tmp_path / "broken.png")


def _empty(tmp_path):
    d = tmp_path / "empty"
    d.mkdir()
    return d


@BOTH_WAYS
def test_abandoned_reader_exits_cleanly_and_quietly(tmp_path, background):
    """A script that stops reading early and exits must neither abort nor spam OpenCV warnings."""
    import subprocess
    import sys

    path = _write(tmp_path / "clip.mp4", _frames(60), codec="mp4v")
    script = (
        "from core.video import iter_frames\n"
        f"it = iter_frames({str(path)!r}, prefetch=2, background={background})\n"
        "for i, f in enumerate(it):\n"
        "    if i == 3:\n"
        "        break\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    assert "WARN" not in done.stderr and "FATAL" not in done.stderr


def test_decodes_frame_finds_truncation(tmp_path, lossless):
    assert decodes_frame(lossless, 0) and decodes_frame(lossless, 39)
    data = lossless.read_bytes()
    cut = tmp_path / f"cut{lossless.suffix}"
    cut.write_bytes(data[: len(data) // 2])
    assert not decodes_frame(cut, 39)  # the header still announces 40 frames
    assert not decodes_frame(tmp_path / "missing.mkv", 0)
    with pytest.raises(ValueError, match="index"):
        decodes_frame(lossless, -1)


def test_proxy_is_browser_h264_frame_for_frame_and_leaves_the_original(tmp_path):
    import hashlib

    size = ImageSize(65, 41)  # odd: H.264 4:2:0 needs even sizes
    src = tmp_path / "cam.mkv"
    rng = np.random.default_rng(1)
    frames = [rng.integers(0, 256, (size.height, size.width), dtype=np.uint8) for _ in range(25)]
    for k, f in enumerate(frames):  # a bright square moving one pixel a frame
        f[:] = f // 8
        f[10:20, 10 + k : 20 + k] = 230
    with VideoWriter(src, fps=60.0, image_size=size) as w:
        for f in frames:
            w.write(f)
    before = hashlib.sha256(src.read_bytes()).hexdigest()
    out = tmp_path / "cam.mp4"
    seen: list[int] = []
    assert write_proxy(src, out, progress=seen.append) == 25
    assert seen[-1] == 25
    assert hashlib.sha256(src.read_bytes()).hexdigest() == before  # original untouched
    info = probe_video(out)
    assert info.fourcc == "h264" and info.frame_count == 25 and info.fps == pytest.approx(60.0)
    assert info.image_size == ImageSize(64, 40)  # last column and row dropped, nothing shifted
    data = out.read_bytes()
    assert 0 <= data.find(b"moov") < data.find(b"mdat")  # faststart: the index comes first
    decoded = list(iter_frames(out))
    for k, (a, b) in enumerate(zip(frames, decoded, strict=True)):
        # Luma is stored in video range (16-235), as browsers expect.
        expected = 16 + a[:40, :64].astype(float) * 219 / 255
        square = (slice(12, 18), slice(12 + k, 18 + k))
        assert abs(float(b[square].mean()) - float(expected[square].mean())) < 4  # grey levels
        assert b[:, : 10 + k].mean() < 60  # the square is in its frame's place (frame order)


@pytest.mark.parametrize(
    ("size", "expected"),
    [
        (ImageSize(640, 512), ImageSize(640, 512)),  # the demo's: as it is
        (ImageSize(960, 600), ImageSize(960, 600)),
        (ImageSize(65, 41), ImageSize(64, 40)),
        (ImageSize(1280, 1024), ImageSize(640, 512)),  # lab rig
        (ImageSize(1920, 1080), ImageSize(960, 540)),  # consumer cameras
        (ImageSize(2880, 1000), ImageSize(960, 332)),  # a factor of 3
    ],
)
def test_proxy_size_is_the_video_reduced_by_a_whole_factor(size, expected):
    assert proxy_size(size) == expected


def test_wide_video_proxy_is_reduced_and_keeps_places_and_frames(tmp_path):
    """A 1282x100 video (reduced by 2): the square is at half its coordinates in its frame."""
    size = ImageSize(1282, 100)
    src = tmp_path / "wide.mkv"
    frames = []
    for k in range(12):
        f = np.full((size.height, size.width), 20, np.uint8)
        f[40:60, 600 + 20 * k : 620 + 20 * k] = 230  # 20 px to the right each frame
        frames.append(f)
    with VideoWriter(src, fps=100.0, image_size=size) as w:
        for f in frames:
            w.write(f)
    out = tmp_path / "wide.mp4"
    assert write_proxy(src, out) == 12
    info = probe_video(out)
    assert info.image_size == ImageSize(640, 50) and info.frame_count == 12
    for k, b in enumerate(iter_frames(out)):
        columns = np.flatnonzero(b[20:30].mean(axis=0) > 120)
        # Source columns 600 + 20k .. 619 + 20k are proxy columns 300 + 10k .. 309 + 10k.
        assert columns.min() == pytest.approx(300 + 10 * k, abs=1)  # px
        assert columns.max() == pytest.approx(309 + 10 * k, abs=1)  # px


def test_proxy_of_a_broken_file_is_an_input_error(tmp_path):
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video")
    with pytest.raises(InputError):
        write_proxy(bad, tmp_path / "out.mp4")
    assert not (tmp_path / "out.mp4").exists()


def test_probe_tells_iter_frames_that_opencv_decodes_the_file(tmp_path, monkeypatch):
    """analyze probes each video, reading its first frame through OpenCV, then decodes it:
    the decoding asks no second time whether OpenCV decodes it (an open and a first
    frame: 15 ms for a 1280x1024 MPEG-4 video, 100 ms for 1080p H.264), unless the file
    changed since."""
    import core.video as video

    path = _write(tmp_path / "clip.mp4", _frames(6), codec="mp4v")
    probe_video(path)
    opened: list[str] = []
    real = video.video_capture

    def counting(p, **kw):
        opened.append(str(p))
        return real(p, **kw)

    monkeypatch.setattr(video, "video_capture", counting)
    assert len(list(iter_frames(path, background=False))) == 6
    assert opened == []  # the gray frames came from PyAV's luma plane, unasked
    _write(path, _frames(8), codec="mp4v")  # the same name, another recording
    assert len(list(iter_frames(path, background=False))) == 8
    assert opened == [str(path)]  # asked again for the new file

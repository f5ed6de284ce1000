"""The inputs people have (issue 11): every container and codec cameras, phones and
browsers write is read frame-exactly, with its timestamps, and a phone held upright
is read upright."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core.camera import ImageSize, StereoRig
from core.errors import InputError
from core.timing import FROM_FPS, frame_times_from_timestamps
from core.video import VideoWriter, iter_frames, probe_video

SIZE = ImageSize(320, 192)
FPS = 30.0
N = 12


def _frames() -> list[np.ndarray]:
    """A bright square that moves 2 px right and 1 px down per frame (each frame and
    its orientation identifiable), on a gradient so that lossy codecs have texture."""
    xs = np.linspace(40, 90, SIZE.width)[None, :]
    ys = np.linspace(0, 30, SIZE.height)[:, None]
    out = []
    for i in range(N):
        img = (xs + ys).astype(np.uint8).repeat(1, axis=0)
        img = np.broadcast_to(img, (SIZE.height, SIZE.width)).copy()
        img[20 + i : 44 + i, 30 + 2 * i : 62 + 2 * i] = 230
        out.append(img)
    return out


def _square_centre(img: np.ndarray) -> np.ndarray:
    """``(x, y)`` centre of the bright square (px)."""
    ys, xs = np.nonzero(img > 180)
    return np.array([xs.mean(), ys.mean()])


@pytest.mark.parametrize(
    ("codec", "suffix"),
    [
        ("lossless", ".mkv"),  # FFV1 in Matroska
        ("mjpg", ".avi"),  # MJPEG in AVI (USB webcams)
        ("mp4v", ".mp4"),
        ("h264", ".mp4"),  # cameras, phones
        ("h264", ".mov"),  # iPhones, QuickTime
        ("hevc", ".mp4"),
        ("hevc", ".mov"),
        ("vp8", ".webm"),  # browsers (MediaRecorder)
        ("vp9", ".webm"),
        ("av1", ".webm"),  # newer browsers and phones: decoded by PyAV (OpenCV cannot)
        ("av1", ".mp4"),
    ],
)
def test_container_and_codec_are_read_frame_exactly(tmp_path, codec, suffix):
    frames = _frames()
    path = tmp_path / f"clip{suffix}"
    with VideoWriter(path, fps=FPS, image_size=SIZE, codec=codec) as w:
        for f in frames:
            w.write(f)
    info = probe_video(path)
    assert info.image_size == SIZE and info.rotation_deg == 0
    assert info.fps == pytest.approx(FPS, rel=1e-3)
    assert info.frame_count == N
    times: list[float] = []
    got = list(iter_frames(path, times_out=times, expected_count=info.frame_count))
    assert len(got) == N
    for i, (a, b) in enumerate(zip(got, frames, strict=True)):
        assert a.shape == (SIZE.height, SIZE.width)
        # px: each frame is itself (the square moves 2 px a frame) and in order.
        np.testing.assert_allclose(
            _square_centre(a), _square_centre(b), atol=0.5, err_msg=f"frame {i}"
        )
        # Gray levels: the luma plane is in video range (16-235) for YUV codecs.
        assert abs(float(np.median(a.astype(float) - b))) < 8  # gray levels
    times_fit = frame_times_from_timestamps(times, fps=info.fps, name=path.name)
    assert times_fit.source == FROM_FPS  # constant rate: i / fps
    np.testing.assert_allclose(np.array(times) - times[0], np.arange(N) / FPS, atol=1.1e-3)  # s


@pytest.mark.parametrize(
    ("codec", "suffix", "rotation"),
    [
        ("h264", ".mp4", 90),
        ("h264", ".mp4", 180),
        ("h264", ".mp4", 270),
        ("hevc", ".mov", 90),
        ("av1", ".mp4", 270),  # read through PyAV, turned by its display matrix
    ],
)
def test_a_phone_held_upright_is_read_upright(tmp_path, codec, suffix, rotation):
    """Landscape sensor frames with a display rotation (an MP4/MOV display matrix) are read
    as a player shows them: OpenCV applies the rotation (CAP_PROP_ORIENTATION_AUTO, on the
    luma plane too); PyAV decodes the sensor frames and reports the same rotation."""
    import av

    frames = _frames()
    path = tmp_path / f"upright{suffix}"
    with VideoWriter(path, fps=FPS, image_size=SIZE, codec=codec, rotation_deg=rotation) as w:
        for f in frames:
            w.write(f)
    info = probe_video(path)
    assert info.rotation_deg == rotation
    upright = [np.rot90(f, -rotation // 90) for f in frames]  # clockwise
    assert info.image_size == ImageSize.of_image(upright[0])
    got = list(iter_frames(path))
    assert len(got) == N
    for a, b in zip(got, upright, strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(_square_centre(a), _square_centre(b), atol=0.5)  # px
    # The container itself, read by PyAV: sensor frames and the rotation applied above.
    with av.open(str(path)) as container:
        first = next(container.decode(video=0))
        assert (first.width, first.height) == tuple(SIZE)
        assert (-first.rotation) % 360 == rotation  # FFmpeg counts counter-clockwise
    with pytest.raises(ValueError, match="multiple of 90"):
        VideoWriter(tmp_path / "x.mp4", fps=FPS, image_size=SIZE, codec="h264", rotation_deg=45)


def test_upright_phones_calibrate_in_portrait(tmp_path):
    """Two phones held upright: the rig is calibrated at the upright (portrait) size."""
    import cv2

    from core.boards import BoardSpec
    from core.calibration import calibrate_stereo_from_paths
    from core.simulation.boards import example_rig, write_board_recordings

    portrait = ImageSize(384, 480)
    rig = example_rig(image_size=portrait)
    rig = StereoRig(rig.left, rig.right)
    write_board_recordings(
        rig,
        tmp_path,
        seed=4,
        board="chessboard",
        duration_s=0.8,
        fps=10.0,
        pose_interval_s=0.1,
        as_images=True,
        supersample=2,
    )
    # What each phone stores: landscape sensor frames, 90 degrees clockwise to show.
    for side in ("left", "right"):
        files = sorted((tmp_path / f"chessboard_{side}").glob("*.png"))
        with VideoWriter(
            tmp_path / f"{side}.mp4",
            fps=10.0,
            image_size=ImageSize(portrait.height, portrait.width),
            codec="h264",
            rotation_deg=90,
        ) as w:
            for f in files:
                w.write(np.ascontiguousarray(np.rot90(cv2.imread(str(f), 0), 1)))
    board = BoardSpec.from_dict(json.loads((tmp_path / "chessboard.json").read_text()))
    result = calibrate_stereo_from_paths(tmp_path / "left.mp4", tmp_path / "right.mp4", board)
    assert result.rig.left.image_size == portrait and result.rig.right.image_size == portrait
    assert abs(result.rig.baseline_mm - rig.baseline_mm) < 1.0  # mm, 8 views at 384x480
    assert np.all(np.abs(result.rig.left.K[:2, 2] - rig.left.K[:2, 2]) < 3.0)  # px


def test_frames_found_by_seeking_and_a_codec_named_when_it_cannot_be_read(tmp_path):
    """read_frame (the calibration's quick check, the upload's truncation check) finds a
    frame by seeking, through OpenCV or, for AV1, PyAV; an undecodable stream's error
    names its codec."""
    from core.video import _undecodable_message, decodes_frame, read_frame

    frames = _frames()
    for codec in ("h264", "av1"):
        path = tmp_path / f"seek-{codec}.webm" if codec == "av1" else tmp_path / "seek.mp4"
        with VideoWriter(path, fps=FPS, image_size=SIZE, codec=codec) as w:
            for f in frames:
                w.write(f)
        for i in (0, 5, N - 1):
            got = read_frame(path, i)
            assert got is not None
            np.testing.assert_allclose(_square_centre(got), _square_centre(frames[i]), atol=0.5)
        assert decodes_frame(path, N - 1) and not decodes_frame(path, N + 5)
    message = _undecodable_message(tmp_path / "seek-av1.webm")
    assert "AV1" in message and "H.264" in message


def _write_webm(path, frames, *, live: bool) -> None:
    """VP9 WebM written by PyAV; ``live`` as a browser's MediaRecorder writes it (no
    duration, no frame count: the muxer never seeks back to the header)."""
    import fractions

    import av

    with av.open(str(path), "w", format="webm", options={"live": "1"} if live else {}) as c:
        s = c.add_stream("libvpx-vp9", rate=int(FPS))
        s.width, s.height, s.pix_fmt = SIZE.width, SIZE.height, "yuv420p"
        s.time_base = s.codec_context.time_base = fractions.Fraction(1, 1000)
        for i, f in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(f, format="gray")
            frame.pts, frame.time_base = round(i * 1000 / FPS), s.time_base
            for packet in s.encode(frame):
                c.mux(packet)
        for packet in s.encode():
            c.mux(packet)


@pytest.mark.parametrize("codec", ["lossless", "vp9"])
def test_a_cut_off_matroska_is_found_by_its_stated_duration(tmp_path, codec):
    """Matroska/WebM states no frame count: the packets are counted. A file whose header
    states a duration its packets fall short of by more than two frames was cut off
    (an interrupted copy or upload): its frame count is the one the duration announces,
    so reading it ends early and says so. Cut within the slack, it is taken as it is."""
    import av

    from core.errors import InputError

    rng = np.random.default_rng(5)
    frames = [rng.integers(0, 200, (SIZE.height, SIZE.width), dtype=np.uint8) for _ in range(N)]
    whole = tmp_path / ("whole.mkv" if codec == "lossless" else "whole.webm")
    if codec == "lossless":
        with VideoWriter(whole, fps=FPS, image_size=SIZE, codec=codec) as w:
            for f in frames:
                w.write(f)
    else:
        _write_webm(whole, frames, live=False)
    assert probe_video(whole).frame_count == N
    data = whole.read_bytes()
    with av.open(str(whole)) as c:  # where each frame's block starts in the file
        starts = [p.pos for p in c.demux(video=0) if p.size]
    assert len(starts) == N
    for kept in (N - 3, N - 2):  # cut where frame `kept` starts: 3 (beyond slack), 2 lost
        cut = tmp_path / f"cut{kept}{whole.suffix}"
        cut.write_bytes(data[: starts[kept]])
        info = probe_video(cut)
        if kept == N - 3:
            assert info.frame_count == N  # announced by the stated duration
            with pytest.raises(InputError, match="truncated"):
                list(iter_frames(cut, expected_count=info.frame_count))
        else:
            assert info.frame_count == kept
            assert len(list(iter_frames(cut, expected_count=info.frame_count))) == kept


def test_a_browser_webm_without_duration_is_read_as_its_packets(tmp_path):
    """A WebM recorded live (MediaRecorder) states neither frame count nor duration: its
    frames are counted from the packets and read whole, not taken for a cut-off file."""
    import av

    frames = _frames()
    path = tmp_path / "browser.webm"
    _write_webm(path, frames, live=True)
    with av.open(str(path)) as c:  # what makes it a browser's file
        assert c.duration is None and not c.streams.video[0].frames
    info = probe_video(path)
    assert info.frame_count == N and info.fps == pytest.approx(FPS)
    got = list(iter_frames(path, expected_count=info.frame_count))
    assert len(got) == N
    np.testing.assert_allclose(_square_centre(got[-1]), _square_centre(frames[-1]), atol=0.5)


@pytest.mark.parametrize(("fmt", "encoder"), [("h264", "libx264"), ("mjpeg", "mjpeg")])
def test_a_raw_stream_has_no_frame_rate_unless_its_timestamps_file_gives_one(
    tmp_path, fmt, encoder
):
    """A raw elementary stream (no container) stores no timestamps: FFmpeg's demuxer invents
    them at 25 fps, which is not taken for the camera's rate."""
    import av

    from core.errors import InputError

    path = tmp_path / f"raw.{fmt}"
    with av.open(str(path), "w", format=fmt) as c:
        s = c.add_stream(encoder, rate=int(FPS))
        s.width, s.height = SIZE.width, SIZE.height
        s.pix_fmt = "yuvj420p" if encoder == "mjpeg" else "yuv420p"
        for i, f in enumerate(_frames()):
            frame = av.VideoFrame.from_ndarray(f, format="gray")
            frame.pts = i
            for packet in s.encode(frame):
                c.mux(packet)
        for packet in s.encode():
            c.mux(packet)
    with pytest.raises(InputError, match="neither frame timestamps nor a frame rate"):
        probe_video(path)
    info = probe_video(path, fps_if_none=FPS)
    assert info.fps == FPS and info.frame_count == N and not info.has_timestamps


@pytest.mark.parametrize(("gap_s", "refused"), [(0.7, True), (0.4, False)])
def test_a_browser_take_with_a_hole_is_refused_in_its_own_frames(tmp_path, gap_s, refused):
    """A browser's WebM (1-ms time base; FFmpeg states 1000 fps) whose camera delivered
    nothing for 0.73 s (0.7 s more than a frame interval) is refused naming the stretch and
    the frames it lost at the packets' own 30 fps (it said "732 frames at 1000 fps"); a
    stretch of 0.43 s is lost frames that the time model bridges, and is read."""
    path = tmp_path / "left.webm"
    times = np.arange(60) / FPS  # s
    times[3:] += gap_s
    with VideoWriter(path, fps=1000.0, image_size=SIZE, codec="vp9") as w:
        for i, t in enumerate(times):
            w.write(_frames()[i % N], time_s=float(t))
    if not refused:
        assert probe_video(path).frame_count == 60
        return
    with pytest.raises(InputError) as caught:
        probe_video(path)
    message = str(caught.value)
    assert "no frames between 0.07 s and 0.80 s" in message, message  # s
    assert "about 21 frames missing at its 30 frames per second" in message, message
    assert "record it again" in message, message


@pytest.mark.parametrize(
    ("codec", "suffix"),
    [("lossless", ".mkv"), ("mp4v", ".mp4"), ("h264", ".mp4"), ("av1", ".webm")],
)
def test_one_decoder_thread_reads_the_same_frames_and_times(tmp_path, codec, suffix):
    """Videos decoded side by side get one decoder thread each on 2 cores, in the thread
    that works on their frames (faster there: docs/performance.md); the frames and
    timestamps are those of FFmpeg's own threading in a background thread, to the bit,
    through OpenCV and through PyAV (AV1)."""
    import cv2

    from core.video import video_capture

    path = tmp_path / f"clip{suffix}"
    with VideoWriter(path, fps=FPS, image_size=SIZE, codec=codec) as w:
        for f in _frames():
            w.write(f)
    times_auto: list[float] = []
    auto = list(iter_frames(path, times_out=times_auto))
    assert len(auto) == N
    for background in (True, False):  # the decoder in a thread of its own, or the caller's
        times_one: list[float] = []
        one = list(iter_frames(path, times_out=times_one, decoder_threads=1, background=background))
        assert len(one) == N
        for a, b in zip(auto, one, strict=True):
            np.testing.assert_array_equal(a, b)
        assert times_one == times_auto
    if codec != "av1":
        cap = video_capture(path, threads=1)
        try:
            assert cap.get(cv2.CAP_PROP_N_THREADS) == 1
        finally:
            cap.release()


def test_decoder_threads_share_out_the_cores(monkeypatch):
    import core.video as video

    for cores, n_videos, threads, background in (
        (2, 2, 1, False),
        (1, 2, 1, False),
        (8, 2, 4, True),
        (8, 1, 8, True),
        (3, 2, 1, True),
    ):
        monkeypatch.setattr(video.os, "sched_getaffinity", lambda _pid, c=cores: set(range(c)))
        assert video.decoder_threads_for(n_videos) == threads
        assert video.decode_in_background(n_videos) is background
    for fn in (video.decoder_threads_for, video.decode_in_background):
        with pytest.raises(ValueError, match="n_videos"):
            fn(0)
    with pytest.raises(ValueError, match="decoder_threads"):
        next(iter_frames("unused.mp4", decoder_threads=0))


def _gray_both_ways(monkeypatch, path) -> tuple[list, list, list, list]:
    """Gray frames and times of ``path``: as read (PyAV's luma plane where it has one), and
    OpenCV's raw frames (the luma path switched off); one decoder thread, as analyze on 2
    cores."""
    import core.video as video

    times_read: list[float] = []
    read = list(iter_frames(path, times_out=times_read, decoder_threads=1, background=False))
    with monkeypatch.context() as m:
        m.setattr(video, "_luma_container", lambda path: None)
        times_cv: list[float] = []
        cv = list(iter_frames(path, times_out=times_cv, decoder_threads=1, background=False))
    return read, times_read, cv, times_cv


@pytest.mark.parametrize(
    ("codec", "suffix", "rotation", "width"),
    [
        ("lossless", ".mkv", 0, 320),
        ("mjpg", ".avi", 0, 320),
        ("mp4v", ".mp4", 0, 1280),  # the lab cameras' width
        ("mp4v", ".mp4", 0, 330),  # rows padded by the decoder: copied to be C-contiguous
        ("h264", ".mp4", 0, 1920),  # consumer cameras'
        ("h264", ".mov", 90, 320),  # a phone held upright: turned, so a copy
        ("hevc", ".mp4", 0, 320),
        ("vp8", ".webm", 0, 320),
        ("vp9", ".webm", 270, 320),
    ],
)
def test_gray_frames_are_the_luma_plane_opencv_would_copy(
    tmp_path, monkeypatch, codec, suffix, rotation, width
):
    """Gray frames are views of the luma plane of PyAV's decoder, not OpenCV's copy of each
    raw frame (a sixth of decoding a 1280x1024 MPEG-4 video, docs/performance.md): the
    same pixels and the same timestamps, to the bit; read-only, so that no caller changes
    the picture the decoder refers to for the next frames."""
    import core.video as video

    size = ImageSize(width, SIZE.height)
    path = tmp_path / f"clip{suffix}"
    with VideoWriter(path, fps=FPS, image_size=size, codec=codec, rotation_deg=rotation) as w:
        for f in _frames():
            w.write(np.ascontiguousarray(np.pad(f, ((0, 0), (0, width - SIZE.width)), "edge")))
    opened = video._luma_container(path)
    assert opened is not None  # 8-bit YUV or gray: the luma path
    opened.close()
    read, times_read, cv, times_cv = _gray_both_ways(monkeypatch, path)
    assert len(read) == len(cv) == N
    for a, b in zip(read, cv, strict=True):
        assert a.flags.c_contiguous and a.dtype == np.uint8
        np.testing.assert_array_equal(a, b)
    assert times_read == times_cv
    for a in read:  # a view of the decoder's picture, or a copy of its own
        assert a.flags.writeable == a.flags.owndata
    if width in (1280, 1920) or codec == "lossless":  # rows not padded by these decoders
        assert not read[0].flags.owndata
        with pytest.raises(ValueError, match="read-only"):
            read[0][0, 0] = 0
    if rotation or width == 330:
        assert read[0].flags.owndata


@pytest.mark.parametrize("suffix", [".webm", ".mp4"])
def test_av1_gray_frames_are_its_luma_plane_as_every_codecs(tmp_path, suffix):
    """AV1, which OpenCV cannot decode, is read by PyAV: its gray frames are the luma plane
    in video range, as every other codec's. Before algorithm 2026.3 they were swscale's
    gray, which stretches video range to full range: a marker brighter against its
    background by ~17 gray levels than in the same scene recorded in H.264."""
    import av

    frames = _frames()
    path = tmp_path / f"clip{suffix}"
    same_in_h264 = tmp_path / "clip-h264.mp4"
    for p, codec in ((path, "av1"), (same_in_h264, "h264")):
        with VideoWriter(p, fps=FPS, image_size=SIZE, codec=codec) as w:
            for f in frames:
                w.write(f)
    with av.open(str(path)) as container:
        planes = []
        for frame in container.decode(video=0):
            plane = frame.planes[0]
            rows = np.frombuffer(plane, np.uint8, count=plane.line_size * frame.height)
            planes.append(rows.reshape(frame.height, plane.line_size)[:, : frame.width])
    read = list(iter_frames(path))
    assert len(read) == len(planes) == N
    for a, b in zip(read, planes, strict=True):
        np.testing.assert_array_equal(a, b)
    h264 = next(iter(iter_frames(same_in_h264)))
    square = frames[0] == 230
    for part in (square, ~square):  # the marker and its background, in gray levels
        assert abs(float(np.median(read[0][part])) - float(np.median(h264[part]))) <= 3


def test_a_frame_that_cannot_be_converted_is_reported_not_taken_for_the_end(tmp_path, monkeypatch):
    """A frame PyAV decodes but cannot convert stops the reading with an error that names
    the frame and what to do, not silently, as if the video had ended there."""
    import av

    import core.video as video

    path = tmp_path / "clip.webm"
    with VideoWriter(path, fps=FPS, image_size=SIZE, codec="av1") as w:
        for f in _frames():
            w.write(f)
    real = video._luma_plane
    seen = []

    def failing(frame):
        seen.append(frame)
        if len(seen) == 5:
            raise av.FFmpegError(22, "Invalid argument")
        return real(frame)

    monkeypatch.setattr(video, "_luma_plane", failing)
    with pytest.raises(InputError, match=r"frame 4 of clip\.webm .*re-encode"):
        list(iter_frames(path, background=False))


def test_timestamps_from_a_late_start_are_opencvs(tmp_path, monkeypatch):
    """A camera's file whose first frame is stamped 1.5 s (variable frame rate): the times
    are counted from the stream's start as OpenCV counts them, to the bit."""
    path = tmp_path / "late.mp4"
    stamps = 1.5 + np.arange(N) / FPS + np.random.default_rng(3).uniform(0, 0.004, N)
    with VideoWriter(path, fps=FPS, image_size=SIZE, codec="h264") as w:
        for f, t in zip(_frames(), stamps, strict=True):
            w.write(f, time_s=float(t))
    read, times_read, cv, times_cv = _gray_both_ways(monkeypatch, path)
    assert times_read == times_cv and len(times_read) == N
    np.testing.assert_allclose(np.diff(times_read), np.diff(stamps), atol=2e-5)  # s
    for a, b in zip(read, cv, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    ("codec", "pix_fmt", "suffix"),
    [
        ("mjpeg", "yuvj420p", ".avi"),
        ("mjpeg", "yuvj422p", ".avi"),
        ("mjpeg", "yuvj444p", ".avi"),
        ("ffv1", "gray", ".mkv"),
        ("ffv1", "yuv420p", ".mkv"),
        ("libx264", "yuv422p", ".mp4"),
        ("libx264", "yuv444p", ".mp4"),
        ("rawvideo", "nv12", ".avi"),
        ("rawvideo", "nv21", ".avi"),
        ("libx264", "yuv420p10le", ".mp4"),  # 16 bits a sample: OpenCV's BGR, then gray
        ("ffv1", "gray16le", ".mkv"),
        ("ffv1", "bgr0", ".mkv"),
    ],
)
def test_the_luma_formats_are_those_opencv_hands_out_raw(
    tmp_path, monkeypatch, codec, pix_fmt, suffix
):
    """``_LUMA_FIRST_PIX_FMTS`` (FFmpeg's names) holds exactly the formats whose raw frames
    OpenCV names by a luma-first code; the others are read as before, through OpenCV."""
    import av
    import cv2

    import core.video as video

    path = tmp_path / f"clip{suffix}"
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=int(FPS))
        stream.width, stream.height, stream.pix_fmt = SIZE.width, SIZE.height, pix_fmt
        for f in _frames():
            frame = av.VideoFrame.from_ndarray(np.dstack([f, f, f]), format="bgr24")
            for packet in stream.encode(frame.reformat(format=pix_fmt)):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        code = video._fourcc_to_str(cap.get(cv2.CAP_PROP_CODEC_PIXEL_FORMAT))
    finally:
        cap.release()
    luma = pix_fmt in video._LUMA_FIRST_PIX_FMTS
    assert (code in video._LUMA_FIRST_FORMATS) == luma, code
    opened = video._luma_container(path)
    assert (opened is not None) == luma
    if opened is not None:
        opened.close()
    read, times_read, cv, times_cv = _gray_both_ways(monkeypatch, path)
    assert len(read) == len(cv) == N and times_read == times_cv
    for a, b in zip(read, cv, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_damaged_video_ends_where_opencv_ends_it(tmp_path, monkeypatch):
    """A packet in the middle of an MPEG-4 file overwritten: the decoder refuses it, and the
    luma path stops at the same frame as OpenCV, with the same frames before it
    (iter_frames' expected_count then reports the file cut short)."""
    import av

    path = tmp_path / "clip.mp4"
    with VideoWriter(path, fps=FPS, image_size=SIZE, codec="mp4v") as w:
        for f in _frames() * 4:
            w.write(f)
    with av.open(str(path)) as container:
        packets = [(p.pos, p.size) for p in container.demux(video=0) if p.size]
    assert len(packets) == 4 * N
    pos, size = packets[2 * N]
    data = bytearray(path.read_bytes())
    data[pos : pos + size] = np.random.default_rng(1).integers(0, 256, size, np.uint8).tobytes()
    path.write_bytes(bytes(data))
    read, times_read, cv, times_cv = _gray_both_ways(monkeypatch, path)
    assert len(read) == len(cv) == 2 * N
    assert times_read == times_cv
    for a, b in zip(read, cv, strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(InputError, match="the file is damaged there"):
        list(iter_frames(path, expected_count=4 * N, background=False))


def _realtime_thread_ids() -> list[int]:
    """Read here, not through core.video's own helper, so that the test does not trust it."""
    import os

    found = []
    for tid in os.listdir("/proc/self/task"):
        try:
            if os.sched_getscheduler(int(tid)) in (os.SCHED_FIFO, os.SCHED_RR):
                found.append(int(tid))
        except ProcessLookupError:  # another test's thread that ended meanwhile
            continue
    return found


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="Linux's thread list")
def test_writing_av1_leaves_no_thread_real_time(tmp_path):
    """SVT-AV1 switches the thread that opens it to SCHED_FIFO at the highest priority where
    it may (as root), and its threads inherit that: a test process that wrote AV1 once then
    ran real-time, and with busy-waiting code beside it stopped the machine's other work.
    The writer puts the threads back under the normal policy."""
    assert _realtime_thread_ids() == []
    with VideoWriter(tmp_path / "a.webm", fps=FPS, image_size=SIZE, codec="av1") as w:
        for k in range(3):
            w.write(np.full((SIZE.height, SIZE.width), 40 * k, np.uint8))
        assert _realtime_thread_ids() == []  # the encoder's own threads too
    assert _realtime_thread_ids() == []

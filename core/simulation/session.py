"""A simulated stereo recording of the finger-tapping test: two videos, rig.json, truth.json.

Timing conventions (INTERFACES.md):

- Frame ``i`` of the left video is at ``t = i / fps``; its exposure is centred
  on that instant.
- With ``offset_frames = K``, right frame ``j`` shows the same instant as left
  frame ``j + K``: it is exposed around ``t = (j + K) / fps``. ``K`` may be
  fractional (unsynchronised cameras) or negative.
- Both videos have the same number of frames; the truth is sampled at the
  left frames.

Free-running cameras (``ImagingScenario.left_timing`` / ``right_timing``,
:mod:`core.simulation.timing`) change this: each camera has its own frame
rate, start, clock drift, lost frames, jitter, timestamps and rolling
shutter; the truth is then sampled at the left frames' true capture times.
"""

from __future__ import annotations

import json
import queue
import threading
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from core.camera import Camera, FloatArray, ImageSize, StereoRig, write_rig
from core.errors import InputError
from core.progress import ProgressCallback, report
from core.simulation.hand import SkinLook, composite_spheres, draw_skin, nail_glints, tapping_hand
from core.simulation.kinematics import (
    TappingModel,
    TappingScenario,
    TappingTruth,
    simulate_tapping,
)
from core.simulation.render import (
    DISC,
    GLINT,
    Patch,
    SensorNoise,
    SphereLayer,
    add_patches,
    draw_spheres,
    make_background,
    sphere_patches,
    to_uint8,
)
from core.simulation.rig import default_rig
from core.simulation.tasks import TaskModel, TaskScenario, TaskTruth, rig_geometry, simulate_task
from core.simulation.timing import CameraClock, CameraTiming, camera_clock, rolling_shutter_times
from core.tasks import Task
from core.video import VideoWriter, video_suffix

TRUTH_FORMAT = "bradyscope.truth/1"
TrialTruth = TappingTruth | TaskTruth
"""The ground truth of a finger-tapping trial or of another task's (core.simulation.tasks)."""
MotionModel = TappingModel | TaskModel
CAMERA_NAMES = ("left", "right")
_MAX_BLUR_SAMPLES = 16
_BLUR_SAMPLE_SPACING_PX = 0.5
_SHOT_NOISE_GAIN = 0.025  # gray levels per electron: sigma = sqrt(0.025 * signal)


@dataclass(frozen=True)
class ImagingScenario:
    """How the two cameras see the scene.

    Attributes
    ----------
    image_size : ImageSize
        ``(width, height)`` of both videos.
    marker_diameter_mm : float
        Diameter of the retro-reflective marker spheres (mm).
    marker_peak : float
        Brightness of a marker's centre above the background (gray levels).
    noise_sigma : float
        Standard deviation of the sensor's read noise (gray levels); shot
        noise on the markers comes on top.
    exposure_s : float
        Exposure time (s), centred on the frame time; 0 = no motion blur.
    distractors_static : int
        Number of static spurious reflections (fixed points of the room, seen
        by both cameras).
    distractors_moving : int
        Number of moving glints fixed to the back of the hand or the wrist
        (a ring, a watch): they follow the hand's slow drift and wobble on
        their own, twinkling; they do not follow the tapping.
    occlusions : tuple of (camera, marker, t_start_s, duration_s)
        The marker is invisible in that camera (``"left"`` or ``"right"``)
        for frames exposed at ``t_start_s <= t < t_start_s + duration_s``
        (times on the left camera's clock).
    offset_frames : float
        ``K``: right frame ``j`` shows the instant of left frame ``j + K``.
    codec : {"lossless", "mp4v"}
        ``"lossless"`` (FFV1 in .mkv) keeps every pixel; ``"mp4v"`` (.mp4)
        adds compression artefacts.
    background_level, background_texture : float
        Mean gray level of the dark background and the amplitude of its texture.
    psf_sigma_px : float
        Lens blur (px).
    skin_level : float
        Gray level of skin that faces the camera at 500 mm under the ring
        light; > 0 draws the IR-lit hand of :mod:`core.simulation.hand`
        (fingers, back of the hand, forearm; shaded, with soft edges; the
        markers sit on the nails and are hidden where skin is in front of
        them). 0 (default) leaves the hand out. ``docs/simulator.md`` gives
        the brightness ratios and their sources (about 0.25 x
        ``marker_peak`` is a bright, pessimistic case).
    nail_glint_peak : float
        Peak gray level of the nail-polish highlights beside the thumb and
        index markers (only with the hand); 0 (default): matt nails.
    left_timing, right_timing : CameraTiming
        Free-running cameras (frame rate, start, drift, lost frames, jitter,
        variable-frame-rate timestamps, rolling shutter, image size); the
        default is a genlocked camera at the scenario's rate and size.
        ``right_timing.start_s`` and ``offset_frames`` are exclusive.
    encoder_options : tuple of (name, value)
        FFmpeg options of a PyAV codec's encoder over the simulator's own
        (:class:`core.video.VideoWriter`), for example
        ``(("preset", "ultrafast"),)``: H.264 at about 16 Mbit/s for 1920x1080
        at 60 fps, a phone's rate, with 2.6 times less CPU for simulating and
        measuring than the default (``superfast``, about 50 Mbit/s: the
        simulated sensor noise kept).
    """

    image_size: ImageSize = ImageSize(1280, 1024)  # noqa: RUF009 (immutable NamedTuple)
    marker_diameter_mm: float = 5.0
    marker_peak: float = 230.0
    noise_sigma: float = 2.0
    exposure_s: float = 0.003
    distractors_static: int = 0
    distractors_moving: int = 0
    occlusions: tuple[tuple[str, str, float, float], ...] = ()
    offset_frames: float = 0.0
    codec: str = "lossless"
    background_level: float = 14.0
    background_texture: float = 5.0
    psf_sigma_px: float = 0.5
    skin_level: float = 0.0
    nail_glint_peak: float = 0.0
    left_timing: CameraTiming = CameraTiming()  # noqa: RUF009 (frozen)
    right_timing: CameraTiming = CameraTiming()  # noqa: RUF009 (frozen)
    encoder_options: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "image_size", ImageSize(*(int(v) for v in self.image_size)))
        object.__setattr__(
            self,
            "occlusions",
            tuple((str(c), str(m), float(t0), float(d)) for c, m, t0, d in self.occlusions),
        )
        if self.image_size.width < 16 or self.image_size.height < 16:
            raise ValueError(f"image_size must be at least 16 x 16 px, got {self.image_size}")
        if not 0 < self.marker_diameter_mm <= 30:
            raise ValueError(
                f"marker_diameter_mm must be in (0, 30], got {self.marker_diameter_mm}"
            )
        if not 0 < self.marker_peak <= 255:
            raise ValueError(f"marker_peak must be in (0, 255], got {self.marker_peak}")
        if not 0 <= self.noise_sigma <= 50:
            raise ValueError(f"noise_sigma must be in [0, 50], got {self.noise_sigma}")
        if not 0 <= self.exposure_s <= 0.1:
            raise ValueError(f"exposure_s must be in [0, 0.1], got {self.exposure_s}")
        if self.distractors_static < 0 or self.distractors_moving < 0:
            raise ValueError("distractor counts must be >= 0")
        for cam, _, _, dur in self.occlusions:
            if cam not in CAMERA_NAMES:
                raise ValueError(f"occlusion camera must be 'left' or 'right', got {cam!r}")
            if not dur > 0:
                raise ValueError(f"occlusion duration must be positive, got {dur}")
        if not np.isfinite(self.offset_frames):
            raise ValueError(f"offset_frames must be finite, got {self.offset_frames}")
        video_suffix(self.codec)  # raises ValueError for an unknown codec
        if not 0 <= self.skin_level <= 200:
            raise ValueError(f"skin_level must be in [0, 200], got {self.skin_level}")
        if not 0 <= self.nail_glint_peak <= 255:
            raise ValueError(f"nail_glint_peak must be in [0, 255], got {self.nail_glint_peak}")
        if not 0 <= self.psf_sigma_px <= 5:
            raise ValueError(f"psf_sigma_px must be in [0, 5], got {self.psf_sigma_px}")
        if self.offset_frames != 0 and self.right_timing.start_s != 0:
            raise ValueError(
                "give the right camera's start as offset_frames or as start_s, not both"
            )
        if self.left_timing.start_s != 0 or self.left_timing.drift_ppm != 0:
            raise ValueError("the left camera is the reference clock: its start_s and drift are 0")
        if (self.left_timing.vfr or self.right_timing.vfr) and self.codec not in (
            "h264", "hevc", "vp9", "vp8",
        ):  # fmt: skip
            raise ValueError(
                "variable-frame-rate timestamps need a codec that stores them (h264, hevc, vp9, vp8)"
            )

    def camera_size(self, camera: str) -> ImageSize:
        """The image size of ``"left"`` or ``"right"``."""
        timing = self.left_timing if camera == "left" else self.right_timing
        return self.image_size if timing.image_size is None else timing.image_size


@dataclass(frozen=True)
class SimulatedSession:
    """Paths of a simulated recording and its ground truth (the parsed ``truth.json``)."""

    left_video: Path
    right_video: Path
    rig_path: Path
    truth_path: Path
    truth: dict[str, Any] = field(repr=False)


@dataclass(frozen=True)
class _StaticDistractor:
    position_mm: FloatArray  # (3,)
    radius_mm: float
    peak: float
    profile: str


@dataclass(frozen=True)
class _MovingDistractor:
    local_mm: FloatArray  # (3,) hand frame
    radius_mm: float
    peak: float
    wobble_amp_mm: FloatArray  # (3,)
    wobble_hz: FloatArray  # (3,)
    wobble_phase: FloatArray  # (3,)
    twinkle_hz: float
    twinkle_phase: float

    def positions_mm(self, model: MotionModel, t_s: FloatArray) -> FloatArray:
        """World positions ``(N, 3)``."""
        base = model.hand_points_mm(t_s, self.local_mm[None])[:, 0]
        wobble = self.wobble_amp_mm * np.sin(
            2 * np.pi * self.wobble_hz * t_s[:, None] + self.wobble_phase
        )
        return base + wobble

    def brightness(self, t_s: FloatArray) -> FloatArray:
        """Peak gray level ``(N,)``: a glint that comes and goes as the hand turns."""
        s = np.sin(2 * np.pi * self.twinkle_hz * t_s + self.twinkle_phase)
        return self.peak * np.clip(0.5 + 1.2 * s, 0.0, 1.0)


class _ThreadedWriter:
    """A :class:`VideoWriter` fed through a small queue so encoding overlaps rendering."""

    def __init__(self, writer: VideoWriter) -> None:
        self._writer = writer
        self._queue: queue.Queue[tuple[NDArray[np.uint8], float | None] | None] = queue.Queue(
            maxsize=4
        )
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"write-{writer.path.name}")
        self._thread.daemon = True
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self._error is None:
                try:
                    self._writer.write(item[0], time_s=item[1])
                except BaseException as exc:  # re-raised in the caller's thread
                    self._error = exc

    def write(self, frame: NDArray[np.uint8], *, time_s: float | None = None) -> None:
        if self._error is not None:
            raise self._error
        self._queue.put((frame, time_s))

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join()
        self._writer.close()
        if self._error is not None:
            raise self._error


def _choose_static(
    n: int, rig: StereoRig, marker_px: list[FloatArray], rng: np.random.Generator
) -> list[_StaticDistractor]:
    """Static reflections in the room behind the hand, visible to both cameras, off the markers' paths."""
    out: list[_StaticDistractor] = []
    for k in range(n):
        best = None
        for _ in range(200):
            z = rng.uniform(650.0, 1100.0)
            # Within the left camera's field of view (world frame = left camera frame).
            p = np.array([rng.uniform(-0.45, 0.45) * z, rng.uniform(-0.35, 0.35) * z, z])
            ok = True
            for cam, mpx in zip(rig.cameras, marker_px, strict=True):
                q = cam.project(p[None])[0]
                if not cam.in_image(q[None], margin_px=15)[0]:
                    ok = False
                    break
                if np.min(np.linalg.norm(mpx - q, axis=1)) < 30.0:  # px from any marker position
                    ok = False
                    break
            best = p
            if ok:
                break
        assert best is not None
        out.append(
            _StaticDistractor(
                position_mm=best,
                radius_mm=float(rng.uniform(1.0, 2.5)),
                peak=float(rng.uniform(90.0, 230.0)),
                profile=DISC if k % 2 == 0 else GLINT,
            )
        )
    return out


# Candidate anchor points in the hand frame (mm) for rings and watch glints:
# the back of the hand and the wrist, away from the tapping fingertips.
_MOVING_ANCHORS_MM = np.array(
    [
        [-120.0, -35.0, 25.0],  # watch on the back of the wrist
        [-70.0, -45.0, 18.0],  # back of the hand
        [0.0, -30.0, 8.0],  # ring on the middle finger's base
        [-100.0, -5.0, 20.0],  # wrist, thumb side
    ]
)


def _choose_moving(n: int, rng: np.random.Generator) -> list[_MovingDistractor]:
    out = []
    for k in range(n):
        anchor = _MOVING_ANCHORS_MM[k % len(_MOVING_ANCHORS_MM)] + rng.uniform(-8, 8, 3)
        out.append(
            _MovingDistractor(
                local_mm=anchor,
                radius_mm=float(rng.uniform(0.8, 1.6)),
                peak=float(rng.uniform(150.0, 250.0)),
                wobble_amp_mm=rng.uniform(1.0, 4.0, 3),
                wobble_hz=rng.uniform(0.4, 1.3, 3),
                wobble_phase=rng.uniform(0, 2 * np.pi, 3),
                twinkle_hz=float(rng.uniform(0.15, 0.6)),
                twinkle_phase=float(rng.uniform(0, 2 * np.pi)),
            )
        )
    return out


def _blur_samples(
    model: MotionModel,
    camera_times: FloatArray,
    exposure_s: float,
    focal_px: float,
) -> NDArray[np.int64]:
    """Sub-samples per frame so that a marker moves <= 0.5 px between them."""
    if exposure_s <= 0:
        return np.ones(len(camera_times), dtype=np.int64)
    a = model.positions_mm(camera_times - exposure_s / 2)
    b = model.positions_mm(camera_times + exposure_s / 2)
    z = np.maximum(np.minimum(a[..., 2], b[..., 2]), 50.0)
    disp_px = np.max(np.linalg.norm(b - a, axis=2) * focal_px / z, axis=1)
    n = np.ceil(disp_px / _BLUR_SAMPLE_SPACING_PX).astype(np.int64) + 1
    result: NDArray[np.int64] = np.clip(n, 1, _MAX_BLUR_SAMPLES)
    return result


def camera_clocks(truth: TrialTruth, imaging: ImagingScenario, seed: int) -> dict[str, CameraClock]:
    """When each camera captures its frames (:mod:`core.simulation.timing`).

    ``offset_frames`` is the right camera's start in frames of the scenario's rate.
    """
    duration_s = len(truth.t_s) / truth.fps
    right = imaging.right_timing
    if imaging.offset_frames != 0:
        right = replace(right, start_s=float(imaging.offset_frames) / truth.fps)
    timings = {"left": imaging.left_timing, "right": right}
    return {
        c: camera_clock(
            timings[c],
            fps=truth.fps,
            duration_s=duration_s,
            rng=np.random.default_rng([int(seed), 0x7133, i]),
        )
        for i, c in enumerate(CAMERA_NAMES)
    }


class StereoRenderer:
    """Renders the stereo frames of a simulated trial, one pair at a time (bounded memory).

    Frames must be rendered in order (``render(0)``, ``render(1)``, ...): the
    sensor noise comes from sequential random streams, which is what makes a
    session reproducible from its seed.

    Parameters
    ----------
    truth : TappingTruth or TaskTruth
    rig : StereoRig
    imaging : ImagingScenario
    seed : int
    """

    def __init__(
        self, truth: TrialTruth, *, rig: StereoRig, imaging: ImagingScenario, seed: int
    ) -> None:
        for cam in rig.cameras:
            if cam.image_size != imaging.camera_size(cam.name):
                raise ValueError(
                    f"the rig's {cam.name} camera is {tuple(cam.image_size)} but the imaging"
                    f" scenario's image_size is {tuple(imaging.camera_size(cam.name))}"
                )
        names = truth.marker_names
        for _, marker, _, _ in imaging.occlusions:
            if marker not in names:
                raise ValueError(f"occlusion marker must be one of {names}, got {marker!r}")
        if imaging.skin_level > 0 and not isinstance(truth.model, TappingModel):
            raise ValueError("the skin is drawn for finger tapping only; use skin_level 0")
        self.truth = truth
        self.rig = rig
        self.imaging = imaging
        self.seed = int(seed)
        self.model = model = truth.model
        self.clocks: dict[str, CameraClock] = camera_clocks(truth, imaging, seed)
        self.times: dict[str, FloatArray] = {c: self.clocks[c].true_s for c in CAMERA_NAMES}
        self.frame_counts = {c: len(self.times[c]) for c in CAMERA_NAMES}
        self.n_frames = self.frame_counts["left"]
        rngs = {
            name: np.random.default_rng([self.seed, 0x51A, i])
            for i, name in enumerate(
                (
                    "bg-left",
                    "bg-right",
                    "noise-left",
                    "noise-right",
                    "shot-left",
                    "shot-right",
                    "scene",
                )
            )
        }
        self._shot_rngs = {c: rngs[f"shot-{c}"] for c in CAMERA_NAMES}
        marker_px = [cam.project(truth.positions_mm.reshape(-1, 3))[::5] for cam in rig.cameras]
        marker_px = [p[np.all(np.isfinite(p), axis=1)] for p in marker_px]
        self.statics = _choose_static(imaging.distractors_static, rig, marker_px, rngs["scene"])
        self.movings = _choose_moving(imaging.distractors_moving, rngs["scene"])
        self._radius_mm = np.full(len(names), imaging.marker_diameter_mm / 2.0)
        self._marker_peaks = imaging.marker_peak * np.array([1.0, 0.96, 0.92][: len(names)])
        self._backgrounds = {
            c: make_background(
                imaging.camera_size(c),
                rng=rngs[f"bg-{c}"],
                level=imaging.background_level,
                texture=imaging.background_texture,
            )
            for c in CAMERA_NAMES
        }
        self._noises = {
            c: SensorNoise(
                imaging.camera_size(c), sigma=imaging.noise_sigma, rng=rngs[f"noise-{c}"]
            )
            for c in CAMERA_NAMES
        }
        self.occluded = {
            c: np.zeros((self.frame_counts[c], len(names)), dtype=bool) for c in CAMERA_NAMES
        }
        # visible fraction of each marker per frame of each camera (own numbering)
        self.visibility = {c: np.ones((self.frame_counts[c], len(names))) for c in CAMERA_NAMES}
        self._skin_look = SkinLook(level=imaging.skin_level) if imaging.skin_level > 0 else None
        for cam_name, marker, t0, dur in imaging.occlusions:
            t = self.times[cam_name]
            self.occluded[cam_name][:, names.index(marker)] |= (t >= t0) & (t < t0 + dur)
        self._cameras = {"left": rig.left, "right": rig.right}
        # The movement hides markers itself (a mount seen from behind): the other tasks.
        self.self_occluded = {
            c: np.zeros((self.frame_counts[c], len(names)), dtype=bool) for c in CAMERA_NAMES
        }
        if isinstance(model, TaskModel):
            for c, cam in self._cameras.items():
                hidden = model.hidden_from(cam.center_world_mm, self.times[c])
                self.self_occluded[c] = hidden
                self.occluded[c] |= hidden
        self._n_sub = {
            c: _blur_samples(model, self.times[c], imaging.exposure_s, float(cam.K[0, 0]))
            for c, cam in self._cameras.items()
        }
        self._static_layers = [
            SphereLayer(
                np.array([d.position_mm for d in self.statics if d.profile == profile])[None],
                np.array([d.radius_mm for d in self.statics if d.profile == profile]),
                np.array([d.peak for d in self.statics if d.profile == profile]),
                profile,
            )
            for profile in (DISC, GLINT)
            if any(d.profile == profile for d in self.statics)
        ]
        self._next = {c: 0 for c in CAMERA_NAMES}
        self._statics_drawn: dict[str, list[Patch]] = {}

    def render(self, j: int) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        """The left and right frames ``j``, uint8 ``(H, W)`` each."""
        return self.render_camera("left", j), self.render_camera("right", j)

    def render_camera(self, c: str, j: int) -> NDArray[np.uint8]:
        """Frame ``j`` of camera ``c`` (``"left"`` or ``"right"``), uint8 ``(H, W)``.

        Each camera's frames must be rendered in order.
        """
        if j != self._next[c]:
            raise ValueError(
                f"{c} frames must be rendered in order: expected {self._next[c]}, got {j}"
            )
        self._next[c] += 1
        return self._render_camera(c, j)

    def _render_camera(self, c: str, j: int) -> NDArray[np.uint8]:
        if self._skin_look is not None:
            return self._render_camera_with_hand(c, j)
        imaging = self.imaging
        cam = self._cameras[c]
        S = int(self._n_sub[c][j])
        t_mid = self.times[c][j]
        sub = imaging.exposure_s * ((np.arange(S) + 0.5) / S - 0.5)
        sub_t = t_mid + sub
        size = imaging.camera_size(c)
        patches = list(self._static_patches(c))
        if self.movings:
            patches += self._moving_patches(size, cam, sub_t, t_mid)
        peaks = np.where(self.occluded[c][j], 0.0, self._marker_peaks)
        patches += sphere_patches(
            size,
            cam,
            SphereLayer(self._marker_centres(c, t_mid, sub), self._radius_mm, peaks, DISC),
            psf_sigma_px=imaging.psf_sigma_px,
            shot_noise=(self._shot_rngs[c], _SHOT_NOISE_GAIN) if imaging.noise_sigma > 0 else None,
        )
        self.visibility[c][j] = np.where(self.occluded[c][j], 0.0, 1.0)
        return self._noises[c].frame_u8(self._backgrounds[c], patches)

    def _static_patches(self, c: str) -> list[Patch]:
        """The static distractors as camera ``c`` sees them: the same in every frame, so
        drawn once (no shot noise on them)."""
        if c not in self._statics_drawn:
            size = self.imaging.camera_size(c)
            self._statics_drawn[c] = [
                patch
                for layer in self._static_layers
                for patch in sphere_patches(
                    size, self._cameras[c], layer, psf_sigma_px=self.imaging.psf_sigma_px
                )
            ]
        return self._statics_drawn[c]

    def _timing(self, c: str) -> CameraTiming:
        return self.imaging.left_timing if c == "left" else self.imaging.right_timing

    def _marker_centres(self, c: str, t_mid: float, sub: FloatArray) -> FloatArray:
        """Marker centres ``(S, M, 3)`` at the exposure's sub-samples ``t_mid + sub``;
        with a rolling shutter, each marker at the instant its row is read."""
        readout_s = self._timing(c).readout_ms * 1e-3
        if readout_s <= 0:
            return self.model.positions_mm(t_mid + sub)
        n_m = len(self._radius_mm)
        cam = self._cameras[c]
        t_m = rolling_shutter_times(cam, self.model.positions_mm, t_mid, readout_s, n_m)
        times = (t_m[None, :] + sub[:, None]).ravel()
        centres = self.model.positions_mm(times).reshape(len(sub), n_m, n_m, 3)
        return centres[:, np.arange(n_m), np.arange(n_m)]

    def _render_camera_with_hand(self, c: str, j: int) -> NDArray[np.uint8]:
        """A frame with the IR-lit hand (core.simulation.hand): the skin replaces the
        background, the markers are opaque and hidden where skin is in front of them;
        records each marker's visible fraction."""
        imaging = self.imaging
        assert self._skin_look is not None
        assert isinstance(self.model, TappingModel)
        cam = self._cameras[c]
        S = int(self._n_sub[c][j])
        t_mid = self.times[c][j]
        sub = imaging.exposure_s * ((np.arange(S) + 0.5) / S - 0.5)
        sub_t = t_mid + sub
        frame = self._backgrounds[c].copy()
        radius = imaging.marker_diameter_mm / 2.0
        capsules = tapping_hand(self.model, t_mid, marker_radius_mm=radius)
        skin = draw_skin(frame, cam, capsules, self._skin_look)
        add_patches(frame, self._static_patches(c))
        if self.movings:
            add_patches(frame, self._moving_patches(imaging.camera_size(c), cam, sub_t, t_mid))
        if imaging.nail_glint_peak > 0:
            glints = nail_glints(
                self.model, cam, t_mid, marker_radius_mm=radius, peak=imaging.nail_glint_peak
            )
            draw_spheres(frame, cam, glints, psf_sigma_px=imaging.psf_sigma_px)
        peaks = np.where(self.occluded[c][j], 0.0, self._marker_peaks)
        vis = composite_spheres(
            frame,
            cam,
            SphereLayer(self._marker_centres(c, t_mid, sub), self._radius_mm, peaks, DISC),
            skin,
            psf_sigma_px=imaging.psf_sigma_px,
            shot_noise=(self._shot_rngs[c], _SHOT_NOISE_GAIN) if imaging.noise_sigma > 0 else None,
        )
        self.visibility[c][j] = vis
        self._noises[c].add_to(frame)
        return to_uint8(frame)

    def _moving_patches(
        self, size: ImageSize, cam: Camera, sub_t: FloatArray, t_mid: float
    ) -> list[Patch]:
        centres = np.stack([d.positions_mm(self.model, sub_t) for d in self.movings], axis=1)
        peaks = np.array([d.brightness(np.array([t_mid]))[0] for d in self.movings])
        radii = np.array([d.radius_mm for d in self.movings])
        return sphere_patches(
            size,
            cam,
            SphereLayer(centres, radii, peaks, GLINT),
            psf_sigma_px=self.imaging.psf_sigma_px,
        )

    def truth_document(self, *, video_names: dict[str, str]) -> dict[str, Any]:
        """The ``truth.json`` document (``bradyscope.truth/1``)."""
        return _truth_document(
            self.truth,
            seed=self.seed,
            imaging=self.imaging,
            video_names=video_names,
            occluded=self.occluded,
            visibility=self.visibility,
            statics=self.statics,
            movings=self.movings,
            model=self.model,
            clocks=self.clocks,
            self_occluded=self.self_occluded,
        )


def simulate_session(
    out_dir: str | Path,
    *,
    seed: int,
    tapping: TappingScenario | None = None,
    imaging: ImagingScenario | None = None,
    rig: StereoRig | None = None,
    progress: ProgressCallback | None = None,
    task: TaskScenario | None = None,
) -> SimulatedSession:
    """Render a stereo recording of a simulated tapping trial with its ground truth.

    Parameters
    ----------
    out_dir : str or Path
        Created if needed; receives ``left.<ext>``, ``right.<ext>``, ``rig.json``
        and ``truth.json`` (``<ext>`` is ``mkv`` for lossless, ``mp4`` for mp4v).
    seed : int
        Everything random derives from it: same seed, same truth.json bytes and
        same decoded frames.
    tapping : TappingScenario, optional
        Default: ``TappingScenario()`` (10 s at 100 fps, 3 Hz, 50 mm).
    imaging : ImagingScenario, optional
        Default: ``ImagingScenario(image_size=rig's image size)``.
    rig : StereoRig, optional
        Default: :func:`~core.simulation.rig.default_rig` for the image size.
    progress : callable, optional
        ``progress("simulation", frames_done, frames_total)``.
    task : TaskScenario, optional
        Simulate that task (hand movements, pronation–supination, toe tapping;
        :mod:`core.simulation.tasks`) instead of finger tapping (``tapping`` is then ignored).

    Returns
    -------
    SimulatedSession
    """
    tapping = TappingScenario() if tapping is None else tapping
    if imaging is None:
        imaging = (
            ImagingScenario() if rig is None else ImagingScenario(image_size=rig.left.image_size)
        )
    if rig is None:
        geometry = rig_geometry(Task.FINGER_TAPPING if task is None else task.task)
        rig = default_rig(image_size=imaging.camera_size("left"), **geometry._asdict())
        if imaging.camera_size("right") != rig.left.image_size:
            rig = StereoRig(
                rig.left,
                default_rig(image_size=imaging.camera_size("right"), **geometry._asdict()).right,
            )
    # The rig file says what each camera's rolling shutter is (readout_ms).
    rig = StereoRig(
        replace(rig.left, readout_ms=imaging.left_timing.readout_ms),
        replace(rig.right, readout_ms=imaging.right_timing.readout_ms),
        dict(rig.quality),
    )
    truth: TrialTruth = (
        simulate_tapping(tapping, seed=seed) if task is None else simulate_task(task, seed=seed)
    )
    renderer = StereoRenderer(truth, rig=rig, imaging=imaging, seed=seed)

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    suffix = video_suffix(imaging.codec)
    paths = {c: out / f"{c}{suffix}" for c in CAMERA_NAMES}
    clocks = renderer.clocks
    writers = {
        c: _ThreadedWriter(
            VideoWriter(
                paths[c],
                fps=clocks[c].fps,
                image_size=imaging.camera_size(c),
                codec=imaging.codec,
                encoder_options=dict(imaging.encoder_options),
            )
        )
        for c in CAMERA_NAMES
    }
    timed = {c: t.vfr for c, t in (("left", imaging.left_timing), ("right", imaging.right_timing))}
    n_frames = max(renderer.frame_counts.values())
    try:
        for j in range(n_frames):
            for c in CAMERA_NAMES:
                if j < renderer.frame_counts[c]:
                    stamp = float(clocks[c].stamp_s[j]) if timed[c] else None
                    writers[c].write(renderer.render_camera(c, j), time_s=stamp)
            if (j + 1) % 10 == 0 or j + 1 == n_frames:
                report(progress, "simulation", j + 1, n_frames)
    finally:
        errors = []
        for w in writers.values():
            try:
                w.close()
            except BaseException as exc:  # keep closing the other writer
                errors.append(exc)
        if errors:
            raise errors[0]

    rig_path = out / "rig.json"
    write_rig(rig, rig_path)
    doc = renderer.truth_document(video_names={c: p.name for c, p in paths.items()})
    truth_path = out / "truth.json"
    truth_path.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return SimulatedSession(paths["left"], paths["right"], rig_path, truth_path, doc)


def read_truth(path: str | Path) -> dict[str, Any]:
    """Read a ``truth.json`` written by :func:`simulate_session`.

    Raises
    ------
    InputError
        The file is missing, not JSON, or not a ``bradyscope.truth/1`` document.
    """
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"cannot read the truth file {p.name}: {exc.strerror}.") from exc
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(
            f"{p.name} is not a JSON truth file written by bradyscope simulate."
        ) from exc
    if not isinstance(doc, dict) or doc.get("format") != TRUTH_FORMAT:
        found = doc.get("format") if isinstance(doc, dict) else None
        raise InputError(
            f"{p.name} has format {found!r}, expected {TRUTH_FORMAT!r};"
            " simulate the session again with this version of bradyscope."
        )
    return doc


def _frame_intervals(mask: NDArray[np.bool_]) -> list[list[int]]:
    """``[first, last]`` frame ranges (inclusive) where ``mask`` is True."""
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return [[int(a), int(b) - 1] for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _truth_document(
    truth: TrialTruth,
    *,
    seed: int,
    imaging: ImagingScenario,
    video_names: dict[str, str],
    occluded: dict[str, NDArray[np.bool_]],
    visibility: dict[str, FloatArray],
    statics: list[_StaticDistractor],
    movings: list[_MovingDistractor],
    model: MotionModel,
    clocks: dict[str, CameraClock],
    self_occluded: dict[str, NDArray[np.bool_]] | None = None,
) -> dict[str, Any]:
    kin = truth.to_dict()
    t_left = clocks["left"].true_s
    if len(t_left) != len(truth.t_s) or not np.array_equal(t_left, truth.t_s):
        # Free-running left camera: the truth at its frames' true capture times.
        kin["positions_mm"] = model.positions_mm(t_left).tolist()
        kin["frame_count"] = len(t_left)
    names = list(truth.marker_names)
    occlusions = []
    for cam_name, marker, t0, dur in imaging.occlusions:
        occlusions.append(
            {
                "camera": cam_name,
                "marker": marker,
                "t_start_s": t0,
                "duration_s": dur,
                # Frame numbers of that camera's own video.
                "frames": _frame_intervals(occluded[cam_name][:, names.index(marker)]),
            }
        )
    imaging_doc = asdict(imaging)
    imaging_doc["image_size"] = list(imaging.image_size)
    for c in CAMERA_NAMES:
        imaging_doc[f"{c}_timing"] = getattr(imaging, f"{c}_timing").to_dict()
    right = clocks["right"]
    right_timing = imaging.right_timing
    offset_s = float(right.true_s[0] - right.stamp_s[0] * (1 + right_timing.drift_ppm * 1e-6))
    imaging_doc["occlusions"] = [list(o) for o in imaging.occlusions]
    imaging_doc["encoder_options"] = dict(imaging.encoder_options)
    doc: dict[str, Any] = {
        "format": TRUTH_FORMAT,
        "units": "mm",
        "seed": int(seed),
        "videos": dict(video_names),
        "rig": "rig.json",
        "world_frame": "left camera (x right, y down, z forward, mm)",
        "fps": truth.fps,
        "frame_count": kin.pop("frame_count"),
        "offset_frames": float(imaging.offset_frames)
        if imaging.offset_frames
        else offset_s * right.fps / (1 + right_timing.drift_ppm * 1e-6),
        "offset_convention": "right frame j shows the same instant as left frame j + offset_frames",
        "frame_time": "frame i of the left video is exposed around t = i / fps s",
        # The time model: left time = offset_s + (1 + drift_ppm 1e-6) * right camera's clock.
        "clock": {"offset_s": offset_s, "drift_ppm": float(right_timing.drift_ppm)},
        "cameras": {
            c: {
                "fps": clocks[c].fps,
                "frame_count": len(clocks[c].true_s),
                "dropped_after": list(clocks[c].dropped_after),
                "readout_ms": getattr(imaging, f"{c}_timing").readout_ms,
                "image_size": list(imaging.camera_size(c)),
                "timestamps_s": clocks[c].stamp_s.tolist(),
                "true_time_s": clocks[c].true_s.tolist(),
            }
            for c in CAMERA_NAMES
        },
        "marker_names": names,
        "marker_diameter_mm": imaging.marker_diameter_mm,
    }
    kin.pop("fps")
    kin.pop("marker_names")
    doc.update(kin)
    doc["occlusions"] = occlusions
    if self_occluded is not None and any(np.any(v) for v in self_occluded.values()):
        # [camera][marker]: frame ranges (that camera's numbering) the movement hid it
        doc["self_occlusions"] = {
            c: {name: _frame_intervals(self_occluded[c][:, k]) for k, name in enumerate(names)}
            for c in CAMERA_NAMES
        }
    # [camera][frame of that camera][marker]: share of the marker's image not hidden
    doc["visibility"] = {c: np.round(visibility[c], 4).tolist() for c in CAMERA_NAMES}
    t = t_left
    doc["distractors"] = {
        "static": [
            {
                "position_mm": d.position_mm.tolist(),
                "radius_mm": d.radius_mm,
                "peak": d.peak,
                "profile": d.profile,
            }
            for d in statics
        ],
        "moving": [
            {
                "attached_to": "hand",
                "radius_mm": d.radius_mm,
                "peak": d.peak,
                "profile": GLINT,
                "positions_mm": d.positions_mm(model, t).tolist(),
                "brightness": d.brightness(t).tolist(),
            }
            for d in movings
        ],
    }
    doc["imaging"] = imaging_doc
    return doc

"""`bradyscope simulate`: write a simulated stereo recording with its ground truth (INTERFACES.md).

Writes ``left.<ext>``, ``right.<ext>``, ``rig.json`` and ``truth.json`` into
``-o DIR``; with ``--boards`` also ``DIR/calibration/`` (chessboard and
ChArUco recordings of the same rig). See ``docs/simulator.md``.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from core.errors import InputError
from core.tasks import TASKS, Task

if TYPE_CHECKING:  # the sub-command imports the simulator only when it runs
    from core.camera import StereoRig
    from core.simulation.kinematics import TappingScenario
    from core.simulation.session import ImagingScenario
    from core.simulation.tasks import TaskScenario


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected WIDTHxHEIGHT such as 1280x1024, got {text!r}"
        ) from None
    if w < 16 or h < 16:
        raise argparse.ArgumentTypeError(f"the image must be at least 16x16 pixels, got {text!r}")
    return w, h


def _int_list(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected tap numbers separated by commas such as 4,9, got {text!r}"
        ) from None


def _halts(text: str) -> tuple[tuple[int, float], ...]:
    out = []
    try:
        for item in text.split(","):
            if item.strip():
                tap, dur = item.split(":")
                out.append((int(tap), float(dur)))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected TAP:SECONDS pairs separated by commas such as 12:0.8,20:1.0, got {text!r}"
        ) from None
    return tuple(out)


def _occlusion(text: str) -> tuple[str, str, float, float]:
    parts = text.split(":")
    try:
        cam, marker, t0, dur = parts
        return cam, marker, float(t0), float(dur)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected CAMERA:MARKER:START_S:DURATION_S such as left:index:2.0:0.5, got {text!r}"
        ) from None


def _drop(text: str) -> tuple[str, int]:
    cam, _, frame = text.partition(":")
    if cam not in ("left", "right") or not frame.strip().isdigit():
        raise argparse.ArgumentTypeError(f"expected CAM:FRAME with CAM left or right, got {text!r}")
    return cam, int(frame)


def _turn(text: str) -> tuple[float, float, float]:
    try:
        t0, dur, angle = (float(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected START_S:DURATION_S:DEGREES such as 2.0:3.0:70, got {text!r}"
        ) from None
    return t0, dur, angle


def _overlap(text: str) -> tuple[str, float]:
    cam, _, sep = text.partition(":")
    try:
        separation = float(sep) if sep else 3.0
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected CAMERA[:MM] such as right:3, got {text!r}"
        ) from None
    if cam not in ("left", "right"):
        raise argparse.ArgumentTypeError(f"the camera must be left or right, got {cam!r}")
    return cam, separation


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "simulate",
        help="write a simulated stereo recording of finger tapping with its ground truth",
        description=(
            "Simulate a finger-tapping trial filmed by two cameras: writes left/right videos,"
            " rig.json (the true rig) and truth.json (true 3D trajectories, taps, amplitudes,"
            " frequency, decrement, pauses) into DIR."
        ),
    )
    p.add_argument("-o", "--out", required=True, type=Path, metavar="DIR", help="output folder")
    p.add_argument("--seed", type=int, default=1, help="random seed (same seed, same output)")
    p.add_argument(
        "--task",
        choices=TASKS,
        default=TASKS[0],
        help="the task simulated (default finger_tapping); the others use their marker protocol"
        " (docs/protocols.md) and the tapping options below with the task's unit",
    )
    _tapping_arguments(p)
    _imaging_arguments(p)
    _timing_arguments(p)
    p.set_defaults(func=run)


def _tapping_arguments(p: argparse.ArgumentParser) -> None:
    """How the simulated patient taps."""
    g = p.add_argument_group("tapping")
    g.add_argument("--duration", type=float, default=10.0, metavar="S", help="length (s)")
    g.add_argument("--fps", type=float, default=100.0, help="frame rate (Hz)")
    g.add_argument(
        "--amplitude",
        type=float,
        default=None,
        metavar="MM",
        help="opening of the first tap (mm, default 50); another task's first cycle in its unit"
        " (degrees for pronation_supination and leg_agility; default 40 mm, 150 deg, 40 mm,"
        " 30 deg)",
    )
    g.add_argument(
        "--frequency",
        type=float,
        default=None,
        metavar="HZ",
        help="taps (cycles) per second while moving (default 3; 1.5, 1.2, 2.5, 1.6 for the other tasks)",
    )
    g.add_argument(
        "--decrement",
        type=float,
        default=0.0,
        metavar="MM",
        help="amplitude change per tap (mm, negative = shrinking)",
    )
    g.add_argument("--jitter", type=float, default=0.03, help="rhythm variability (CV of cycles)")
    g.add_argument(
        "--amplitude-jitter",
        type=float,
        default=0.0,
        help="amplitude variability around the trend (CV)",
    )
    g.add_argument(
        "--hesitation-taps",
        type=_int_list,
        default=(),
        metavar="K,K",
        help="taps preceded by a brief pause, e.g. 4,9",
    )
    g.add_argument(
        "--hesitation-s", type=float, default=0.25, metavar="S", help="length of a hesitation (s)"
    )
    g.add_argument(
        "--halts",
        type=_halts,
        default=(),
        metavar="K:S,K:S",
        help="freezes before taps, e.g. 12:0.8 (tap 12, 0.8 s; at least 0.3 s)",
    )
    g.add_argument("--drift", type=float, default=5.0, metavar="MM", help="slow hand drift (mm)")
    g.add_argument("--hand", choices=("right", "left"), default="right")
    g.add_argument(
        "--hand-marker", action="store_true", help="add a third marker on the back of the hand"
    )
    g.add_argument(
        "--turn",
        type=_turn,
        action="append",
        default=[],
        metavar="T0:DUR:DEG",
        help="the hand rolls about its long axis by DEG and back, e.g. 2:3:70 (repeatable)",
    )
    g.add_argument(
        "--overlap",
        type=_overlap,
        default=None,
        metavar="CAMERA[:MM]",
        help="turn the hand so that the closed markers overlap in that camera, their centres"
        " MM apart (default 3; the marker diameter makes them touch)",
    )


def _imaging_arguments(p: argparse.ArgumentParser) -> None:
    """How the two cameras see it."""
    g = p.add_argument_group("imaging")
    g.add_argument(
        "--size", type=_size, default=(1280, 1024), metavar="WxH", help="image size, e.g. 1280x1024"
    )
    g.add_argument(
        "--marker-mm",
        type=float,
        default=None,
        help="marker diameter (mm; default the task's protocol: 5, or 10 for toe_tapping and"
        " leg_agility)",
    )
    g.add_argument(
        "--noise", type=float, default=2.0, metavar="SIGMA", help="sensor noise (gray levels)"
    )
    g.add_argument("--exposure-ms", type=float, default=3.0, help="exposure time (ms)")
    g.add_argument(
        "--offset",
        "--offset-frames",
        dest="offset",
        type=float,
        default=0.0,
        metavar="K",
        help="right frame j shows the instant of left frame j+K (may be fractional)",
    )
    g.add_argument(
        "--distractors-static", type=int, default=0, metavar="N", help="static spurious reflections"
    )
    g.add_argument(
        "--distractors-moving",
        type=int,
        default=0,
        metavar="N",
        help="glints moving with the hand (ring, watch)",
    )
    g.add_argument(
        "--occlusion",
        type=_occlusion,
        action="append",
        default=[],
        metavar="CAM:MARKER:T0:DUR",
        help="hide a marker in one camera, e.g. left:index:2.0:0.5 (repeatable)",
    )
    g.add_argument(
        "--skin",
        type=float,
        default=0.0,
        metavar="LEVEL",
        help="draw the IR-lit hand, skin facing the camera at this gray level"
        " (0 = not drawn; 57 is a bright case, a quarter of the markers)",
    )
    g.add_argument(
        "--nail-glints",
        type=float,
        default=0.0,
        metavar="LEVEL",
        help="nail-polish highlights beside the markers at this peak gray level (with --skin)",
    )
    g.add_argument(
        "--codec",
        choices=("lossless", "mp4v", "h264", "hevc", "vp9", "vp8"),
        default="lossless",
        help="lossless FFV1 (.mkv, default), MPEG-4 or H.264/HEVC (.mp4), VP9/VP8 (.webm)",
    )


def _timing_arguments(p: argparse.ArgumentParser) -> None:
    """Free-running cameras: their clocks and lost frames."""
    g = p.add_argument_group("free-running cameras (docs/sync.md)")
    g.add_argument("--right-fps", type=float, default=None, metavar="HZ",
                   help="the right camera's frame rate (default: --fps)")  # fmt: skip
    g.add_argument("--offset-s", type=float, default=0.0, metavar="S",
                   help="the right camera starts this long after the left (s)")  # fmt: skip
    g.add_argument("--drift-ppm", type=float, default=0.0, metavar="PPM",
                   help="the right camera's clock runs slow by this (ppm)")  # fmt: skip
    g.add_argument("--drop", type=_drop, action="append", default=[], metavar="CAM:FRAME",
                   help="a frame lost after FRAME of camera CAM, e.g. right:150 (repeatable)")  # fmt: skip
    g.add_argument("--vfr", action="store_true",
                   help="write the capture times as timestamps (variable frame rate; needs h264/hevc/vp9/vp8)")  # fmt: skip
    g.add_argument("--time-jitter-ms", type=float, default=0.0, metavar="MS",
                   help="capture-time jitter of both cameras (ms, standard deviation)")  # fmt: skip
    g.add_argument("--rolling-shutter-ms", type=float, default=0.0, metavar="MS",
                   help="readout time top to bottom row of both cameras (ms; written to rig.json)")  # fmt: skip
    g.add_argument("--right-size", type=_size, default=None, metavar="WxH",
                   help="the right camera's image size (default: --size)")  # fmt: skip
    p.add_argument(
        "--boards",
        action="store_true",
        help="also write calibration recordings of the same rig into DIR/calibration",
    )


def _tapping(args: argparse.Namespace) -> TappingScenario:
    from core.simulation.kinematics import TappingScenario

    return TappingScenario(
        duration_s=args.duration,
        fps=args.fps,
        amplitude_mm=50.0 if args.amplitude is None else args.amplitude,
        frequency_hz=3.0 if args.frequency is None else args.frequency,
        decrement_mm_per_tap=args.decrement,
        rhythm_jitter=args.jitter,
        amplitude_jitter=args.amplitude_jitter,
        hesitations=args.hesitation_taps,
        hesitation_s=args.hesitation_s,
        halts=args.halts,
        drift_mm=args.drift,
        hand=args.hand,
        hand_marker=args.hand_marker,
        turns=tuple(args.turn),
    )


def _task(args: argparse.Namespace) -> TaskScenario:
    from core.simulation.tasks import TaskScenario

    for flag, given in (
        ("--hand-marker", args.hand_marker),
        ("--turn", bool(args.turn)),
        ("--overlap", args.overlap is not None),
        ("--skin", args.skin > 0),
    ):
        if given:
            raise ValueError(f"{flag} applies to finger tapping only")
    return TaskScenario(
        task=Task(args.task),
        duration_s=args.duration,
        fps=args.fps,
        amplitude=math.nan if args.amplitude is None else args.amplitude,
        frequency_hz=math.nan if args.frequency is None else args.frequency,
        decrement_per_cycle=args.decrement,
        rhythm_jitter=args.jitter,
        amplitude_jitter=args.amplitude_jitter,
        hesitations=args.hesitation_taps,
        hesitation_s=args.hesitation_s,
        halts=args.halts,
        drift_mm=min(args.drift, 30.0),
        side=args.hand,
    )


def _imaging(args: argparse.Namespace) -> ImagingScenario:
    from core.camera import ImageSize
    from core.protocols import marker_diameter_mm
    from core.simulation.session import ImagingScenario
    from core.simulation.timing import CameraTiming

    return ImagingScenario(
        image_size=ImageSize(*args.size),
        marker_diameter_mm=marker_diameter_mm(args.task)
        if args.marker_mm is None
        else args.marker_mm,
        noise_sigma=args.noise,
        exposure_s=args.exposure_ms / 1000.0,
        distractors_static=args.distractors_static,
        distractors_moving=args.distractors_moving,
        occlusions=tuple(args.occlusion),
        offset_frames=args.offset,
        codec=args.codec,
        skin_level=args.skin,
        left_timing=CameraTiming(
            drop_after=tuple(f for c, f in args.drop if c == "left"),
            jitter_s=args.time_jitter_ms / 1000.0,
            vfr=args.vfr,
            readout_ms=args.rolling_shutter_ms,
        ),
        right_timing=CameraTiming(
            fps=args.right_fps,
            start_s=args.offset_s,
            drift_ppm=args.drift_ppm,
            drop_after=tuple(f for c, f in args.drop if c == "right"),
            jitter_s=args.time_jitter_ms / 1000.0,
            vfr=args.vfr,
            readout_ms=args.rolling_shutter_ms,
            image_size=None if args.right_size is None else ImageSize(*args.right_size),
        ),
        nail_glint_peak=args.nail_glints,
    )


def _scenarios(
    args: argparse.Namespace,
) -> tuple[TappingScenario, TaskScenario | None, ImagingScenario, StereoRig]:
    """The scenarios and rig of the command line, checked before anything is rendered."""
    from core.camera import StereoRig
    from core.simulation.hand import overlap_orientation_deg
    from core.simulation.kinematics import simulate_tapping
    from core.simulation.rig import default_rig
    from core.simulation.session import camera_clocks
    from core.simulation.tasks import rig_geometry, simulate_task

    try:
        tapping = _tapping(args)
        task = None if args.task == Task.FINGER_TAPPING.value else _task(args)
        imaging = _imaging(args)
        # Cheap checks that need the tap timeline (do the pauses fit?) before rendering.
        truth = (
            simulate_tapping(tapping, seed=args.seed)
            if task is None
            else simulate_task(task, seed=args.seed)
        )
        camera_clocks(truth, imaging, args.seed)  # do the lost frames fit the videos?
        names = tapping.marker_names if task is None else task.marker_names
        for _, marker, _, _ in imaging.occlusions:
            if marker not in names:
                raise ValueError(
                    f"an occlusion names marker {marker!r}; markers are {', '.join(names)}"
                )
        geometry = rig_geometry(args.task)
        rig = default_rig(image_size=imaging.image_size, **geometry._asdict())
        if args.right_size is not None:
            rig = StereoRig(
                rig.left,
                default_rig(image_size=imaging.camera_size("right"), **geometry._asdict()).right,
            )
        if args.overlap is not None:
            cam_name, separation = args.overlap
            camera = rig.left if cam_name == "left" else rig.right
            tapping = replace(
                tapping,
                orientation_deg=overlap_orientation_deg(tapping, camera, separation_mm=separation),
            )
    except ValueError as exc:
        raise InputError(f"invalid scenario: {exc}; see bradyscope simulate --help.") from exc
    return tapping, task, imaging, rig


def run(args: argparse.Namespace) -> int:
    from app.cli.progress import progress_bar
    from core.simulation.boards import write_board_recordings
    from core.simulation.session import simulate_session
    from core.simulation.timing import CameraTiming

    tapping, task, imaging, rig = _scenarios(args)
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(
            f"cannot create the output folder {args.out} ({exc.strerror});"
            " choose a folder you can write to."
        ) from exc
    with progress_bar() as progress:
        session = simulate_session(
            args.out,
            seed=args.seed,
            tapping=tapping,
            imaging=imaging,
            rig=rig,
            progress=progress,
            task=task,
        )
    if args.boards:
        # The board is filmed by the same free-running cameras (their start and clock;
        # lost frames and rolling shutter belong to the tapping recording).
        free = args.offset_s != 0 or args.drift_ppm != 0
        timing = (
            (
                CameraTiming(start_s=max(0.0, -args.offset_s)),
                CameraTiming(start_s=max(0.0, args.offset_s), drift_ppm=args.drift_ppm),
            )
            if free
            else None
        )
        write_board_recordings(rig, args.out / "calibration", seed=args.seed, timing=timing)
    truth = session.truth
    print(
        f"wrote {args.out}: {session.left_video.name}, {session.right_video.name}"
        f" ({truth['frame_count']} frames at {truth['fps']:g} fps), rig.json, truth.json"
        + (
            f" ({truth['tap_count']} taps)"
            if task is None
            else f" ({truth['cycle_count']} cycles of {args.task})"
        )
        + (", calibration/" if args.boards else "")
    )
    return 0

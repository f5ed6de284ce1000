"""What the review view draws on each video frame: tracked markers and raw detections.

The clinician checks a measurement by watching the two videos with the
markers drawn on them. For every frame of each video, :func:`camera_overlay`
gives

- the **tracked markers**: the labelled 3D trajectories (``(T, M, 3)`` mm, per
  left frame) brought to that frame's instant and projected through the rig
  (:meth:`core.camera.Camera.project`, OpenCV pixels, lens distortion
  included), so a label drawn in the wrong place shows a tracking, labelling or
  synchronisation error;
- the **detections**: the marker centres the detector found in that frame
  (px), before matching and tracking.

Frame numbers are each video's own; ``left_frame`` says where each frame lies
on the left video's frame axis (the time model of :mod:`core.clock`), which
the player uses to keep the two videos in step. :func:`overlay_document` is
the JSON form stored with a result (``bradyscope.overlay/1``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from core.camera import Camera, ImageSize

FloatArray = NDArray[np.float64]

OVERLAY_FORMAT = "bradyscope.overlay/1"
#: Decimals of the pixel coordinates in the JSON form (0.001 px).
PIXEL_DECIMALS = 3


@dataclass(frozen=True)
class CameraOverlay:
    """The overlay of one video.

    Attributes
    ----------
    camera : str
        The rig camera that took the video (``"left"`` or ``"right"``).
    image_size : ImageSize
    fps : float
        Frame rate of the video (Hz).
    left_frame : ndarray, shape (F,)
        Position of each of the video's frames on the left video's frame axis
        (fractional; NaN outside the left recording).
    tracks_px : ndarray, shape (F, M, 2)
        Tracked markers projected into the video (px); NaN where unknown.
    labels : tuple of str
        The ``M`` marker names.
    detections_px : list of ndarray, each (N_f, 2)
        The detector's marker centres in each frame (px).
    """

    camera: str
    image_size: ImageSize
    fps: float
    left_frame: FloatArray
    tracks_px: FloatArray
    labels: tuple[str, ...]
    detections_px: list[FloatArray]

    def to_dict(self) -> dict[str, Any]:
        """JSON form: numbers rounded to 0.001 px / frame, null where unknown."""
        return {
            "camera": self.camera,
            "image_size": [int(self.image_size.width), int(self.image_size.height)],
            "fps": float(self.fps),
            "frame_count": len(self.left_frame),
            "left_frame": [_num(v) for v in self.left_frame],
            "tracks": {
                name: [_point(p) for p in self.tracks_px[:, m]]
                for m, name in enumerate(self.labels)
            },
            "detections": [[_point(p) for p in d] for d in self.detections_px],
        }


def _num(v: float) -> float | None:
    v = float(v)
    return round(v, PIXEL_DECIMALS) if math.isfinite(v) else None


def _point(p: FloatArray) -> list[float] | None:
    if not np.all(np.isfinite(p)):
        return None
    return [round(float(p[0]), PIXEL_DECIMALS), round(float(p[1]), PIXEL_DECIMALS)]


def positions_at(positions_mm: FloatArray, left_frame: FloatArray) -> FloatArray:
    """Positions ``(T, M, 3)`` linearly interpolated at fractional left frames ``(F,)``.

    NaN outside ``[0, T - 1]`` and wherever a neighbouring sample is NaN.
    """
    pos = np.asarray(positions_mm, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[2] != 3:
        raise ValueError(f"positions_mm must be (T, M, 3), got {pos.shape}")
    s = np.asarray(left_frame, dtype=np.float64).reshape(-1)
    t = pos.shape[0]
    out = np.full((s.size, pos.shape[1], 3), np.nan)
    ok = np.isfinite(s) & (s >= 0) & (s <= t - 1)
    if t == 0 or not ok.any():
        return out
    i0 = np.minimum(np.floor(s[ok]).astype(np.intp), t - 1)
    i1 = np.minimum(i0 + 1, t - 1)
    w = (s[ok] - i0)[:, None, None]
    out[ok] = (1 - w) * pos[i0] + w * pos[i1]
    return out


def camera_overlay(
    camera: Camera,
    positions_mm: FloatArray,
    labels: Sequence[str],
    detections_px: Sequence[FloatArray],
    *,
    fps: float,
    left_frame: FloatArray | None = None,
) -> CameraOverlay:
    """The overlay of one camera's video.

    Parameters
    ----------
    camera : Camera
        The calibrated camera that took the video.
    positions_mm : (T, M, 3) float
        Tracked markers per left frame (mm, rig frame); NaN where missing.
    labels : sequence of M str
    detections_px : sequence of F arrays (N_f, 2)
        The detector's centres in each of the video's frames (px).
    fps : float
        Frame rate of the video (Hz).
    left_frame : (F,) float, optional
        Position of each frame on the left frame axis; default ``0 .. F-1``
        (the left video itself).

    Returns
    -------
    CameraOverlay
    """
    pos = np.asarray(positions_mm, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[1] != len(labels):
        raise ValueError(f"positions_mm must be (T, {len(labels)}, 3), got {pos.shape}")
    n = len(detections_px)
    lf = np.arange(n, dtype=np.float64) if left_frame is None else np.asarray(left_frame, float)
    if lf.shape != (n,):
        raise ValueError(f"left_frame must be ({n},) like detections_px, got {lf.shape}")
    at = positions_at(pos, lf)
    flat = at.reshape(-1, 3)
    px = np.full((flat.shape[0], 2), np.nan)
    ok = np.all(np.isfinite(flat), axis=1)
    if ok.any():
        px[ok] = camera.project(flat[ok])
    dets = [np.asarray(d, dtype=np.float64).reshape(-1, 2) for d in detections_px]
    return CameraOverlay(
        camera=camera.name,
        image_size=camera.image_size,
        fps=float(fps),
        left_frame=lf,
        tracks_px=px.reshape(n, pos.shape[1], 2),
        labels=tuple(labels),
        detections_px=dets,
    )


def overlay_document(cameras: Sequence[CameraOverlay], *, fps: float) -> dict[str, Any]:
    """The ``bradyscope.overlay/1`` document of a result: one entry per camera."""
    return {
        "format": OVERLAY_FORMAT,
        "fps": float(fps),
        "cameras": [c.to_dict() for c in cameras],
    }


def swap_overlay_labels(
    document: dict[str, Any], a: str = "thumb", b: str = "index"
) -> dict[str, Any]:
    """``document`` with the tracks ``a`` and ``b`` renamed to each other."""
    out = dict(document)
    cams = []
    for cam in document.get("cameras", []):
        tracks = dict(cam.get("tracks", {}))
        if a in tracks and b in tracks:
            tracks[a], tracks[b] = tracks[b], tracks[a]
        cams.append({**cam, "tracks": tracks})
    out["cameras"] = cams
    return out


__all__ = [
    "OVERLAY_FORMAT",
    "CameraOverlay",
    "camera_overlay",
    "overlay_document",
    "positions_at",
    "swap_overlay_labels",
]

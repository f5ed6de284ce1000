"""The aperture signal: thumb–index distance over time, filtered, and its velocity.

The aperture is the 3D Euclidean distance between the thumb and index markers
(mm). It is independent of where the hand is in the room, so hand drift does
not enter it. It is low-pass filtered without phase shift (a Butterworth filter
run forwards and backwards, :func:`scipy.signal.sosfiltfilt`) and differentiated
by the derivative of a cubic spline through the filtered samples.

Gaps are respected, never bridged: frames where a marker is missing (NaN) split
the recording into separate runs that are filtered and differentiated on their
own, and the filtered signal and velocity are NaN inside the gap. Frames that
the tracker filled in (``measured`` False) are kept for the continuity of the
filter when the filled-in stretch is short (at most ``max_fill_s``), or when
the two markers' images merged in one camera in every frame of it while the
other camera saw both (``merged``, a closure seen along the opening
direction: only their depth was interpolated; at most ``max_merged_fill_s``),
and treated as missing when it is longer.
Either way they are marked not ``valid``.

See ``docs/metrics.md`` for the choice of the cut-off frequency.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Default low-pass cut-off (Hz); see docs/metrics.md for the reasons.
DEFAULT_CUTOFF_HZ = 20.0
#: The cut-off never exceeds this fraction of the sampling rate (0.8 × Nyquist).
MAX_CUTOFF_FRACTION_OF_FPS = 0.4
#: Butterworth order of the one-way filter (the zero-phase filter doubles it).
FILTER_ORDER = 4
#: Longest filled-in (interpolated) stretch kept for filtering (s).
DEFAULT_MAX_FILL_S = 0.1
#: Longest one in which the markers' images merged in one camera in every frame, the
#: other seeing both (only the depth interpolated) (s).
DEFAULT_MAX_MERGED_FILL_S = 0.15


@dataclass(frozen=True)
class Aperture:
    """Thumb–index aperture of one recording, sampled at the video frames.

    Attributes
    ----------
    t_s : (T,) float64
        Time of each frame, ``i / fps`` seconds.
    distance_mm : (T,) float64
        Raw 3D thumb–index distance (mm); NaN where a marker is missing.
    filtered_mm : (T,) float64
        Zero-phase low-passed distance (mm); NaN in gaps.
    velocity_mm_s : (T,) float64
        Time derivative of ``filtered_mm`` (mm/s); positive while opening,
        negative while closing; NaN in gaps.
    valid : (T,) bool
        True where both markers were measured (not missing, not filled in).
    fps : float
        Sampling rate (frames per second).
    cutoff_hz : float
        Cut-off frequency of the low-pass filter actually used (Hz).
    noise_mm : float
        Robust estimate of the SD of the measurement noise of the raw
        distance (mm), from the residual of the filter (see
        :func:`estimate_noise_mm`); 0 when there are too few samples.
    velocity_noise_mm_s : float
        The SD of velocity noise this raw noise produces after filtering and
        differentiation (mm/s).
    """

    t_s: FloatArray
    distance_mm: FloatArray
    filtered_mm: FloatArray
    velocity_mm_s: FloatArray
    valid: BoolArray
    fps: float
    cutoff_hz: float
    noise_mm: float = 0.0
    velocity_noise_mm_s: float = 0.0

    @property
    def usable(self) -> BoolArray:
        """(T,) bool: frames with a defined filtered signal (not inside a gap)."""
        return np.isfinite(self.filtered_mm)

    def runs(self) -> list[tuple[int, int]]:
        """Half-open ``[start, stop)`` frame ranges of contiguous usable signal."""
        return true_runs(self.usable)


def true_runs(mask: BoolArray) -> list[tuple[int, int]]:
    """Half-open ``[start, stop)`` index ranges where a 1-D boolean mask is True."""
    m = np.asarray(mask, dtype=bool).astype(np.int8)
    if m.size == 0:
        return []
    edges = np.diff(np.concatenate(([0], m, [0])))
    starts = np.flatnonzero(edges == 1)
    stops = np.flatnonzero(edges == -1)
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]


def default_cutoff_hz(fps: float) -> float:
    """The default cut-off (Hz): 20 Hz, but at most ``0.4 * fps``."""
    return float(min(DEFAULT_CUTOFF_HZ, MAX_CUTOFF_FRACTION_OF_FPS * fps))


def lowpass_zero_phase(
    signal: FloatArray, fps: float, cutoff_hz: float, *, order: int = FILTER_ORDER
) -> FloatArray:
    """Zero-phase Butterworth low-pass of a 1-D signal without NaNs.

    Parameters
    ----------
    signal : (N,) float64
        Samples; must be finite.
    fps : float
        Sampling rate (Hz).
    cutoff_hz : float
        Cut-off of the one-way filter (Hz); the forward–backward magnitude
        response is -6 dB there.
    order : int
        Order of the one-way filter.

    Returns
    -------
    (N,) float64
        The filtered signal. Runs shorter than 4 samples are returned unchanged
        (too short to filter, and too short to hold a tap).
    """
    # Imported here: scipy.signal costs ~0.6 s, which the web app's and CLI's start-up do not need.
    from scipy.signal import butter, sosfiltfilt

    x = np.asarray(signal, dtype=np.float64)
    if x.size < 4:
        return x.copy()
    sos = butter(order, cutoff_hz, btype="low", fs=fps, output="sos")
    padlen_default = 3 * (2 * len(sos) + 1)
    padlen = min(padlen_default, x.size - 1)
    return np.asarray(sosfiltfilt(sos, x, padlen=padlen), dtype=np.float64)


def smooth_derivative(signal: FloatArray, fps: float) -> FloatArray:
    """Derivative (per second) of a smooth finite 1-D signal by a cubic spline.

    The spline derivative is accurate to O(h^4) for band-limited signals,
    unlike the two-point central difference, which under-estimates a 15-Hz
    component by 36 % at 60 fps.
    """
    x = np.asarray(signal, dtype=np.float64)
    if x.size < 2:
        return np.zeros_like(x)
    if x.size < 4:
        return np.gradient(x) * fps
    from scipy.interpolate import CubicSpline  # here, like scipy.signal above: start-up cost

    t = np.arange(x.size) / fps
    return np.asarray(CubicSpline(t, x).derivative()(t), dtype=np.float64)


def aperture_signal(
    positions_mm: NDArray[np.floating],
    fps: float,
    *,
    measured: NDArray[np.bool_] | None = None,
    cutoff_hz: float | None = None,
    max_fill_s: float = DEFAULT_MAX_FILL_S,
    merged: NDArray[np.bool_] | None = None,
    max_merged_fill_s: float = DEFAULT_MAX_MERGED_FILL_S,
) -> Aperture:
    """Compute the thumb–index aperture, filtered, with its velocity.

    Parameters
    ----------
    positions_mm : (T, M, 3) float
        Marker positions (mm), marker axis ``thumb, index[, ...]`` (only the
        first two markers are used); NaN where a marker is missing.
    fps : float
        Frames per second (> 0).
    measured : (T, M) or (T,) bool, optional
        False where a marker position was filled in (interpolated) or is
        missing. Default: every finite position counts as measured.
    cutoff_hz : float, optional
        Low-pass cut-off (Hz), ``0 < cutoff_hz < fps / 2``. Default:
        :func:`default_cutoff_hz` (20 Hz for 60–200 fps).
    max_fill_s : float
        Filled-in stretches longer than this (s) are treated as gaps.
    merged : (T, M) or (T,) bool, optional
        True where a filled-in position was seen by one camera while the two
        markers' images merged in the other (``core.tracks.Tracks.merged``:
        only its depth interpolated).
    max_merged_fill_s : float
        Filled-in stretches in which every frame's markers are measured or
        ``merged`` are kept up to this long (s).

    Returns
    -------
    Aperture

    Raises
    ------
    ValueError
        On wrong shapes or non-positive ``fps`` / invalid ``cutoff_hz``.
    """
    pos = np.asarray(positions_mm, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[1] < 2 or pos.shape[2] != 3:
        raise ValueError(f"positions_mm must have shape (T, M>=2, 3), got {pos.shape}")
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be a positive number, got {fps}")
    if cutoff_hz is None:
        cutoff_hz = default_cutoff_hz(fps)
    if not (0 < cutoff_hz < fps / 2):
        raise ValueError(f"cutoff_hz must lie in (0, fps/2) = (0, {fps / 2}), got {cutoff_hz}")
    if max_fill_s < 0:
        raise ValueError(f"max_fill_s must be >= 0, got {max_fill_s}")
    distance = np.linalg.norm(pos[:, 1, :] - pos[:, 0, :], axis=1)
    return signal_aperture(
        distance,
        fps,
        measured=measured,
        cutoff_hz=cutoff_hz,
        max_fill_s=max_fill_s,
        merged=merged,
        max_merged_fill_s=max_merged_fill_s,
    )


def signal_aperture(
    signal: NDArray[np.floating],
    fps: float,
    *,
    measured: NDArray[np.bool_] | None = None,
    cutoff_hz: float,
    max_fill_s: float = DEFAULT_MAX_FILL_S,
    merged: NDArray[np.bool_] | None = None,
    max_merged_fill_s: float = DEFAULT_MAX_MERGED_FILL_S,
) -> Aperture:
    """Filter and differentiate a cycle signal as :func:`aperture_signal` does the aperture.

    The other tasks' cycle signals (``core.protocols``: a distance in mm, or
    a rotation in degrees) go through the same filter, gap policy and noise
    estimate as the thumb–index aperture, so that :mod:`core.taps` segments
    them alike.

    Parameters
    ----------
    signal : (T,) float
        The raw signal; NaN where it is missing.
    fps, cutoff_hz, max_fill_s, merged, max_merged_fill_s
        As for :func:`aperture_signal` (the cut-off already checked).
    measured : (T, M) or (T,) bool, optional
        False where a marker position was filled in or is missing (with
        ``(T, M)``, a frame counts when its first two markers do).
    """
    distance = np.asarray(signal, dtype=np.float64)
    n_frames = distance.shape[0]
    finite = np.isfinite(distance)
    meas = finite.copy() if measured is None else _per_frame(measured, n_frames, "measured")
    meas &= finite
    seen = meas  # measured, or merged in one camera with only the depth filled in
    if merged is not None:
        sv = np.asarray(merged, dtype=bool)
        if measured is not None and np.shape(measured) == sv.shape:
            sv = sv | np.asarray(measured, dtype=bool)  # per marker: measured or one view
        seen = _per_frame(sv, n_frames, "merged") & finite
    distance = np.where(finite, distance, np.nan)

    # Usable for filtering: finite, and not inside a long filled-in stretch.
    usable = finite.copy()
    max_fill_frames = int(np.floor(max_fill_s * fps + 1e-9))
    max_merged_frames = max(max_fill_frames, int(np.floor(max_merged_fill_s * fps + 1e-9)))
    for a, b in true_runs(finite & ~meas):
        if b - a > max_fill_frames and not (b - a <= max_merged_frames and np.all(seen[a:b])):
            usable[a:b] = False

    filtered = np.full(n_frames, np.nan)
    velocity = np.full(n_frames, np.nan)
    for a, b in true_runs(usable):
        seg = lowpass_zero_phase(distance[a:b], fps, cutoff_hz)
        filtered[a:b] = seg
        velocity[a:b] = smooth_derivative(seg, fps)

    noise = estimate_noise_mm(distance - filtered, fps, cutoff_hz)
    return Aperture(
        t_s=np.arange(n_frames, dtype=np.float64) / fps,
        distance_mm=distance,
        filtered_mm=filtered,
        velocity_mm_s=velocity,
        valid=meas,
        fps=float(fps),
        cutoff_hz=float(cutoff_hz),
        noise_mm=noise,
        velocity_noise_mm_s=noise * noise_gains(fps, cutoff_hz)[1],
    )


def _per_frame(mask: NDArray[np.bool_], n_frames: int, name: str) -> NDArray[np.bool_]:
    """A ``(T,)`` frame mask from a ``(T, M>=2)`` or ``(T,)`` one (with ``(T, M)``, a
    frame counts when its first two markers do)."""
    m = np.asarray(mask, dtype=bool)
    if m.ndim == 2:
        if m.shape[0] != n_frames or m.shape[1] < 2:
            raise ValueError(f"{name} must have shape (T, M>=2) or (T,), got {m.shape}")
        result: NDArray[np.bool_] = m[:, 0] & m[:, 1]
        return result
    if m.shape != (n_frames,):
        raise ValueError(f"{name} must have shape (T, M>=2) or (T,), got {m.shape}")
    return m


def noise_gains(fps: float, cutoff_hz: float, *, order: int = FILTER_ORDER) -> tuple[float, float]:
    """How white noise of SD 1 mm appears in the filter residual (mm) and the velocity (mm/s).

    From the forward–backward Butterworth power response ``|H|^4`` with
    ``|H|^2 = 1 / (1 + (f / f_c)^(2 order))``: the residual ``raw - filtered``
    has SD ``sqrt(2/fps * integral (1 - |H|^2)^2 df)`` and the velocity SD
    ``sqrt(2/fps * integral (2 pi f)^2 |H|^4 df)``, over ``0 .. fps/2``.
    """
    f = np.linspace(0.0, fps / 2, 4001)
    h2 = 1.0 / (1.0 + (f / cutoff_hz) ** (2 * order))
    residual = np.sqrt(2.0 / fps * np.trapezoid((1.0 - h2) ** 2, f))
    velocity = np.sqrt(2.0 / fps * np.trapezoid((2 * np.pi * f) ** 2 * h2**2, f))
    return float(residual), float(velocity)


def estimate_noise_mm(residual_mm: FloatArray, fps: float, cutoff_hz: float) -> float:
    """Robust SD (mm) of white measurement noise from the residual ``raw - filtered``.

    The median absolute deviation of the residual (×1.4826, a Gaussian SD),
    divided by the share of white noise the low-pass filter leaves in the
    residual (:func:`noise_gains`). Robust to the few frames where the filter
    rounds a sharp turn. NaNs are ignored; 0 with fewer than 10 samples.
    """
    r = np.asarray(residual_mm, dtype=np.float64)
    r = r[np.isfinite(r)]
    if r.size < 10:
        return 0.0
    mad = float(np.median(np.abs(r - np.median(r))))
    return 1.4826 * mad / noise_gains(fps, cutoff_hz)[0]

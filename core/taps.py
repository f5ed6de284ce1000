"""Tap segmentation: each tap as an opening–closing cycle of the aperture.

The rule (the full text, with the reasons, is in ``docs/metrics.md``):

1. **Maximal apertures** are the peaks of the filtered aperture whose
   prominence (the drop to the deeper closure on the shallower side, as in
   :func:`scipy.signal.find_peaks`) is at least
   ``max(min_amplitude_mm, relative_amplitude * P90)``, P90 being the 90th
   percentile of the prominences of all candidate peaks of the recording.
   Small wobbles of the fingers are not taps; taps that shrink to a few
   millimetres late in a decrementing recording still are.
2. **Closures.** Between two consecutive maxima the closure is the minimal
   filtered aperture. Around it the *turn* is the contiguous stretch where the
   fingers are nearly still (aperture speed below the *still speed*,
   ``max(still_fraction * median peak opening speed, 3 * velocity noise SD)``,
   ignoring noise blips up to 50 ms) and closed (within ``dwell_tolerance`` of
   the adjacent amplitude above the minimum); its ends are interpolated where
   the speed crosses the still speed. Every turn, even a brisk one, has a
   short still stretch because the aperture speed passes through zero; its
   median length over the recording is the *typical turn* ``D``. A turn
   longer than ``D + min_pause_s`` holds a **pause** of ``length - D``: the
   closing movement ends ``D/2`` after the turn begins and the next opening
   starts ``D/2`` before it ends. Otherwise there is no pause, and closing end
   and opening start are both the middle of the turn.
3. **A tap** runs from the start of its opening to the end of its closing,
   through the maximal aperture. Pauses with the fingers closed lie *between*
   taps and belong to the tap that follows them (``pause_before_s``), as in
   the simulator's ground truth and the clinical wording "a hesitation before
   a tap".
4. **Completeness.** A tap is kept only when both of its closures are seen:
   true local minima strictly inside one run of usable signal, or still
   fingers at the edge of a run (a turning point rather than a movement cut
   off by the edge), deep enough (at least the peak threshold below the
   maximum). A tap cut by the start or the end of the recording, or by a gap
   (missing markers), is dropped; the cycles lost in a gap are counted in
   ``cycle_number``.
5. **Reliability.** A tap whose maximum or either closure falls on a
   filled-in (interpolated) frame is kept but marked ``reliable=False``: it
   counts as a tap and in the rhythm, not in amplitude or velocity statistics.

``amplitude_mm`` is the maximal aperture minus the aperture at the closure
that starts the tap (INTERFACES.md): both frames are located on the filtered
signal and their values read on the raw distance, which the low-pass filter
would distort at brisk turns.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray

from core.aperture import Aperture, true_runs

FloatArray = NDArray[np.float64]

#: Smallest opening (mm) that can be a tap.
DEFAULT_MIN_AMPLITUDE_MM = 3.0
#: A maximum must also rise this fraction of the recording's typical (P90) tap.
DEFAULT_RELATIVE_AMPLITUDE = 0.1
#: "Still": aperture speed below this fraction of the median peak opening speed.
DEFAULT_STILL_FRACTION = 0.1
#: A closed turn stays within this fraction of the adjacent amplitude of the minimum.
DEFAULT_DWELL_TOLERANCE = 0.1
#: Shortest pause (s) between taps; shorter excesses of a turn are frame jitter.
DEFAULT_MIN_PAUSE_S = 0.05
#: The still speed is at least this many SDs of the velocity noise.
NOISE_SDS_FOR_STILL = 3.0
#: Closures are not searched closer than this (s) to the edge of a run of signal.
EDGE_MARGIN_S = 0.03
#: Moving stretches this short (s) between still frames are noise, not movement.
MAX_NOISE_BLIP_S = 0.05


@dataclass(frozen=True)
class Tap:
    """One tap: opening from a closure to the maximal aperture, closing to the next closure.

    Attributes
    ----------
    index : int
        Position in the list of complete taps, from 0.
    cycle_number : int
        Estimated ordinal of the tap in the recording, from 0, counting the
        cycles lost in gaps of the signal (equal to ``index`` without gaps).
    i_start, i_max, i_end : int
        Frames nearest to the start of the opening, the maximal aperture and
        the end of the closing.
    t_start_s, t_max_aperture_s, t_end_s : float
        Their times (s); start and end may fall between frames (see the rule).
    closed_aperture_mm : float
        Raw aperture at the closure that starts the tap (mm), at the frame of the
        filtered minimum.
    max_aperture_mm : float
        Raw aperture at the frame of the filtered maximum (mm).
    amplitude_mm : float
        ``max_aperture_mm - closed_aperture_mm`` (mm).
    duration_s : float
        ``t_end_s - t_start_s``: the movement cycle, pauses excluded (s).
    opening_duration_s, closing_duration_s : float
        ``t_max_aperture_s - t_start_s`` and ``t_end_s - t_max_aperture_s`` (s).
    opening_velocity_mm_s_max, closing_velocity_mm_s_max : float
        Peak aperture speed while opening / closing (mm/s, both positive).
    opening_velocity_mm_s_mean : float
        ``amplitude_mm / opening_duration_s`` (mm/s).
    closing_velocity_mm_s_mean : float
        (maximal aperture − end closure) / ``closing_duration_s`` (mm/s).
    pause_before_s : float | None
        Pause with the fingers closed between the previous closing and this
        opening (s); 0 for a brisk turn; None when the previous closing was
        not seen (first tap, or first after a gap).
    cycle_s : float | None
        ``pause_before_s + duration_s``: closure-to-closure time (s), None
        when ``pause_before_s`` is.
    interval_s : float | None
        Inter-tap interval: start of the next tap minus start of this one (s),
        pauses included; None for the last tap and before a gap.
    after_gap : bool
        The tap is the first complete one after a gap in the signal.
    filled_fraction : float
        Fraction of the tap's frames that were filled in or not measured.
    reliable : bool
        False when the maximum or a closure falls on a filled-in frame.
    """

    index: int
    cycle_number: int
    i_start: int
    i_max: int
    i_end: int
    t_start_s: float
    t_max_aperture_s: float
    t_end_s: float
    closed_aperture_mm: float
    max_aperture_mm: float
    amplitude_mm: float
    duration_s: float
    opening_duration_s: float
    closing_duration_s: float
    opening_velocity_mm_s_max: float
    closing_velocity_mm_s_max: float
    opening_velocity_mm_s_mean: float
    closing_velocity_mm_s_mean: float
    pause_before_s: float | None
    cycle_s: float | None
    interval_s: float | None
    after_gap: bool
    filled_fraction: float
    reliable: bool

    def to_dict(self) -> dict[str, float | int | bool | None]:
        """Plain JSON-serialisable dict (one row of result.json's ``taps``)."""
        return dict(asdict(self))


@dataclass(frozen=True)
class Segmentation:
    """Taps and the recording-level thresholds used to find them.

    Attributes
    ----------
    taps : list[Tap]
    peak_threshold_mm : float
        Smallest prominence of a maximal aperture that counted as a tap (mm).
    still_velocity_mm_s : float
        Aperture speed below which the fingers count as still (mm/s).
    typical_turn_s : float
        Median length of the still stretch at a closure between two taps
        (s); a still stretch longer than this holds a pause of the excess.
    """

    taps: list[Tap]
    peak_threshold_mm: float
    still_velocity_mm_s: float
    typical_turn_s: float


@dataclass(frozen=True)
class _Valley:
    i_min: int
    first: float  # start of the turn (still and closed), sub-frame
    last: float  # end of the turn, sub-frame
    seen: bool  # the closure was observed (see rule 4)
    inner: bool  # lies between two maxima of the same run


def _vertex(f: FloatArray, i: int) -> float:
    """Sub-frame position of the extremum at frame ``i`` (parabola through 3 samples)."""
    if i <= 0 or i >= len(f) - 1 or not np.isfinite(f[i - 1 : i + 2]).all():
        return float(i)
    curvature = f[i - 1] - 2 * f[i] + f[i + 1]
    if curvature == 0:
        return float(i)
    return i + float(np.clip(0.5 * (f[i - 1] - f[i + 1]) / curvature, -0.5, 0.5))


def _still_mask(speed: FloatArray, still: float, max_blip: int) -> NDArray[np.bool_]:
    """Frames with speed below ``still``, ignoring noise blips of up to ``max_blip`` frames."""
    mask = np.isfinite(speed) & (speed < still)
    for a, b in true_runs(~mask & np.isfinite(speed)):
        if b - a <= max_blip and a > 0 and b < len(mask) and mask[a - 1] and mask[b]:
            mask[a:b] = True
    return mask


def _turn(
    f: FloatArray,
    speed: FloatArray,
    still_mask: NDArray[np.bool_],
    i_min: int,
    lo: int,
    hi: int,
    still: float,
    tol: float,
    max_offset: int,
) -> tuple[float, float]:
    """Start and end (sub-frame) of the still-and-closed stretch around ``i_min`` in ``[lo, hi]``.

    The ends are where the speed crosses ``still``, linearly interpolated
    between the last still frame and the first moving one.
    """
    limit = f[i_min] + tol
    if not still_mask[i_min]:
        # The filter may put the minimum a frame or two off the still stretch
        # of a sharp closure: start from the nearest still, closed frame.
        near = [
            j
            for d in range(1, max_offset + 1)
            for j in (i_min - d, i_min + d)
            if lo <= j <= hi and still_mask[j] and f[j] <= limit
        ]
        if not near:
            return float(i_min), float(i_min)
        i_min = near[0]
    first = i_min
    while first - 1 >= lo and still_mask[first - 1] and f[first - 1] <= limit:
        first -= 1
    last = i_min
    while last + 1 <= hi and still_mask[last + 1] and f[last + 1] <= limit:
        last += 1
    return _crossing(speed, still, first, first - 1), _crossing(speed, still, last, last + 1)


def _crossing(speed: FloatArray, still: float, inside: int, outside: int) -> float:
    if not 0 <= outside < len(speed) or not speed[outside] >= still > speed[inside]:
        return float(inside)
    frac = (still - speed[inside]) / (speed[outside] - speed[inside])
    return inside + float(frac) * (outside - inside)


def segment_recording(
    aperture: Aperture,
    *,
    min_amplitude_mm: float = DEFAULT_MIN_AMPLITUDE_MM,
    relative_amplitude: float = DEFAULT_RELATIVE_AMPLITUDE,
    still_fraction: float = DEFAULT_STILL_FRACTION,
    dwell_tolerance: float = DEFAULT_DWELL_TOLERANCE,
    min_pause_s: float = DEFAULT_MIN_PAUSE_S,
) -> Segmentation:
    """Split an aperture signal into complete taps (see the module docstring).

    Parameters
    ----------
    aperture : Aperture
        From :func:`core.aperture.aperture_signal`.
    min_amplitude_mm : float
        Smallest prominence (mm) of a maximal aperture that can be a tap.
    relative_amplitude : float
        A maximum must also rise at least this fraction of the 90th percentile
        of all candidate prominences, in [0, 1).
    still_fraction : float
        Fingers count as still below this fraction of the median peak opening
        speed of the taps, in (0, 1).
    dwell_tolerance : float
        A closed turn stays within this fraction of the smaller adjacent
        amplitude above the minimum, in [0, 1).
    min_pause_s : float
        A turn holds a pause only when it outlasts the typical turn by at
        least this much (s).

    Returns
    -------
    Segmentation
    """
    if not min_amplitude_mm > 0:
        raise ValueError(f"min_amplitude_mm must be > 0, got {min_amplitude_mm}")
    if not 0 <= relative_amplitude < 1:
        raise ValueError(f"relative_amplitude must lie in [0, 1), got {relative_amplitude}")
    if not 0 < still_fraction < 1:
        raise ValueError(f"still_fraction must lie in (0, 1), got {still_fraction}")
    if not 0 <= dwell_tolerance < 1:
        raise ValueError(f"dwell_tolerance must lie in [0, 1), got {dwell_tolerance}")
    if not min_pause_s >= 0:
        raise ValueError(f"min_pause_s must be >= 0, got {min_pause_s}")

    f = aperture.filtered_mm
    v = aperture.velocity_mm_s
    speed = np.abs(v)
    fps = aperture.fps
    runs = [(a, b) for a, b in aperture.runs() if b - a >= 3]
    # Imported here: scipy.signal costs ~0.6 s, which the web app's start-up does not need.
    from scipy.signal import find_peaks

    # 1. Maximal apertures, with a threshold relative to the whole recording.
    candidates = []
    for a, b in runs:
        pk, props = find_peaks(f[a:b], prominence=min_amplitude_mm)
        candidates.append((a, b, pk.astype(int) + a, np.asarray(props["prominences"], float)))
    all_prom = np.concatenate([c[3] for c in candidates]) if candidates else np.empty(0)
    if all_prom.size == 0:
        return Segmentation([], float(min_amplitude_mm), float("nan"), 0.0)
    threshold = max(min_amplitude_mm, relative_amplitude * float(np.percentile(all_prom, 90)))

    edge = max(2, round(EDGE_MARGIN_S * fps))  # frames
    per_run: list[tuple[int, int, list[int], list[int]]] = []
    opening_peak_speeds: list[float] = []
    for a, b, pk, prom in candidates:
        peaks = [int(p) for p in pk[prom >= threshold]]
        if not peaks:
            continue
        # The closures before the first and after the last maximum are searched
        # a few frames away from the run's edges, where a noisy rest could put
        # the minimum on the very edge frame, which is never a seen closure.
        first_lo = a + edge if a + edge < peaks[0] else a
        last_hi = b - 1 - edge if b - 1 - edge > peaks[-1] else b - 1
        bounds = [first_lo, *peaks, last_hi]
        mins = [lo + int(np.argmin(f[lo : hi + 1])) for lo, hi in pairwise(bounds)]
        per_run.append((a, b, peaks, mins))
        opening_peak_speeds += [float(np.max(v[mins[j] : p + 1])) for j, p in enumerate(peaks)]
    if not per_run:
        return Segmentation([], threshold, float("nan"), 0.0)
    # Still: slow compared with the taps, and clearly above the velocity noise.
    still = max(
        still_fraction * float(np.median(opening_peak_speeds)),
        NOISE_SDS_FOR_STILL * aperture.velocity_noise_mm_s,
    )
    still_mask = _still_mask(speed, still, max(1, round(MAX_NOISE_BLIP_S * fps)))

    # 2. Closures and their turns.
    run_valleys: list[list[_Valley]] = []
    inner_turns: list[float] = []
    for a, b, peaks, mins in per_run:
        valleys = []
        for j, i_min in enumerate(mins):
            lo = a if j == 0 else peaks[j - 1]
            hi = b - 1 if j == len(peaks) else peaks[j]
            adjacent = [f[p] - f[i_min] for p in (lo, hi) if p in peaks]
            first, last = _turn(
                f, speed, still_mask, i_min, lo, hi, still, dwell_tolerance * min(adjacent), edge
            )
            inner = 0 < j < len(peaks)
            seen = a < i_min < b - 1 and f[i_min - 1] >= f[i_min] <= f[i_min + 1]
            if not inner:
                p = peaks[0] if j == 0 else peaks[-1]
                at_rest = last > first or bool(still_mask[i_min])
                seen = (seen or at_rest) and f[p] - f[i_min] >= threshold
            else:
                inner_turns.append(last - first)
            valleys.append(_Valley(i_min, first, last, bool(seen), inner))
        run_valleys.append(valleys)
    turn = float(np.median(inner_turns)) if inner_turns else 0.0  # frames

    min_pause = min_pause_s * fps

    def has_pause(vl: _Valley) -> bool:
        return vl.last - vl.first - turn >= min_pause

    def turn_point(vl: _Valley) -> float:
        # The middle of the turn: the minimum is ill-defined on a flat, noisy closure.
        return (vl.first + vl.last) / 2 if vl.last > vl.first else _vertex(f, vl.i_min)

    def closing_end(vl: _Valley) -> float:
        return vl.first + turn / 2 if has_pause(vl) else turn_point(vl)

    def opening_start(vl: _Valley) -> float:
        return vl.last - turn / 2 if has_pause(vl) else turn_point(vl)

    # 3. Taps.
    filled = ~aperture.valid
    raw = aperture.distance_mm
    taps: list[Tap] = []
    prev_end_frame: float | None = None
    cycle = -1
    for (_a, _b, peaks, _mins), valleys in zip(per_run, run_valleys, strict=True):
        first_in_run = True
        prev_peak_j = -2
        for j, p in enumerate(peaks):
            v0, v1 = valleys[j], valleys[j + 1]
            if not (v0.seen and v1.seen):
                continue
            start, end = opening_start(v0), closing_end(v1)
            consecutive = prev_peak_j == j - 1
            if cycle < 0:
                cycle = 0
            elif consecutive:
                cycle += 1
            else:
                typical = float(np.median([tp.duration_s for tp in taps])) if taps else 0.0
                lost_s = (start - (prev_end_frame or start)) / fps
                cycle += 1 + (round(lost_s / typical) if typical > 0 else 0)
            pause = (start - closing_end(v0)) / fps if v0.inner else None
            closed = float(raw[v0.i_min])
            top = float(raw[p])
            amp = top - closed
            dur = (end - start) / fps
            t_max = _vertex(f, p) / fps
            open_dur = t_max - start / fps
            close_dur = end / fps - t_max
            i0, i1 = int(np.floor(start)), int(np.ceil(end))
            taps.append(
                Tap(
                    index=len(taps),
                    cycle_number=cycle,
                    i_start=round(start),
                    i_max=p,
                    i_end=round(end),
                    t_start_s=start / fps,
                    t_max_aperture_s=t_max,
                    t_end_s=end / fps,
                    closed_aperture_mm=closed,
                    max_aperture_mm=top,
                    amplitude_mm=amp,
                    duration_s=dur,
                    opening_duration_s=open_dur,
                    closing_duration_s=close_dur,
                    opening_velocity_mm_s_max=float(np.max(v[i0 : p + 1])),
                    closing_velocity_mm_s_max=float(np.max(-v[p : i1 + 1])),
                    opening_velocity_mm_s_mean=amp / open_dur if open_dur > 0 else float("nan"),
                    closing_velocity_mm_s_mean=(
                        (top - float(raw[v1.i_min])) / close_dur if close_dur > 0 else float("nan")
                    ),
                    pause_before_s=pause,
                    cycle_s=None if pause is None else pause + dur,
                    interval_s=None,
                    after_gap=first_in_run and len(taps) > 0,
                    filled_fraction=float(np.mean(filled[i0 : i1 + 1])),
                    reliable=not bool(filled[p] or filled[v0.i_min] or filled[v1.i_min]),
                )
            )
            first_in_run = False
            prev_peak_j = j
            prev_end_frame = end

    # Inter-tap intervals between consecutive taps (no gap in between).
    out = []
    for k, tap in enumerate(taps):
        nxt = taps[k + 1] if k + 1 < len(taps) else None
        if nxt is not None and nxt.cycle_number == tap.cycle_number + 1 and not nxt.after_gap:
            tap = replace(tap, interval_s=nxt.t_start_s - tap.t_start_s)
        out.append(tap)
    return Segmentation(out, threshold, still, turn / fps)


def segment_taps(
    aperture: Aperture,
    *,
    min_amplitude_mm: float = DEFAULT_MIN_AMPLITUDE_MM,
    relative_amplitude: float = DEFAULT_RELATIVE_AMPLITUDE,
    still_fraction: float = DEFAULT_STILL_FRACTION,
    dwell_tolerance: float = DEFAULT_DWELL_TOLERANCE,
    min_pause_s: float = DEFAULT_MIN_PAUSE_S,
) -> list[Tap]:
    """The complete taps of an aperture signal, in time order.

    Same parameters as :func:`segment_recording`; an empty list when there is
    no tap.
    """
    return segment_recording(
        aperture,
        min_amplitude_mm=min_amplitude_mm,
        relative_amplitude=relative_amplitude,
        still_fraction=still_fraction,
        dwell_tolerance=dwell_tolerance,
        min_pause_s=min_pause_s,
    ).taps


def still_periods(aperture: Aperture, *, still_velocity_mm_s: float) -> list[tuple[int, int]]:
    """Half-open frame ranges ``[start, stop)`` where the aperture speed is below a threshold.

    Frames inside gaps (NaN velocity) are never still.
    """
    speed = np.abs(aperture.velocity_mm_s)
    return true_runs(np.isfinite(speed) & (speed < still_velocity_mm_s))

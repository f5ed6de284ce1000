"""Test oracles for the compiled loops of ``core/_geometry.pyx``: the numpy formulations they
replaced, kept as they were (as ``markers_reference.py`` keeps the marker search's), so that a
test can compare the compiled results with them bit for bit."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from core.camera import FloatArray, _full_dist, distort_normalized, tilt_matrix
from core.clock import TrackTable
from core.sync import _segment_indices


def undistort_normalized_reference(
    xy_distorted: FloatArray, dist: FloatArray, *, max_iter: int = 50, tol: float = 1e-14
) -> FloatArray:
    """Invert :func:`distort_normalized` with Newton's method, ``(N, 2)`` -> ``(N, 2)``.

    Points where the iteration does not converge (outside the region where the
    distortion is invertible) come back as NaN rather than as a wrong value.
    """
    d = _full_dist(dist)
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tau_x, tau_y = d
    target = np.array(xy_distorted, dtype=np.float64, copy=True)
    if tau_x != 0.0 or tau_y != 0.0:
        inv_tilt = np.linalg.inv(tilt_matrix(tau_x, tau_y))
        v = inv_tilt @ np.vstack([target[:, 0], target[:, 1], np.ones(len(target))])
        target = np.column_stack([v[0] / v[2], v[1] / v[2]])
    x = target[:, 0].copy()
    y = target[:, 1].copy()
    tx, ty = target[:, 0], target[:, 1]
    converged = np.zeros(len(x), dtype=bool)
    for _ in range(max_iter):
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        num = 1 + k1 * r2 + k2 * r4 + k3 * r6
        den = 1 + k4 * r2 + k5 * r4 + k6 * r6
        rad = num / den
        drad = ((k1 + 2 * k2 * r2 + 3 * k3 * r4) * den - num * (k4 + 2 * k5 * r2 + 3 * k6 * r4)) / (
            den * den
        )
        fx = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4 - tx
        fy = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4 - ty
        j11 = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x + 2 * s1 * x + 4 * s2 * r2 * x
        j12 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y + 2 * s1 * y + 4 * s2 * r2 * y
        j21 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y + 2 * s3 * x + 4 * s4 * r2 * x
        j22 = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x + 2 * s3 * y + 4 * s4 * r2 * y
        det = j11 * j22 - j12 * j21
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = (j22 * fx - j12 * fy) / det
            dy = (-j21 * fx + j11 * fy) / det
        x = x - dx
        y = y - dy
        converged = np.abs(fx) + np.abs(fy) < tol
        if np.all(converged | ~np.isfinite(x)):
            break
    # A final residual check: a Newton step may have jumped to another branch.
    check = distort_normalized(np.column_stack([x, y]), dist)
    bad = ~np.all(np.abs(check - np.asarray(xy_distorted)) < 1e-9, axis=1)
    out = np.column_stack([x, y])
    out[bad] = np.nan
    return out


def points_at_times_reference(
    table: TrackTable, t_s: FloatArray, *, exact_tol_s: float = 1e-9
) -> tuple[FloatArray, NDArray[np.intp]]:
    """``core.clock.points_at_times`` as numpy computed it before ``core._geometry``."""
    pts, starts, nxt, prv = table.points, table.starts, table.nxt, table.prv
    ft, pt = table.frame_t, table.point_t
    n = len(ft)
    t = np.asarray(t_s, dtype=np.float64)
    if n == 0 or len(t) == 0:
        return np.zeros((0, 2)), np.zeros(len(t), dtype=np.intp)
    j = np.searchsorted(ft, t, side="right") - 1
    jc = np.clip(j, 0, n - 1)
    global_shutter = bool(np.all(pt == np.repeat(ft, np.diff(starts))))
    exact = (j >= 0) & (np.abs(t - ft[jc]) <= exact_tol_s) & global_shutter
    usable = exact | ((j >= 0) & (j < n - 1) & ~table.gap_after[jc])
    counts = np.where(usable, starts[jc + 1] - starts[jc], 0)
    idx, which = _segment_indices(starts[jc], counts)
    keep = exact[which] | (nxt[idx] >= 0)
    idx, which = idx[keep], which[keep]
    out = pts[idx].copy()
    moving = ~exact[which]
    a = idx[moving]
    tq = t[which[moving]]
    b = nxt[a]
    pm, c = prv[a], nxt[b]
    res = np.full((len(a), 2), np.nan)
    # Nodes: (pm, a, b, c) when all exist; else three of them.
    four = (pm >= 0) & (c >= 0)
    three_l = ~four & (pm >= 0)
    three_r = ~four & (c >= 0)
    for mask, nodes in (
        (four, (pm, a, b, c)),
        (three_l, (pm, a, b)),
        (three_r, (a, b, c)),
    ):
        if not np.any(mask):
            continue
        sel = [v[mask] for v in nodes]
        res[mask] = _lagrange_reference([pt[v] for v in sel], [pts[v] for v in sel], tq[mask])
    out[moving] = res
    ok = np.all(np.isfinite(out), axis=1)
    out, which = out[ok], which[ok]
    return out, np.bincount(which, minlength=len(t)).astype(np.intp)


def _lagrange_reference(ts: list[FloatArray], ps: list[FloatArray], t: FloatArray) -> FloatArray:
    """Lagrange interpolation through nodes ``(ts[k], ps[k])`` (each ``(M,)``, ``(M, 2)``) at ``t``."""
    out = np.zeros((len(t), 2))
    for k in range(len(ts)):
        w = np.ones(len(t))
        for m in range(len(ts)):
            if m != k:
                w *= (t - ts[m]) / (ts[k] - ts[m])
        out += w[:, None] * ps[k]
    return out

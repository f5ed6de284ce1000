# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled inner loops of the analysis' serial part (after detection).

Each function here is a loop that numpy ran as a dozen passes over arrays of
hundreds of thousands of elements; here it is one pass, without the GIL.  The
arithmetic is the numpy formulation's, operation for operation and in the
same order (``-ffp-contract=off`` keeps the compiler from fusing a multiply
and an add), so the results are bit for bit the former ones; the tests keep
the numpy formulations and compare.
"""

from libc.float cimport DBL_MAX
from libc.math cimport INFINITY, NAN, fabs, sqrt

import numpy as np


def nearest_epipolar(
    const double[:, ::1] line_r,
    const double[::1] norm_r,
    const double[:, ::1] r_pts,
    const double[::1] norm_l,
    const Py_ssize_t[::1] starts,
    const Py_ssize_t[::1] counts,
    const Py_ssize_t[::1] rows,
    double f_right,
    double f_left,
):
    """Symmetric epipolar distance (px) of left points to the nearest right point of a row.

    Element ``e`` of ``rows`` pairs left point ``e % L`` (``L = len(line_r)``)
    with the right points ``starts[r] .. starts[r] + counts[r] - 1`` of row
    ``r = rows[e]``; its distance to right point ``j`` is
    ``sqrt(0.5 * (d_l**2 + d_r**2))`` with ``alg = |x_j a + y_j b + c|`` (the
    left point's line ``(a, b, c)`` in the right image), ``d_r = alg / norm_r
    * f_right`` and ``d_l = alg / norm_l[j] * f_left``.  The minimum over the
    row is NaN when any distance is NaN (``np.minimum``), ``inf`` for an empty
    row.  Returns ``(len(rows),)`` float64.
    """
    cdef Py_ssize_t n = rows.shape[0], n_l = line_r.shape[0]
    out_arr = np.empty(n, dtype=np.float64)
    cdef double[::1] out = out_arr
    cdef Py_ssize_t e, l, j, j0, j1, r
    cdef double a, b, c, nr, alg, d_r, d_l, d, m
    with nogil:
        for e in range(n):
            r = rows[e]
            j0 = starts[r]
            j1 = j0 + counts[r]
            if j1 <= j0:
                out[e] = INFINITY
                continue
            l = e % n_l
            a = line_r[l, 0]
            b = line_r[l, 1]
            c = line_r[l, 2]
            nr = norm_r[l]
            m = 0.0
            for j in range(j0, j1):
                alg = r_pts[j, 0] * a
                alg = alg + r_pts[j, 1] * b
                alg = fabs(alg + c)
                d_r = alg / nr
                d_r = d_r * f_right
                d_l = alg / norm_l[j]
                d_l = d_l * f_left
                d = sqrt(0.5 * (d_l * d_l + d_r * d_r))
                if j == j0 or (m == m and (d != d or d < m)):  # a NaN, once there, stays
                    m = d
            out[e] = m
    return out_arr


def undistort(const double[:, ::1] xy, const double[::1] dist, int max_iter, double tol):
    """:func:`core.camera.undistort_normalized` for a lens without sensor tilt.

    ``xy`` ``(N, 2)`` distorted normalized points, ``dist`` the 14 OpenCV
    coefficients (``tau_x = tau_y = 0``).  Newton's method as there: every point
    takes each step until, after a step, every point has converged (``|f_x| +
    |f_y| < tol`` before it) or is not finite, at most ``max_iter`` steps; a
    point whose distortion does not give back its input within 1e-9 is NaN.
    Returns ``(N, 2)`` float64.
    """
    cdef Py_ssize_t n = xy.shape[0], i
    out_arr = np.empty((n, 2), dtype=np.float64)
    cdef double[:, ::1] out = out_arr
    cdef double k1 = dist[0], k2 = dist[1], p1 = dist[2], p2 = dist[3], k3 = dist[4]
    cdef double k4 = dist[5], k5 = dist[6], k6 = dist[7]
    cdef double s1 = dist[8], s2 = dist[9], s3 = dist[10], s4 = dist[11]
    # the scalar products numpy forms first (2 * k2 * r2 is (2 * k2) * r2)
    cdef double c2k2 = 2 * k2, c3k3 = 3 * k3, c2k5 = 2 * k5, c3k6 = 3 * k6
    cdef double c2p1 = 2 * p1, c2p2 = 2 * p2, c6p1 = 6 * p1, c6p2 = 6 * p2
    cdef double c2s1 = 2 * s1, c4s2 = 4 * s2, c2s3 = 2 * s3, c4s4 = 4 * s4
    cdef double x, y, tx, ty, r2, r4, r6, num, den, rad, drad, fx, fy
    cdef double j11, j12, j21, j22, det, dx, dy, radial, a1, xd, yd
    cdef int it, done
    with nogil:
        for i in range(n):
            out[i, 0] = xy[i, 0]
            out[i, 1] = xy[i, 1]
        for it in range(max_iter):
            done = 1
            for i in range(n):
                x = out[i, 0]
                y = out[i, 1]
                tx = xy[i, 0]
                ty = xy[i, 1]
                r2 = x * x + y * y
                r4 = r2 * r2
                r6 = r4 * r2
                num = 1.0 + k1 * r2 + k2 * r4 + k3 * r6
                den = 1.0 + k4 * r2 + k5 * r4 + k6 * r6
                rad = num / den
                drad = ((k1 + c2k2 * r2 + c3k3 * r4) * den - num * (k4 + c2k5 * r2 + c3k6 * r4)) / (
                    den * den
                )
                fx = x * rad + c2p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4 - tx
                fy = y * rad + p1 * (r2 + 2 * y * y) + c2p2 * x * y + s3 * r2 + s4 * r4 - ty
                j11 = rad + 2 * x * x * drad + c2p1 * y + c6p2 * x + c2s1 * x + c4s2 * r2 * x
                j12 = 2 * x * y * drad + c2p1 * x + c2p2 * y + c2s1 * y + c4s2 * r2 * y
                j21 = 2 * x * y * drad + c2p1 * x + c2p2 * y + c2s3 * x + c4s4 * r2 * x
                j22 = rad + 2 * y * y * drad + c6p1 * y + c2p2 * x + c2s3 * y + c4s4 * r2 * y
                det = j11 * j22 - j12 * j21
                dx = (j22 * fx - j12 * fy) / det
                dy = (-j21 * fx + j11 * fy) / det
                x = x - dx
                y = y - dy
                out[i, 0] = x
                out[i, 1] = y
                if not (fabs(fx) + fabs(fy) < tol or not (fabs(x) <= DBL_MAX)):
                    done = 0
            if done:
                break
        # A final residual check: a Newton step may have jumped to another branch.
        for i in range(n):
            x = out[i, 0]
            y = out[i, 1]
            r2 = x * x + y * y
            r4 = r2 * r2
            r6 = r4 * r2
            radial = (1.0 + k1 * r2 + k2 * r4 + k3 * r6) / (1.0 + k4 * r2 + k5 * r4 + k6 * r6)
            a1 = 2 * x * y
            xd = x * radial + p1 * a1 + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
            yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * a1 + s3 * r2 + s4 * r4
            if not (fabs(xd - xy[i, 0]) < 1e-9 and fabs(yd - xy[i, 1]) < 1e-9):
                out[i, 0] = NAN
                out[i, 1] = NAN
    return out_arr


def points_at_times(
    const double[:, ::1] pts,
    const Py_ssize_t[::1] starts,
    const Py_ssize_t[::1] nxt,
    const Py_ssize_t[::1] prv,
    const double[::1] frame_t,
    const double[::1] point_t,
    const unsigned char[::1] gap_after,
    const double[::1] t,
    const Py_ssize_t[::1] j_before,
    double exact_tol_s,
):
    """:func:`core.clock.points_at_times` after its ``searchsorted``: the points of each instant.

    ``j_before[s]`` is the last frame at or before instant ``t[s]`` (-1 before the
    first).  An instant within ``exact_tol_s`` of its frame's time gives that frame's
    points as they are when every point's instant is its frame's (global shutter);
    otherwise each point of frame ``j`` linked to one of frame ``j + 1`` is
    interpolated with the Lagrange polynomial through ``(prv, a, b, nxt)`` of its
    track, else the three of them it has (none across a gap, before the first frame
    or after the last); non-finite results are left out.  The weights and sums are
    ``_lagrange``'s: ``w_k = 1 · Π_m (t − t_m) / (t_k − t_m)``, ``p = 0 + Σ_k w_k p_k``.
    Returns ``(points (M, 2), counts (S,))``.
    """
    cdef Py_ssize_t n = frame_t.shape[0], n_t = t.shape[0], s, f, jc, i, a, b, pm, c
    cdef Py_ssize_t total = 0, m_out = 0, k, m, n_nodes
    cdef bint global_shutter = True, exact, usable
    cdef double tq, w, x, y
    cdef Py_ssize_t nodes[4]
    cdef double tn[4]
    counts_arr = np.zeros(n_t, dtype=np.intp)
    cdef Py_ssize_t[::1] counts = counts_arr
    with nogil:
        for f in range(n):
            for i in range(starts[f], starts[f + 1]):
                if not (point_t[i] == frame_t[f]):
                    global_shutter = False
        for s in range(n_t):
            jc = min(max(j_before[s], 0), n - 1)
            total += starts[jc + 1] - starts[jc]
    out_arr = np.empty((total, 2), dtype=np.float64)
    cdef double[:, ::1] out = out_arr
    with nogil:
        for s in range(n_t):
            jc = min(max(j_before[s], 0), n - 1)
            tq = t[s]
            exact = j_before[s] >= 0 and fabs(tq - frame_t[jc]) <= exact_tol_s and global_shutter
            usable = exact or (j_before[s] >= 0 and j_before[s] < n - 1 and not gap_after[jc])
            if not usable:
                continue
            for i in range(starts[jc], starts[jc + 1]):
                if exact:
                    x = pts[i, 0]
                    y = pts[i, 1]
                else:
                    a = i
                    b = nxt[a]
                    if b < 0:
                        continue
                    pm = prv[a]
                    c = nxt[b]
                    if pm >= 0 and c >= 0:
                        nodes[0] = pm
                        nodes[1] = a
                        nodes[2] = b
                        nodes[3] = c
                        n_nodes = 4
                    elif pm >= 0:
                        nodes[0] = pm
                        nodes[1] = a
                        nodes[2] = b
                        n_nodes = 3
                    elif c >= 0:
                        nodes[0] = a
                        nodes[1] = b
                        nodes[2] = c
                        n_nodes = 3
                    else:
                        continue  # a track of two samples: nothing (NaN, left out)
                    for k in range(n_nodes):
                        tn[k] = point_t[nodes[k]]
                    x = 0.0
                    y = 0.0
                    for k in range(n_nodes):
                        w = 1.0
                        for m in range(n_nodes):
                            if m != k:
                                w = w * ((tq - tn[m]) / (tn[k] - tn[m]))
                        x = x + w * pts[nodes[k], 0]
                        y = y + w * pts[nodes[k], 1]
                if fabs(x) <= DBL_MAX and fabs(y) <= DBL_MAX:
                    out[m_out, 0] = x
                    out[m_out, 1] = y
                    m_out += 1
                    counts[s] += 1
    return out_arr[:m_out].copy(), counts_arr

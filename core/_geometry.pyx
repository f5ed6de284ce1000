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


def truncated_epipolar_costs(
    const double[::1] la,
    const double[::1] lb,
    const double[::1] lc,
    const double[::1] norm_r,
    const double[:, ::1] r_pts,
    const double[::1] norm_l,
    const Py_ssize_t[::1] starts,
    const Py_ssize_t[::1] counts,
    const Py_ssize_t[::1] rows,
    double f_right,
    double f_left,
    double gate_px,
    double gate_sq,
):
    """:func:`core.sync._epipolar_costs`' truncated cost ``min(d, gate)**2 / gate_sq``.

    Element ``e`` of ``rows`` pairs left point ``l = e % L`` (``L = len(la)``, its line
    ``(la, lb, lc)`` in the right image) with the right points ``starts[r] ..
    starts[r] + counts[r] - 1`` of row ``r = rows[e]``.  For right point ``j``,
    ``alg = la * x_j + lc + lb * y_j`` (summed in that order, as einsum sums the
    3-term dot product), ``d_r = alg / norm_r * f_right``, ``d_l = alg / norm_l[j] *
    f_left``, ``s_j = d_l**2 + d_r**2``, and ``d = sqrt(0.5 * min_j s_j)``, the least
    leaving NaNs out (``np.fmin``); ``inf`` when none is finite.  A right point whose
    ``|alg|`` alone puts it beyond the gate (``d_r >= sqrt(2) · gate`` with a margin of
    1e-6 that covers every rounding) is not measured: it could only give a ``d`` above
    the gate, whose cost is the gate's, as an empty row's.  Returns ``(len(rows),)``.
    """
    cdef Py_ssize_t n = rows.shape[0], n_l = la.shape[0], e, l, j, j0, j1, r, c
    out_arr = np.empty(n, dtype=np.float64)
    cdef double[::1] out = out_arr
    thr_arr = np.empty(n_l, dtype=np.float64)
    cdef double[::1] thr = thr_arr
    cdef double a, b, cc, nr, t, alg, d_r, d_l, s, d
    # Beyond |alg| > thr[l], d_r > sqrt(2) · gate: s_j / 2 > gate**2.
    cdef double reach = gate_px * sqrt(2.0) * (1.0 + 1e-6)
    with nogil:
        for l in range(n_l):
            thr[l] = reach * norm_r[l] / f_right if gate_px >= 1e-100 else INFINITY
        e = 0
        while e < n:
            for l in range(n_l):
                r = rows[e]
                j0 = starts[r]
                j1 = j0 + counts[r]
                a = la[l]
                b = lb[l]
                cc = lc[l]
                nr = norm_r[l]
                t = thr[l]
                s = NAN
                for j in range(j0, j1):
                    alg = a * r_pts[j, 0]
                    alg = alg + cc
                    alg = alg + b * r_pts[j, 1]
                    if fabs(alg) > t:
                        continue
                    d_r = alg / nr
                    d_r = d_r * f_right
                    d_l = alg / norm_l[j]
                    d_l = d_l * f_left
                    d_r = d_r * d_r
                    d_l = d_l * d_l
                    d_l = d_l + d_r
                    if s != s or d_l < s:  # np.fmin: a NaN gives way to the other
                        s = d_l
                d = sqrt(0.5 * s)
                if not d < gate_px:  # also NaN, inf: no partner within the gate
                    d = gate_px
                out[e] = d * d / gate_sq
                e += 1
    return out_arr


cdef struct Lens:
    double k1, k2, p1, p2, k3, fx, fy, cx, cy
    bint has_k3, tangential


cdef Lens _lens(tuple lens):
    cdef Lens out
    out.k1, out.k2, out.p1, out.p2, out.k3, out.fx, out.fy, out.cx, out.cy = lens
    out.has_k3 = out.k3 != 0.0
    out.tangential = out.p1 != 0.0 or out.p2 != 0.0
    return out


cdef inline bint _project(
    const Lens* c, double x, double y, double z, double* u, double* v
) noexcept nogil:
    """``core.triangulation._Projector`` of one camera-frame point: its operations in its
    order.  False when the point is so far off axis that it must go through
    ``Camera.project``."""
    cdef double r2, r4, radial, xd, yd, a1
    x = x / z
    y = y / z
    if z <= 0:
        x = NAN
        y = NAN
    r2 = x * x + y * y
    if r2 > 1e30:  # _Projector._MAX_R2
        return False
    r4 = r2 * r2
    radial = 1 + c.k1 * r2 + c.k2 * r4
    if c.has_k3:
        radial = radial + c.k3 * (r4 * r2)
    xd = x * radial
    yd = y * radial
    if c.tangential:
        a1 = 2 * x * y
        xd = xd + c.p1 * a1 + c.p2 * (r2 + 2 * x * x)
        yd = yd + c.p1 * (r2 + 2 * y * y) + c.p2 * a1
    u[0] = xd * c.fx + c.cx
    v[0] = yd * c.fy + c.cy
    return True


def refine_system(
    const double[:, ::1] cam_left,
    const double[:, ::1] cam_right,
    tuple lens_left,
    tuple lens_right,
    const double[:, ::1] obs,
    const double[::1] step_mm,
    const double[::1] lam,
    double[:, :, ::1] damped,
    double[:, ::1] jtr,
    double[::1] cost,
):
    """One Gauss–Newton system of :func:`core.triangulation._refine` for ``n`` points.

    ``cam_left``, ``cam_right`` ``(3, 4n)``: camera-frame coordinates of the points and of
    the points moved by ``step_mm`` along x, y and z (``_Projector._to_camera`` of the
    stacked ``(4n, 3)``); ``lens_*`` ``(k1, k2, p1, p2, k3, fx, fy, cx, cy)``; ``obs``
    ``(n, 4)`` observed left u, v, right u, v.  Fills ``damped`` ``(n, 3, 3)`` (``J^T J +
    lam · trace · I``), ``jtr`` ``(n, 3)`` and ``cost`` ``(n,)`` (the squared residual
    length), each summed in the order of the numpy formulation.  Returns False when a
    point needs ``Camera.project`` (what was filled is then not to be used).
    """
    cdef Py_ssize_t n = obs.shape[0], i, k, j, m, c, e
    if n == 0:
        return True
    cdef Lens cams[2]
    cams[0] = _lens(lens_left)
    cams[1] = _lens(lens_right)
    cdef const double* cam_of[2]
    cam_of[0] = &cam_left[0, 0]
    cam_of[1] = &cam_right[0, 0]
    cdef Py_ssize_t row = 4 * n  # the stride of a coordinate
    cdef double p[4][4]  # p[c][k]: pixel coordinate c of point k (0: x, 1..3: x + a step)
    cdef double J[4][3]
    cdef double r[4]
    cdef double jtj[3][3]
    cdef double h, tr, on, off
    cdef bint fast = True
    with nogil:
        for i in range(n):
            h = step_mm[i]
            for k in range(4):
                e = k * n + i
                for c in range(2):
                    fast = fast and _project(
                        &cams[c], cam_of[c][e], cam_of[c][row + e], cam_of[c][2 * row + e],
                        &p[2 * c][k], &p[2 * c + 1][k],
                    )
            if not fast:
                break
            for c in range(4):
                for k in range(3):
                    J[c][k] = (p[c][k + 1] - p[c][0]) / h
                r[c] = p[c][0] - obs[i, c]
            for j in range(3):
                for m in range(j, 3):
                    jtj[j][m] = (
                        J[0][j] * J[0][m] + J[1][j] * J[1][m] + J[2][j] * J[2][m] + J[3][j] * J[3][m]
                    )
                jtr[i, j] = J[0][j] * r[0] + J[1][j] * r[1] + J[2][j] * r[2] + J[3][j] * r[3]
            tr = jtj[0][0] + jtj[1][1] + jtj[2][2]
            on = lam[i] * tr
            off = lam[i] * 0.0 * tr
            for j in range(3):
                for m in range(j, 3):
                    damped[i, j, m] = jtj[j][m] + (on if j == m else off)
                    damped[i, m, j] = damped[i, j, m]
            cost[i] = r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3]
    return fast


def refine_accept(
    const double[:, ::1] cam_left,
    const double[:, ::1] cam_right,
    tuple lens_left,
    tuple lens_right,
    const double[:, ::1] obs,
    const double[::1] cost,
    const double[:, ::1] x_new,
    const double[:, ::1] delta,
    double[:, ::1] x,
    double[::1] lam,
    double tol_mm,
):
    """The step of :func:`core.triangulation._refine`: keep ``x_new`` where it costs no
    more than ``cost`` (and its residuals are finite), and update the damping.

    ``cam_*`` ``(3, n)``: camera-frame coordinates of ``x_new``.  Updates ``x`` and ``lam``
    in place.  Returns None when a point needs ``Camera.project`` (nothing updated), else
    whether the refinement is done (every accepted step below ``tol_mm`` in each
    coordinate, or none accepted).
    """
    cdef Py_ssize_t n = obs.shape[0], i, c, k
    if n == 0:
        return True
    cdef Lens cams[2]
    cams[0] = _lens(lens_left)
    cams[1] = _lens(lens_right)
    cdef const double* cam_of[2]
    cam_of[0] = &cam_left[0, 0]
    cam_of[1] = &cam_right[0, 0]
    cdef double p[4]
    cdef double rn, cost_new
    cdef bint better, finite, any_better = False, small = True, fast = True
    with nogil:
        for i in range(n):
            for c in range(2):
                fast = fast and _project(
                    &cams[c], cam_of[c][i], cam_of[c][n + i], cam_of[c][2 * n + i],
                    &p[2 * c], &p[2 * c + 1],
                )
    if not fast:
        return None
    with nogil:
        for i in range(n):
            for c in range(2):
                _project(
                    &cams[c], cam_of[c][i], cam_of[c][n + i], cam_of[c][2 * n + i],
                    &p[2 * c], &p[2 * c + 1],
                )
            finite = True
            cost_new = 0.0
            for c in range(4):
                rn = p[c] - obs[i, c]
                finite = finite and fabs(rn) <= DBL_MAX
                cost_new = rn * rn if c == 0 else cost_new + rn * rn
            better = cost_new <= cost[i] and finite
            if better:
                any_better = True
                for k in range(3):
                    x[i, k] = x_new[i, k]
                    if not fabs(delta[i, k]) < tol_mm:
                        small = False
                lam[i] = lam[i] * 0.1
            else:
                lam[i] = lam[i] * 10.0
    return small or not any_better


def link_frames(
    const double[:, ::1] pts,
    const Py_ssize_t[::1] counts,
    Py_ssize_t[::1] nxt,
    double max_step_px,
):
    """:func:`core.sync.link_points` frame pair by frame pair: fills ``nxt`` (flat successor
    index or -1; all -1 on entry).

    Pair ``j`` predicts each detection of frame ``j`` from its predecessor (``2 p - p_prev``,
    constant velocity; as found without one) and measures ``d = sqrt(dx² + dy²)`` to each
    detection of frame ``j + 1`` (``np.linalg.norm``'s sum); the pairs within
    ``max_step_px`` are the links when no detection has two of them, else the Hungarian
    method (``scipy.optimize.linear_sum_assignment``) decides on ``d``, the pairs beyond
    the gate costing 1e9 and left out.
    """
    cdef Py_ssize_t n = counts.shape[0], n_pts = pts.shape[0], j, a, b, s0, s1, ca, cb, i, k
    cdef bint clash
    cdef double px, py, dx, dy, d
    prv_arr = np.full(n_pts, -1, dtype=np.intp)
    cdef Py_ssize_t[::1] prv = prv_arr
    cdef Py_ssize_t max_count = 0
    for j in range(n):
        max_count = max(max_count, counts[j])
    dist_arr = np.empty(max_count * max_count, dtype=np.float64)
    cdef double[::1] dist = dist_arr
    cand_arr = np.zeros(n_pts, dtype=np.intp)  # gated candidates of each detection
    cdef Py_ssize_t[::1] cand = cand_arr
    cdef double[:, ::1] cost
    linear_sum_assignment = None
    fast_ok = max_step_px < 1e6  # gated costs far below the 1e9 of excluded pairs
    s0 = 0
    for j in range(n - 1):
        ca = counts[j]
        cb = counts[j + 1]
        s1 = s0 + ca
        if ca == 0 or cb == 0:
            s0 = s1
            continue
        clash = not fast_ok
        with nogil:
            for a in range(s0, s1):
                cand[a] = 0
            for b in range(s1, s1 + cb):
                cand[b] = 0
            for a in range(s0, s1):
                if prv[a] >= 0:
                    px = 2 * pts[a, 0] - pts[prv[a], 0]
                    py = 2 * pts[a, 1] - pts[prv[a], 1]
                else:
                    px = pts[a, 0]
                    py = pts[a, 1]
                for b in range(s1, s1 + cb):
                    dx = px - pts[b, 0]
                    dy = py - pts[b, 1]
                    d = sqrt(dx * dx + dy * dy)
                    dist[(a - s0) * cb + (b - s1)] = d
                    if d <= max_step_px:
                        cand[a] += 1
                        cand[b] += 1
            for i in range(s0, s1 + cb):
                if cand[i] > 1:
                    clash = True
            if not clash:
                for a in range(s0, s1):
                    for b in range(s1, s1 + cb):
                        if dist[(a - s0) * cb + (b - s1)] <= max_step_px:
                            nxt[a] = b
                            prv[b] = a
        if clash:
            if linear_sum_assignment is None:
                from scipy.optimize import linear_sum_assignment
            cost_arr = np.empty((ca, cb))
            cost = cost_arr
            for i in range(ca):
                for k in range(cb):
                    d = dist[i * cb + k]
                    cost[i, k] = d if d <= max_step_px else 1e9
            rows, cols = linear_sum_assignment(cost_arr)
            for i, k in zip(rows.tolist(), cols.tolist()):
                if cost[i, k] < 1e9:
                    nxt[s0 + i] = s1 + k
                    prv[s1 + k] = s0 + i
        s0 = s1

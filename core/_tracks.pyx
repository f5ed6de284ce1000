# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""The tracker's frame-to-frame loop (:func:`core.tracks.build_tracklets`), compiled.

A frame offers the tracker a handful of stereo candidates and detections and
meets a handful of tracks: in Python, the loop was mostly the cost of the
interpreter on scalars (prediction, the merged-image check, the gated
assignment, single-view continuation, new tracks). Here it is C on plain
doubles, with the operations of the Python formulation in the same order
(``-ffp-contract=off`` keeps the compiler from fusing a multiply and an add),
so the tracklets are bit for bit the former ones.

Three steps stay calls into Python, each where it decides bits or ties that
only that call gives:

- the Hungarian method (scipy's ``linear_sum_assignment``, then numpy's
  ``argsort`` of the assigned costs) when gates overlap or two pairs are
  equally close;
- in single-view continuation, ``Camera.to_camera`` and ``Camera.backproject``
  of the one prediction and detection, and numpy's ``dot`` along the ray:
  their small matrix products go through BLAS, whose order of operations
  (fused or not, by the CPU's kernel) is not the plain sum's;
- ``Camera.project`` for a camera whose sensor is tilted (Scheimpflug).

Kinds: 0 stereo, 1 left only, 2 right only (``core.tracks.STEREO``...).
"""

from cpython.mem cimport PyMem_Free, PyMem_Malloc, PyMem_Realloc
from libc.math cimport INFINITY, NAN, isfinite, sqrt
from libc.stdint cimport int64_t
from libc.string cimport memset

import numpy as np
from scipy.optimize import linear_sum_assignment

cdef double BIG_COST = 1e6  # gated-out pairs in the assignment


cdef struct Cam:
    double r[9]  # R_cam_from_world, row by row
    double t[3]
    double fx, fy, cx, cy
    double d[12]  # k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4
    double f_px  # mean focal length, for the single-view gate
    bint tilted  # tau_x or tau_y: Camera.project does it


cdef struct Track:
    double x, y, z, vx, vy, vz
    Py_ssize_t last_frame, last_stereo


cdef struct Rec:  # one frame of one track
    Py_ssize_t track, frame
    int kind
    double x, y, z, reproj, u, v


cdef int _cam_init(Cam* c, cam) except -1:
    cdef Py_ssize_t i
    r = cam.R_cam_from_world.tolist()
    t = cam.t_cam_from_world_mm.tolist()
    for i in range(9):
        c.r[i] = r[i // 3][i % 3]
    for i in range(3):
        c.t[i] = t[i]
    K = cam.K
    c.fx, c.fy, c.cx, c.cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    c.f_px = 0.5 * (c.fx + c.fy)
    dist = cam.dist.tolist() + [0.0] * (14 - cam.dist.shape[0])
    for i in range(12):
        c.d[i] = dist[i]
    c.tilted = dist[12] != 0.0 or dist[13] != 0.0
    return 0


cdef inline void _distort_px(const Cam* c, double x, double y, double* u, double* v) noexcept nogil:
    """``core.camera.distort_normalized`` and ``normalized_to_pixels`` of one point, untilted."""
    cdef double rr2 = x * x + y * y
    cdef double rr4 = rr2 * rr2
    cdef double rr6 = rr4 * rr2
    cdef double radial = (1 + c.d[0] * rr2 + c.d[1] * rr4 + c.d[4] * rr6) / (
        1 + c.d[5] * rr2 + c.d[6] * rr4 + c.d[7] * rr6
    )
    cdef double a1 = 2 * x * y
    cdef double xd = x * radial + c.d[2] * a1 + c.d[3] * (rr2 + 2 * x * x) + c.d[8] * rr2 + c.d[9] * rr4
    cdef double yd = y * radial + c.d[2] * (rr2 + 2 * y * y) + c.d[3] * a1 + c.d[10] * rr2 + c.d[11] * rr4
    u[0] = xd * c.fx + c.cx
    v[0] = yd * c.fy + c.cy


cdef int _project(const Cam* c, cam, double px, double py, double pz, double* u, double* v) except -1:
    """Distorted pixel of a world point (mm), NaN behind the camera: ``Camera.project`` with
    the camera frame as plain sums (as the merged-image check always computed it)."""
    if c.tilted:
        u[0], v[0] = cam.project(np.array([[px, py, pz]]))[0].tolist()
        return 0
    cdef double z = px * c.r[6] + py * c.r[7] + pz * c.r[8] + c.t[2]
    if not z > 0:
        u[0] = NAN
        v[0] = NAN
        return 0
    cdef double x = (px * c.r[0] + py * c.r[1] + pz * c.r[2] + c.t[0]) / z
    cdef double y = (px * c.r[3] + py * c.r[4] + pz * c.r[5] + c.t[1]) / z
    _distort_px(c, x, y, u, v)
    return 0


cdef inline double _distance(double px, double py, double pz, const double* q) noexcept nogil:
    # The float64 operations of np.linalg.norm(p - q) over the last axis, in its order.
    cdef double dx = px - q[0], dy = py - q[1], dz = pz - q[2]
    return sqrt(dx * dx + dy * dy + dz * dz)


cdef class _Work:
    """The loop's memory: tracks, records and per-frame scratch (C arrays, grown by doubling)."""

    cdef Track* tracks
    cdef Py_ssize_t n_tracks, cap_tracks
    cdef Py_ssize_t* active
    cdef Rec* recs
    cdef Py_ssize_t n_recs, cap_recs
    # per active track
    cdef double* preds
    cdef double* gates
    cdef char* assigned
    cdef Py_ssize_t* recent
    cdef double* pu
    cdef double* pv
    cdef char* close
    cdef Py_ssize_t cap_active
    # per pair of the assignment
    cdef double* pd
    cdef Py_ssize_t* pr
    cdef Py_ssize_t* pc
    cdef Py_ssize_t cap_pairs
    # per detection and candidate of a frame
    cdef char* used_l
    cdef char* used_r
    cdef Py_ssize_t* free
    cdef Py_ssize_t cap_l, cap_r, cap_c

    def __dealloc__(self):
        PyMem_Free(self.tracks)
        PyMem_Free(self.active)
        PyMem_Free(self.recs)
        PyMem_Free(self.preds)
        PyMem_Free(self.gates)
        PyMem_Free(self.assigned)
        PyMem_Free(self.recent)
        PyMem_Free(self.pu)
        PyMem_Free(self.pv)
        PyMem_Free(self.close)
        PyMem_Free(self.pd)
        PyMem_Free(self.pr)
        PyMem_Free(self.pc)
        PyMem_Free(self.used_l)
        PyMem_Free(self.used_r)
        PyMem_Free(self.free)


cdef void* _grow(void* p, Py_ssize_t n, size_t size) except NULL:
    cdef void* q = PyMem_Realloc(p, (n if n > 0 else 1) * size)
    if q == NULL:
        raise MemoryError()
    return q


cdef int _reserve_tracks(_Work w, Py_ssize_t n) except -1:
    if n <= w.cap_tracks:
        return 0
    cdef Py_ssize_t cap = max(n, 2 * w.cap_tracks, 16)
    w.tracks = <Track*>_grow(w.tracks, cap, sizeof(Track))
    w.active = <Py_ssize_t*>_grow(w.active, cap, sizeof(Py_ssize_t))
    w.cap_tracks = cap
    return 0


cdef int _reserve_active(_Work w, Py_ssize_t n) except -1:
    if n <= w.cap_active:
        return 0
    cdef Py_ssize_t cap = max(n, 2 * w.cap_active, 16)
    w.preds = <double*>_grow(w.preds, 3 * cap, sizeof(double))
    w.gates = <double*>_grow(w.gates, cap, sizeof(double))
    w.assigned = <char*>_grow(w.assigned, cap, sizeof(char))
    w.recent = <Py_ssize_t*>_grow(w.recent, cap, sizeof(Py_ssize_t))
    w.pu = <double*>_grow(w.pu, cap, sizeof(double))
    w.pv = <double*>_grow(w.pv, cap, sizeof(double))
    w.close = <char*>_grow(w.close, cap, sizeof(char))
    w.cap_active = cap
    return 0


cdef int _reserve_pairs(_Work w, Py_ssize_t n) except -1:
    if n <= w.cap_pairs:
        return 0
    cdef Py_ssize_t cap = max(n, 2 * w.cap_pairs, 64)
    w.pd = <double*>_grow(w.pd, cap, sizeof(double))
    w.pr = <Py_ssize_t*>_grow(w.pr, cap, sizeof(Py_ssize_t))
    w.pc = <Py_ssize_t*>_grow(w.pc, cap, sizeof(Py_ssize_t))
    w.cap_pairs = cap
    return 0


cdef int _record(
    _Work w, Py_ssize_t track, Py_ssize_t frame, int kind,
    double x, double y, double z, double reproj, double u, double v,
) except -1:
    cdef Py_ssize_t cap
    if w.n_recs == w.cap_recs:
        cap = max(2 * w.cap_recs, 256)
        w.recs = <Rec*>_grow(w.recs, cap, sizeof(Rec))
        w.cap_recs = cap
    cdef Rec* r = &w.recs[w.n_recs]
    r.track, r.frame, r.kind = track, frame, kind
    r.x, r.y, r.z, r.reproj, r.u, r.v = x, y, z, reproj, u, v
    w.n_recs += 1
    return 0


cdef inline void _add_stereo(Track* tr, Py_ssize_t frame, double x, double y, double z) noexcept nogil:
    cdef double dt = <double>(frame - tr.last_frame)
    # w * new_v + (1 - w) * v with w = 1 (1.0 * a == a exactly).
    tr.vx = (x - tr.x) / dt + 0.0 * tr.vx
    tr.vy = (y - tr.y) / dt + 0.0 * tr.vy
    tr.vz = (z - tr.z) / dt + 0.0 * tr.vz
    tr.x, tr.y, tr.z = x, y, z
    tr.last_frame = frame
    tr.last_stereo = frame


cdef inline void _add_single_view(Track* tr, Py_ssize_t frame, double x, double y, double z) noexcept nogil:
    cdef double dt = <double>(frame - tr.last_frame)
    # Single-view depth is provisional: let it steer the velocity only gently.
    tr.vx = 0.5 * ((x - tr.x) / dt) + 0.5 * tr.vx
    tr.vy = 0.5 * ((y - tr.y) / dt) + 0.5 * tr.vy
    tr.vz = 0.5 * ((z - tr.z) / dt) + 0.5 * tr.vz
    tr.x, tr.y, tr.z = x, y, z
    tr.last_frame = frame


cdef Py_ssize_t _assign(
    _Work w, Py_ssize_t n_t, const double* preds, const double* gates,
    const double[:, ::1] cand, Py_ssize_t c0, Py_ssize_t n_c,
) except -1:
    """Gated global assignment of tracks to stereo candidates, closest pairs first.

    The same pairs, in the same order, as the Hungarian method on the gated 3D
    distances (``dist`` where ``dist <= gate``, else a prohibitive cost), with
    the gated-out pairs dropped and the rest sorted by distance. When every
    track has at most one candidate within its gate and every candidate lies
    within at most one gate, the optimum is exactly those pairs (any
    assignment leaving one out costs a whole prohibitive cost more), so the
    Hungarian method is only run when gates overlap, or when two pairs are
    equally close (so that their order is decided as numpy's ``argsort`` does).
    Leaves the pairs in ``w.pr``, ``w.pc``; returns how many.
    """
    cdef Py_ssize_t r, c, n = 0, a, b, rr, cc
    cdef double px, py, pz, g, dx, dy, dz, d, total
    cdef bint fast
    _reserve_pairs(w, n_t * n_c)
    for r in range(n_t):
        px, py, pz, g = preds[3 * r], preds[3 * r + 1], preds[3 * r + 2], gates[r]
        for c in range(n_c):
            # |dx| > g implies dist > g (sqrt(fl(dx * dx)) == |dx|, sums only grow).
            dx = px - cand[c0 + c, 0]
            if dx > g or -dx > g:
                continue
            dy = py - cand[c0 + c, 1]
            if dy > g or -dy > g:
                continue
            dz = pz - cand[c0 + c, 2]
            d = sqrt(dx * dx + dy * dy + dz * dz)  # as _distance, inline
            if d <= g:
                w.pd[n], w.pr[n], w.pc[n] = d, r, c
                n += 1
    if n == 0:
        return 0
    fast = n <= n_t and n <= n_c
    total = 0.0  # Python's sum of floats (3.11: in order, from 0)
    a = 0
    while fast and a < n:
        total = total + w.pd[a]
        for b in range(a + 1, n):
            if w.pr[a] == w.pr[b] or w.pc[a] == w.pc[b] or w.pd[a] == w.pd[b]:
                fast = False  # gates overlap, or a tie: the order is not unambiguous
                break
        a += 1
    # The argument needs the prohibitive cost to outweigh all gated distances together.
    if fast and total < 0.5 * BIG_COST:
        for a in range(1, n):  # by distance (all different)
            d, rr, cc = w.pd[a], w.pr[a], w.pc[a]
            b = a
            while b > 0 and w.pd[b - 1] > d:
                w.pd[b], w.pr[b], w.pc[b] = w.pd[b - 1], w.pr[b - 1], w.pc[b - 1]
                b -= 1
            w.pd[b], w.pr[b], w.pc[b] = d, rr, cc
        return n
    cost_arr = np.empty((n_t, n_c))
    cdef double[:, ::1] cost = cost_arr
    for r in range(n_t):
        for c in range(n_c):
            d = _distance(preds[3 * r], preds[3 * r + 1], preds[3 * r + 2], &cand[c0 + c, 0])
            cost[r, c] = d if d <= gates[r] else BIG_COST
    r_idx, c_idx = linear_sum_assignment(cost_arr)
    order = np.argsort(cost_arr[r_idx, c_idx])
    n = 0
    for rr, cc in zip(r_idx[order].tolist(), c_idx[order].tolist()):
        if cost[rr, cc] < BIG_COST:
            w.pr[n], w.pc[n] = rr, cc
            n += 1
    return n


cdef bint _block_merged(
    _Work w, Py_ssize_t n_t, Py_ssize_t frame, const Cam* cams, cams_py,
    const double* limits, const double* const* dets, const unsigned char* const* fitted,
    const Py_ssize_t* n_dets, char* const* used,
) except -1:
    """Mark used (unavailable) the detections of a camera in which two established
    tracks' predictions project closer than ``merge_px`` (their images touch);
    whether any was."""
    cdef Py_ssize_t r, k, a, b, j, n_rec = 0, ci
    cdef double limit, du, dv, x, y
    cdef bint blocked = False, any_close
    for r in range(n_t):
        if frame - w.tracks[w.active[r]].last_stereo <= 3:
            w.recent[n_rec] = r
            n_rec += 1
    if n_rec < 2:
        return False
    for ci in range(2):
        limit = limits[ci]
        if n_dets[ci] == 0 or not limit > 0:
            continue
        for k in range(n_rec):
            r = w.recent[k]
            _project(&cams[ci], cams_py[ci], w.preds[3 * r], w.preds[3 * r + 1], w.preds[3 * r + 2],
                     &w.pu[k], &w.pv[k])
            w.close[k] = 0
        # each pair once; |du| >= limit implies a distance >= limit (sqrt of a sum of squares)
        any_close = False
        for a in range(n_rec):
            for b in range(a + 1, n_rec):
                du = w.pu[a] - w.pu[b]
                dv = w.pv[a] - w.pv[b]
                if du < limit and -du < limit and sqrt(du * du + dv * dv) < limit:
                    w.close[a] = w.close[b] = 1
                    any_close = True
        if not any_close:
            continue
        for j in range(n_dets[ci]):
            if fitted[ci][j]:
                continue  # measured in the merged image (core.merged): not pulled by the other
            x = dets[ci][2 * j]
            y = dets[ci][2 * j + 1]
            for k in range(n_rec):
                if w.close[k] and sqrt((x - w.pu[k]) * (x - w.pu[k]) + (y - w.pv[k]) * (y - w.pv[k])) < limit:
                    used[ci][j] = 1
                    blocked = True
                    break
    return blocked


cdef int _continue_single_view(
    _Work w, Py_ssize_t t, Py_ssize_t frame, const double* pred, double gate_mm,
    const Cam* cams, cams_py, const double* const* dets, const Py_ssize_t* n_dets,
    char* const* used, dets_py, const Py_ssize_t* det_offsets,
) except -1:
    """Continue track ``t`` on the detection nearest to its projected prediction in one
    camera; marks the detection used when the track takes it."""
    cdef Py_ssize_t ci, j, i, best_ci = -1, best_j = -1
    cdef double best = 0.0, xc, yc, zc, u, v, gate_px, depth, d, m, dx, dy, s
    cdef double ox, oy, oz, ex, ey, ez
    cdef Track* tr
    pred_arr = None
    for ci in range(2):
        if n_dets[ci] == 0:
            continue
        if pred_arr is None:
            pred_arr = np.array([[pred[0], pred[1], pred[2]]])
        cam = cams_py[ci]
        xc, yc, zc = cam.to_camera(pred_arr)[0].tolist()
        if cams[ci].tilted:
            u, v = cam.project(pred_arr)[0].tolist()
        elif zc > 0:
            _distort_px(&cams[ci], xc / zc, yc / zc, &u, &v)
        else:
            continue  # behind the camera: NaN
        if not (isfinite(u) and isfinite(v)):
            continue
        depth = zc if not 1e-6 > zc else 1e-6
        gate_px = gate_mm * cams[ci].f_px / depth
        # the nearest unused detection (np.argmin: the first of equals; a NaN wins)
        j = -1
        m = 0.0
        for i in range(n_dets[ci]):
            dx = dets[ci][2 * i] - u
            dy = dets[ci][2 * i + 1] - v
            d = sqrt(dx * dx + dy * dy)
            if used[ci][i]:
                d = INFINITY
            if j < 0 or d < m or (d != d and m == m):
                j, m = i, d
            if m != m:
                break
        if m <= gate_px and (best_ci < 0 or m / gate_px < best):
            best, best_ci, best_j = m / gate_px, ci, j
    if best_ci < 0:
        return 0
    ci, j = best_ci, best_j
    k = det_offsets[ci] + j
    origin, direction = cams_py[ci].backproject(dets_py[ci][k : k + 1])
    if not np.all(np.isfinite(direction)):
        return 0
    tr = &w.tracks[t]
    # The depth along the ray is unobserved: keep the last one (the point nearest the
    # last position), not the constant-velocity prediction's, which overshoots the
    # turning point of a closure by centimetres within ten frames.
    last = np.array([tr.x, tr.y, tr.z])
    s = float(np.dot(last - origin[0], direction[0]))
    s = s if not 1e-6 > s else 1e-6
    ox, oy, oz = origin[0].tolist()
    ex, ey, ez = direction[0].tolist()
    ox, oy, oz = ox + s * ex, oy + s * ey, oz + s * ez  # numpy's origin + s * direction
    used[ci][j] = 1
    _add_single_view(tr, frame, ox, oy, oz)
    _record(w, t, frame, 1 + ci, ox, oy, oz, NAN, dets[ci][2 * j], dets[ci][2 * j + 1])
    return 0


def link(
    cams_py,
    double gate_mm,
    Py_ssize_t max_coast_frames,
    Py_ssize_t max_single_view_frames,
    merge_px,
    cand_py,
    reproj_py,
    left_index_py,
    right_index_py,
    cand_offsets_py,
    left_py,
    left_fitted_py,
    left_offsets_py,
    right_py,
    right_fitted_py,
    right_offsets_py,
    overlap_frames,
):
    """The tracker's loop over frames; see :func:`core.tracks.build_tracklets`.

    The observations come concatenated over frames: frame ``f`` owns candidates
    ``cand_offsets[f]:cand_offsets[f + 1]`` (``(C, 3)`` mm, reprojection errors,
    left and right detection indices within the frame), left detections
    ``left_offsets[f]:left_offsets[f + 1]`` (``(NL, 2)`` px, ``fitted`` uint8), and
    so for the right. ``merge_px`` is None or ``(left, right)`` px. Frames in which
    the merged-image check blocked detections are appended to ``overlap_frames``
    (a list, or None).

    Returns ``(frames, kind, positions_mm, reprojection_px, pixels_px, offsets,
    order)``: the tracks' frames one track after the other (track ``k`` in
    ``offsets[k]:offsets[k + 1]``) and the tracks in the order they ended
    (those still active at the end last, in their order).
    """
    cdef const double[:, ::1] cand = cand_py
    cdef const double[::1] reproj = reproj_py
    cdef const Py_ssize_t[::1] left_index = left_index_py
    cdef const Py_ssize_t[::1] right_index = right_index_py
    cdef const Py_ssize_t[::1] c_off = cand_offsets_py
    cdef const double[:, ::1] left = left_py
    cdef const double[:, ::1] right = right_py
    cdef const unsigned char[::1] left_fitted = left_fitted_py
    cdef const unsigned char[::1] right_fitted = right_fitted_py
    cdef const Py_ssize_t[::1] l_off = left_offsets_py
    cdef const Py_ssize_t[::1] r_off = right_offsets_py
    cdef Py_ssize_t n_frames = c_off.shape[0] - 1
    if (
        l_off.shape[0] != n_frames + 1
        or r_off.shape[0] != n_frames + 1
        or reproj.shape[0] != cand.shape[0]
        or left_index.shape[0] != cand.shape[0]
        or right_index.shape[0] != cand.shape[0]
        or left_fitted.shape[0] != left.shape[0]
        or right_fitted.shape[0] != right.shape[0]
        or (n_frames >= 0 and (c_off[n_frames] != cand.shape[0] or l_off[n_frames] != left.shape[0]
                               or r_off[n_frames] != right.shape[0]))
    ):
        raise ValueError("the concatenated observations and their offsets do not agree")
    cdef Cam cams[2]
    _cam_init(&cams[0], cams_py[0])
    _cam_init(&cams[1], cams_py[1])
    cdef bint merging = merge_px is not None
    cdef double limits[2]
    if merging:
        limits[0], limits[1] = float(merge_px[0]), float(merge_px[1])
    dets_py = (left_py, right_py)
    cdef _Work w = _Work()
    cdef Py_ssize_t f, r, k, c, t, li, ri, n_t = 0, n_c, c0, n_pairs, n_still, n_free, a, b
    cdef Py_ssize_t max_l = 0, max_r = 0, max_c = 0, gap
    cdef double key
    cdef Track* tr
    cdef const double* dets[2]
    cdef const unsigned char* fitted[2]
    cdef Py_ssize_t n_dets[2]
    cdef Py_ssize_t det_offsets[2]
    cdef char* used[2]
    for f in range(n_frames):
        max_c = max(max_c, c_off[f + 1] - c_off[f])
        max_l = max(max_l, l_off[f + 1] - l_off[f])
        max_r = max(max_r, r_off[f + 1] - r_off[f])
    w.used_l = <char*>_grow(NULL, max_l, sizeof(char))
    w.used_r = <char*>_grow(NULL, max_r, sizeof(char))
    w.free = <Py_ssize_t*>_grow(NULL, max_c, sizeof(Py_ssize_t))
    used[0], used[1] = w.used_l, w.used_r
    done = []
    for f in range(n_frames):
        c0, n_c = c_off[f], c_off[f + 1] - c_off[f]
        det_offsets[0], det_offsets[1] = l_off[f], r_off[f]
        n_dets[0], n_dets[1] = l_off[f + 1] - l_off[f], r_off[f + 1] - r_off[f]
        if n_dets[0] < 0 or n_dets[1] < 0 or n_c < 0:
            raise ValueError("the offsets of the observations must not decrease")
        dets[0] = &left[l_off[f], 0] if n_dets[0] else NULL
        dets[1] = &right[r_off[f], 0] if n_dets[1] else NULL
        fitted[0] = &left_fitted[l_off[f]] if n_dets[0] else NULL
        fitted[1] = &right_fitted[r_off[f]] if n_dets[1] else NULL
        memset(w.used_l, 0, n_dets[0])
        memset(w.used_r, 0, n_dets[1])
        for c in range(n_c):
            li, ri = left_index[c0 + c], right_index[c0 + c]
            if not (0 <= li < n_dets[0] and 0 <= ri < n_dets[1]):
                raise IndexError(
                    f"frame {f}: candidate {c} uses detections ({li}, {ri}) of"
                    f" {n_dets[0]} left and {n_dets[1]} right"
                )
        if n_t:
            _reserve_active(w, n_t)
            for r in range(n_t):
                tr = &w.tracks[w.active[r]]
                gap = f - tr.last_frame
                w.preds[3 * r] = tr.x + tr.vx * gap
                w.preds[3 * r + 1] = tr.y + tr.vy * gap
                w.preds[3 * r + 2] = tr.z + tr.vz * gap
                w.gates[r] = gate_mm * (1.0 + 0.5 * (gap - 1))
                w.assigned[r] = 0
            if merging and n_t > 1:
                if _block_merged(w, n_t, f, cams, cams_py, limits, dets, fitted, n_dets, used):
                    if overlap_frames is not None:
                        overlap_frames.append(f)
            if n_c:
                n_pairs = _assign(w, n_t, w.preds, w.gates, cand, c0, n_c)
                for k in range(n_pairs):
                    r, c = w.pr[k], w.pc[k]
                    li, ri = left_index[c0 + c], right_index[c0 + c]
                    if w.used_l[li] or w.used_r[ri]:
                        continue  # a detection already explains a closer track
                    w.used_l[li] = w.used_r[ri] = 1
                    w.assigned[r] = 1
                    t = w.active[r]
                    _add_stereo(&w.tracks[t], f, cand[c0 + c, 0], cand[c0 + c, 1], cand[c0 + c, 2])
                    _record(w, t, f, 0, cand[c0 + c, 0], cand[c0 + c, 1], cand[c0 + c, 2],
                            reproj[c0 + c], NAN, NAN)
            # Single-view continuation for tracks without a stereo candidate; end
            # tracks that lost their markers (an assigned track has just been seen).
            n_still = 0
            for r in range(n_t):
                t = w.active[r]
                if not w.assigned[r]:
                    _continue_single_view(w, t, f, &w.preds[3 * r], w.gates[r], cams, cams_py,
                                          dets, n_dets, used, dets_py, det_offsets)
                    tr = &w.tracks[t]
                    if (
                        f - tr.last_frame > max_coast_frames
                        or f - tr.last_stereo > max_single_view_frames
                    ):
                        done.append(t)
                        continue
                w.active[n_still] = t
                n_still += 1
            n_t = n_still
        # New tracks from unused stereo candidates (lowest reprojection error first,
        # stably, a NaN last: numpy's stable argsort).
        n_free = 0
        for c in range(n_c):
            if not (w.used_l[left_index[c0 + c]] or w.used_r[right_index[c0 + c]]):
                key = reproj[c0 + c]
                a = n_free
                while a > 0 and (key < reproj[c0 + w.free[a - 1]] or (
                        reproj[c0 + w.free[a - 1]] != reproj[c0 + w.free[a - 1]] and key == key)):
                    w.free[a] = w.free[a - 1]
                    a -= 1
                w.free[a] = c
                n_free += 1
        for k in range(n_free):
            c = w.free[k]
            li, ri = left_index[c0 + c], right_index[c0 + c]
            if w.used_l[li] or w.used_r[ri]:
                continue
            w.used_l[li] = w.used_r[ri] = 1
            _reserve_tracks(w, w.n_tracks + 1)
            t = w.n_tracks
            w.n_tracks += 1
            tr = &w.tracks[t]
            # Tracks start on a stereo candidate, at rest.
            tr.x, tr.y, tr.z = cand[c0 + c, 0], cand[c0 + c, 1], cand[c0 + c, 2]
            tr.vx = tr.vy = tr.vz = 0.0
            tr.last_frame = tr.last_stereo = f
            _record(w, t, f, 0, tr.x, tr.y, tr.z, reproj[c0 + c], NAN, NAN)
            w.active[n_t] = t
            n_t += 1
    for r in range(n_t):
        done.append(w.active[r])
    return _grouped(w) + (done,)


cdef tuple _grouped(_Work w):
    """The records, track after track (a counting sort: each track's frames stay in order)."""
    cdef Py_ssize_t n = w.n_recs, k, t, i
    offsets_arr = np.zeros(w.n_tracks + 1, dtype=np.intp)
    cdef Py_ssize_t[::1] offsets = offsets_arr
    for k in range(n):
        offsets[w.recs[k].track + 1] += 1
    for t in range(w.n_tracks):
        offsets[t + 1] += offsets[t]
    fill_arr = offsets_arr[: w.n_tracks].copy()
    cdef Py_ssize_t[::1] fill = fill_arr
    frames_arr = np.empty(n, dtype=np.int64)
    kind_arr = np.empty(n, dtype=np.int64)
    pos_arr = np.empty((n, 3))
    reproj_arr = np.empty(n)
    px_arr = np.empty((n, 2))
    cdef int64_t[::1] frames = frames_arr
    cdef int64_t[::1] kind = kind_arr
    cdef double[:, ::1] pos = pos_arr
    cdef double[::1] reproj = reproj_arr
    cdef double[:, ::1] px = px_arr
    cdef Rec* r
    for k in range(n):
        r = &w.recs[k]
        i = fill[r.track]
        fill[r.track] += 1
        frames[i] = r.frame
        kind[i] = r.kind
        pos[i, 0], pos[i, 1], pos[i, 2] = r.x, r.y, r.z
        reproj[i] = r.reproj
        px[i, 0], px[i, 1] = r.u, r.v
    return frames_arr, kind_arr, pos_arr, reproj_arr, px_arr, offsets_arr


def project(cam, const double[:, ::1] points_mm):
    """The tracker's projection of points ``(N, 3)`` mm to distorted pixels ``(N, 2)``
    (the merged-image check's); NaN behind the camera. For tests."""
    cdef Cam c
    _cam_init(&c, cam)
    out_arr = np.empty((points_mm.shape[0], 2))
    cdef double[:, ::1] out = out_arr
    cdef Py_ssize_t i
    for i in range(points_mm.shape[0]):
        _project(&c, cam, points_mm[i, 0], points_mm[i, 1], points_mm[i, 2], &out[i, 0], &out[i, 1])
    return out_arr


def assign(const double[:, ::1] preds, const double[::1] gates, const double[:, ::1] cands):
    """The tracker's gated assignment of tracks ``(T, 3)`` to candidates ``(C, 3)``:
    ``[(track, candidate), ...]``, closest first. For tests."""
    if preds.shape[0] != gates.shape[0]:
        raise ValueError(f"{preds.shape[0]} predictions but {gates.shape[0]} gates")
    cdef _Work w = _Work()
    cdef Py_ssize_t n_t = preds.shape[0], k, n
    if n_t == 0 or cands.shape[0] == 0:
        return []
    n = _assign(w, n_t, &preds[0, 0], &gates[0], cands, 0, cands.shape[0])
    return [(w.pr[k], w.pc[k]) for k in range(n)]


def distances(const double[:, ::1] p, const double[:, ::1] q):
    """The tracker's 3D distances of points ``(N, 3)`` to points ``(M, 3)``, ``(N, M)``.
    For tests."""
    out_arr = np.empty((p.shape[0], q.shape[0]))
    cdef double[:, ::1] out = out_arr
    cdef Py_ssize_t i, j
    for i in range(p.shape[0]):
        for j in range(q.shape[0]):
            out[i, j] = _distance(p[i, 0], p[i, 1], p[i, 2], &q[j, 0])
    return out_arr

# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled blob search and measurement behind :func:`core.markers.detect_markers`.

``core/markers.py`` documents the method; this module is its per-pixel part:
the seeds of each candidate region and the measurement of each blob (core,
shape, support, centroid, flatness), which in Python cost ~20 small OpenCV
and numpy calls per blob.  The numbers are OpenCV's: the 3x3 mean in float32
as ``cv2.boxFilter(CV_32F)`` gives it, comparisons against it in float32 as
numpy makes them, ``cv2.moments`` formulas, the 5x5 elliptic structuring
element, and exact Euclidean distances as ``cv2.distanceTransform(DIST_L2,
DIST_MASK_PRECISE)``.  ``tests/core/test_markers.py`` checks the results
against ground truth and, field by field, against the OpenCV formulation kept
in ``tests/core/markers_reference.py``.
"""

from libc.math cimport INFINITY, M_PI, NAN, acos, atan2, ceil, cos, exp, fabs, floor, sin, sqrt
from libc.stdlib cimport free, malloc, qsort, realloc
from libc.string cimport memcpy, memset

import numpy as np

# Pixel loops in plain C with restrict pointers: a uint8 or float pointer may alias
# any other (and a module-level float), so that the compiler would not vectorise
# these loops written in Cython. The same operations in the same order.
cdef extern from *:
    """
    static void bl_colsum3(const unsigned char *__restrict a, const unsigned char *__restrict b,
                           const unsigned char *__restrict c, int *__restrict out, int n) {
        for (int i = 0; i < n; i++) out[i] = a[i] + b[i] + c[i];
    }
    static int bl_mean3(const int *__restrict cs, float *__restrict o, int n, float ninth,
                        int smax) {
        for (int i = 0; i < n; i++) {
            int s = cs[i] + cs[i + 1] + cs[i + 2];
            smax = s > smax ? s : smax;
            o[i] = (float)s * ninth;
        }
        return smax;
    }
    """
    void bl_colsum3(const unsigned char* a, const unsigned char* b, const unsigned char* c,
                    int* out, int n) noexcept nogil
    int bl_mean3(const int* cs, float* o, int n, float ninth, int smax) noexcept nogil

# one output row per blob (float64); the Python side reads these columns
DEF NCOL = 21
COLUMNS = (
    "x", "y", "diameter", "peak", "roundness", "background", "area", "fill",
    "cxx", "cxy", "cyy", "quality", "flatness",
    "rect_x0", "rect_y0", "rect_x1", "rect_y1", "moment_x", "moment_y", "region",
    "fit_residual",
)

DEF MARGIN_PX = 3        # support of the centroid beyond the half-maximum core
DEF SIZE_TOL_PX = 0.5    # pixelisation of the measured diameter, allowed beyond the limits
DEF EDT_BIG = 1e20       # "no such pixel" in a distance transform (px^2)
DEF EDT_INF = 1e300
DEF NO_PIXEL = 0x3fffffff

cdef float NINTH = <float>(1.0 / 9.0)
cdef int RING_DX[8]
cdef int RING_DY[8]
RING_DX[:] = [1, 1, 0, -1, -1, -1, 0, 1]
RING_DY[:] = [0, 1, 1, 1, 0, -1, -1, -1]


cdef struct Params:
    double d_min
    double d_max
    double min_contrast
    double max_elong
    double min_fill
    int reject_border
    int ring_r
    int half_limit
    int max_seeds


cdef struct Core:  # a measured half-maximum region: its box (absolute) and mask
    int x0
    int y0
    int w
    int h
    size_t off


cdef struct Seed:
    float v
    int y
    int x


cdef struct Buf:  # a growable byte buffer
    unsigned char* p
    size_t n
    size_t cap


cdef int buf_reserve(Buf* b, size_t extra) except -1 nogil:
    cdef size_t cap
    cdef unsigned char* p
    if b.n + extra <= b.cap:
        return 0
    cap = max(2 * b.cap, b.n + extra, <size_t>4096)
    p = <unsigned char*>realloc(b.p, cap)
    if p == NULL:
        with gil:
            raise MemoryError()
    b.p = p
    b.cap = cap
    return 0


cdef struct Frame:
    const unsigned char* img
    int W
    int H
    Params prm
    int want_support
    Buf cores        # Core structs
    Buf core_bits    # their masks, one byte per pixel
    Buf rows         # double[NCOL] per blob
    Buf supports     # support masks (when want_support), one byte per pixel
    Buf work         # scratch for one measurement
    int region


cdef int cmp_seed(const void* a, const void* b) noexcept nogil:
    cdef const Seed* s = <const Seed*>a
    cdef const Seed* t = <const Seed*>b
    if s.v > t.v:
        return -1
    if s.v < t.v:
        return 1
    if s.y != t.y:
        return -1 if s.y < t.y else 1
    if s.x != t.x:
        return -1 if s.x < t.x else 1
    return 0


cdef inline int clampi(int v, int lo, int hi) noexcept nogil:
    return lo if v < lo else (hi if v > hi else v)


cdef int smooth(const Frame* f, int x0, int y0, int x1, int y1, float* out, int* colsum) noexcept nogil:
    """3x3 mean of the image over [x0, x1) x [y0, y1), replicated at the image border.

    ``colsum`` holds ``x1 - x0 + 2`` ints.  Its rows are ``bl_colsum3`` and
    ``bl_mean3``, which the compiler vectorises.  Returns the largest 3x3 sum (the largest mean is that times
    ``NINTH`` in float32, since the rounding is monotonic).
    """
    cdef int W = f.W, H = f.H, y, w = x1 - x0, smax = 0
    cdef int left = x0 - 1 if x0 > 0 else 0
    cdef int right = x1 if x1 < W else W - 1
    cdef const unsigned char* ra
    cdef const unsigned char* rb
    cdef const unsigned char* rc
    for y in range(y0, y1):
        ra = f.img + <size_t>(y - 1 if y > 0 else 0) * W
        rb = f.img + <size_t>y * W
        rc = f.img + <size_t>(y + 1 if y < H - 1 else H - 1) * W
        colsum[0] = ra[left] + rb[left] + rc[left]
        colsum[w + 1] = ra[right] + rb[right] + rc[right]
        bl_colsum3(ra + x0, rb + x0, rc + x0, colsum + 1, w)
        smax = bl_mean3(colsum, out + (y - y0) * w, w, NINTH, smax)
    return smax


cdef int kth(const int* hist, int k) noexcept nogil:
    """The k-th smallest (0-based) of values counted in a 256-bin histogram."""
    cdef int v = 0, c = 0
    for v in range(256):
        c += hist[v]
        if c > k:
            return v
    return 255


cdef void dilate_square(const unsigned char* src, unsigned char* dst, unsigned char* tmp, int stride,
                        int ax0, int ay0, int ax1, int ay1, int r, int* last) noexcept nogil:
    """Binary dilation by a (2r+1)^2 square on the rectangle [ax0, ax1) x [ay0, ay1)
    of images with row length ``stride`` (source pixels outside it ignored).

    Separable, each pass in O(1) per pixel: a pixel is set when the nearest set
    pixel before or after it along the line is at most ``r`` away.  ``last``
    holds ``ax1 - ax0`` ints.
    """
    cdef int x, y, near, w = ax1 - ax0
    cdef int far = -2 * r - 2
    for y in range(ay0, ay1):
        near = far
        for x in range(ax0, ax1):
            if src[y * stride + x]:
                near = x
            tmp[y * stride + x] = x - near <= r
        near = ax1 + 2 * r + 2
        for x in range(ax1 - 1, ax0 - 1, -1):
            if src[y * stride + x]:
                near = x
            tmp[y * stride + x] |= near - x <= r
    for x in range(w):
        last[x] = ay0 + far
    for y in range(ay0, ay1):
        for x in range(w):
            if tmp[y * stride + ax0 + x]:
                last[x] = y
            dst[y * stride + ax0 + x] = y - last[x] <= r
    for x in range(w):
        last[x] = ay1 - far
    for y in range(ay1 - 1, ay0 - 1, -1):
        for x in range(w):
            if tmp[y * stride + ax0 + x]:
                last[x] = y
            dst[y * stride + ax0 + x] |= last[x] - y <= r


cdef inline unsigned char or_within(const unsigned char* s, int lo, int hi, int ax0,
                                    int ax1) noexcept nogil:
    """OR of ``s[lo..hi]`` (inclusive) clipped to ``[ax0, ax1)``."""
    cdef int i
    cdef unsigned char acc = 0
    for i in range(max(ax0, lo), min(ax1 - 1, hi) + 1):
        acc |= s[i]
    return acc


cdef void dilate_disc5(const unsigned char* src, unsigned char* dst, unsigned char* tmp, int stride,
                       int ax0, int ay0, int ax1, int ay1) noexcept nogil:
    """Binary dilation by cv2.getStructuringElement(MORPH_ELLIPSE, (5, 5)) on a rectangle
    (as :func:`dilate_square`): the 5x3 box of rows -1..1 and columns -2..2, plus the
    pixels 2 rows above and below."""
    cdef int x, y
    cdef unsigned char acc
    cdef const unsigned char* s
    cdef unsigned char* t
    cdef unsigned char* d
    cdef const unsigned char* up
    cdef const unsigned char* down
    cdef const unsigned char* up2
    cdef const unsigned char* down2
    cdef int ix0 = min(ax0 + 2, ax1), ix1 = max(ax1 - 2, ix0)  # columns with 2 on each side
    for y in range(ay0, ay1):
        s = src + <size_t>y * stride
        t = tmp + <size_t>y * stride
        for x in range(ix0, ix1):
            t[x] = s[x - 2] | s[x - 1] | s[x] | s[x + 1] | s[x + 2]
        for x in range(ax0, ix0):
            t[x] = or_within(s, x - 2, x + 2, ax0, ax1)
        for x in range(ix1, ax1):
            t[x] = or_within(s, x - 2, x + 2, ax0, ax1)
    for y in range(ay0, ay1):
        t = tmp + <size_t>y * stride
        d = dst + <size_t>y * stride
        if ay0 + 2 <= y < ay1 - 2:
            up = t - stride
            down = t + stride
            up2 = src + <size_t>(y - 2) * stride
            down2 = src + <size_t>(y + 2) * stride
            for x in range(ax0, ax1):
                d[x] = t[x] | up[x] | down[x] | up2[x] | down2[x]
            continue
        for x in range(ax0, ax1):
            acc = t[x]
            if y > ay0:
                acc |= tmp[(y - 1) * stride + x]
            if y < ay1 - 1:
                acc |= tmp[(y + 1) * stride + x]
            if y > ay0 + 1:
                acc |= src[(y - 2) * stride + x]
            if y < ay1 - 2:
                acc |= src[(y + 2) * stride + x]
            d[x] = acc


cdef void edt_1d(const double* f, double* out, int n, int* v, double* z) noexcept nogil:
    """Squared distance transform of one line (Felzenszwalb & Huttenlocher 2012)."""
    cdef int q, k = 0
    cdef double s
    v[0] = 0
    z[0] = -EDT_INF
    z[1] = EDT_INF
    for q in range(1, n):
        s = ((f[q] + q * q) - (f[v[k]] + v[k] * v[k])) / (2.0 * q - 2.0 * v[k])
        while s <= z[k]:
            k -= 1
            s = ((f[q] + q * q) - (f[v[k]] + v[k] * v[k])) / (2.0 * q - 2.0 * v[k])
        k += 1
        v[k] = q
        z[k] = s
        z[k + 1] = EDT_INF
    k = 0
    for q in range(n):
        while z[k + 1] < q:
            k += 1
        out[q] = (q - v[k]) * (q - v[k]) + f[v[k]]


cdef int edt(const unsigned char* zero, double* d, int w, int h) except -1 nogil:
    """Exact squared Euclidean distance (px^2) to the nearest pixel with ``zero`` set, as
    ``cv2.distanceTransform(DIST_L2, DIST_MASK_PRECISE)`` squared: integers, so that
    comparisons of two maps have no rounding ties."""
    cdef int n = max(w, h), x, y
    cdef double* f = <double*>malloc((3 * n + 2) * sizeof(double) + n * sizeof(int))
    if f == NULL:
        with gil:
            raise MemoryError()
    cdef double* out = f + n
    cdef double* z = out + n
    cdef int* v = <int*>(z + n + 2)
    for x in range(w):
        for y in range(h):
            f[y] = 0.0 if zero[y * w + x] else EDT_BIG
        edt_1d(f, out, h, v, z)
        for y in range(h):
            d[y * w + x] = out[y]
    for y in range(h):
        edt_1d(d + y * w, out, w, v, z)
        memcpy(d + y * w, out, w * sizeof(double))
    free(f)
    return 0


cdef int store_core(Frame* f, const unsigned char* mask, int mw, int x0, int y0,
                    int bx, int by, int bw, int bh) except -1 nogil:
    """Remember the core (``mask == 2`` in its box) so later seeds inside it are skipped."""
    cdef Core c
    cdef int y, x
    cdef unsigned char* bits
    buf_reserve(&f.cores, sizeof(Core))
    buf_reserve(&f.core_bits, <size_t>bw * bh)
    c.x0 = x0 + bx
    c.y0 = y0 + by
    c.w = bw
    c.h = bh
    c.off = f.core_bits.n
    bits = f.core_bits.p + f.core_bits.n
    for y in range(bh):
        for x in range(bw):
            bits[y * bw + x] = mask[(by + y) * mw + bx + x] == 2
    f.core_bits.n += <size_t>bw * bh
    memcpy(f.cores.p + f.cores.n, &c, sizeof(Core))
    f.cores.n += sizeof(Core)
    return 0


cdef void mark_core(const Frame* f, const Core* c, unsigned char* taken,
                    int x0, int y0, int x1, int y1) noexcept nogil:
    cdef int ax0 = max(x0, c.x0), ay0 = max(y0, c.y0)
    cdef int ax1 = min(x1, c.x0 + c.w), ay1 = min(y1, c.y0 + c.h)
    cdef int x, y
    cdef const unsigned char* bits = f.core_bits.p + c.off
    for y in range(ay0, ay1):
        for x in range(ax0, ax1):
            if bits[(y - c.y0) * c.w + x - c.x0]:
                taken[(y - y0) * (x1 - x0) + x - x0] = 1



cdef bint in_core(const Frame* f, int x, int y) noexcept nogil:
    """Whether pixel ``(x, y)`` lies in the core of a blob measured before."""
    cdef const Core* cores = <const Core*>f.cores.p
    cdef size_t i
    for i in range(f.cores.n // sizeof(Core)):
        if (cores[i].x0 <= x < cores[i].x0 + cores[i].w
                and cores[i].y0 <= y < cores[i].y0 + cores[i].h
                and f.core_bits.p[cores[i].off + <size_t>(y - cores[i].y0) * cores[i].w
                                  + x - cores[i].x0]):
            return True
    return False


# ------------------------------------------------------------------ one blob

cdef int measure(Frame* f, int sx, int sy, int* has_core) except -1 nogil:
    """Measure the blob around seed ``(sx, sy)``; append a row when it is a marker.

    ``has_core`` is set when a half-maximum core was found; the core is then
    stored, marker or not, so that later seeds inside it are skipped.
    """
    cdef Params* p = &f.prm
    cdef int W = f.W, H = f.H
    cdef int half = p.ring_r, reseeds = 0
    cdef int wx0 = 0, wx1 = 0, wy0 = 0, wy1 = 0, ww = 0, wh = 0, n = 0, i, x, y, lx = 0, ly = 0
    cdef int hist[256]
    cdef size_t npx = 0
    cdef float* sm = NULL
    cdef int* colsum = NULL
    cdef int* stack = NULL
    cdef double* d_own = NULL
    cdef double* d_other = NULL
    cdef unsigned char* mask = NULL
    cdef unsigned char* core = NULL
    cdef unsigned char* low = NULL
    cdef unsigned char* near = NULL
    cdef unsigned char* low_near = NULL
    cdef unsigned char* sup = NULL
    cdef unsigned char* tmp = NULL
    cdef int sp, area = 0, bx = 0, by = 0, bx1 = 0, by1 = 0, bw, bh, mx_l, my_l, px, py, nx, ny, dx, dy
    cdef double bg = 0.0, contrast, peak_val = 0.0, m10, m01, m20, m02, m11, cxm = 0.0, cym = 0.0
    cdef double mu20, mu02, mu11, cxx = 0.0, cyy = 0.0, cxy = 0.0, tr, det, disc, lam_max, lam_min
    cdef double diameter = 0.0, roundness = 0.0, fill = 0.0
    cdef float hm, fpk
    cdef int margin = 0, need
    has_core[0] = 0
    while True:
        wx0 = max(0, sx - half)
        wx1 = min(W, sx + half + 1)
        wy0 = max(0, sy - half)
        wy1 = min(H, sy + half + 1)
        ww = wx1 - wx0
        wh = wy1 - wy0
        npx = <size_t>ww * wh
        # scratch: 2 pixel maps of 4 bytes, the column sums, 7 masks of 1 byte
        f.work.n = 0
        buf_reserve(&f.work, npx * (2 * 4 + 7) + <size_t>(ww + 2) * 4)
        sm = <float*>f.work.p
        stack = <int*>(sm + npx)
        colsum = stack + npx
        mask = <unsigned char*>(colsum + ww + 2)
        core = mask + npx
        low = core + npx
        near = low + npx
        low_near = near + npx
        sup = low_near + npx
        tmp = sup + npx
        smooth(f, wx0, wy0, wx1, wy1, sm, colsum)
        # background and noise from the window's border (its median and quartiles)
        memset(hist, 0, sizeof(hist))
        for x in range(ww):
            hist[f.img[<size_t>wy0 * W + wx0 + x]] += 1
            hist[f.img[<size_t>(wy1 - 1) * W + wx0 + x]] += 1
        for y in range(wy0 + 1, wy1 - 1):
            hist[f.img[<size_t>y * W + wx0]] += 1
            hist[f.img[<size_t>y * W + wx1 - 1]] += 1
        n = 2 * ww + 2 * (wh - 2)
        bg = 0.5 * (<double>kth(hist, (n - 1) // 2) + <double>kth(hist, n // 2))
        lx = sx - wx0
        ly = sy - wy0
        contrast = <double>sm[ly * ww + lx] - bg
        if contrast < p.min_contrast:
            return 0
        hm = <float>(bg + 0.5 * contrast)
        for i in range(<int>npx):
            mask[i] = sm[i] > hm
        # the core: the 8-connected half-maximum region of the seed, set to 2
        area = 0
        bx = bx1 = lx
        by = by1 = ly
        mask[ly * ww + lx] = 2
        stack[0] = ly * ww + lx
        sp = 1
        while sp > 0:
            sp -= 1
            i = stack[sp]
            py = i // ww
            px = i - py * ww
            area += 1
            bx = min(bx, px)
            bx1 = max(bx1, px)
            by = min(by, py)
            by1 = max(by1, py)
            for dy in range(-1, 2):
                ny = py + dy
                if ny < 0 or ny >= wh:
                    continue
                for dx in range(-1, 2):
                    nx = px + dx
                    if nx < 0 or nx >= ww or mask[ny * ww + nx] != 1:
                        continue
                    mask[ny * ww + nx] = 2
                    stack[sp] = ny * ww + nx
                    sp += 1
        # the core's maximum, first in raster order (every seed of a blob measures the same)
        fpk = -1.0
        mx_l = my_l = 0
        for y in range(by, by1 + 1):
            for x in range(bx, bx1 + 1):
                if mask[y * ww + x] == 2 and sm[y * ww + x] > fpk:
                    fpk = sm[y * ww + x]
                    mx_l = x
                    my_l = y
        peak_val = fpk
        if (mx_l != lx or my_l != ly) and reseeds < 2:
            sx = mx_l + wx0
            sy = my_l + wy0
            if in_core(f, sx, sy):
                # a seed on the flank of a blob measured before (its halo on lit skin)
                # would measure it again: a duplicate row and core. Counted as found,
                # as that measurement was (the region's max_seeds)
                has_core[0] = 2
                return 0
            reseeds += 1
            continue
        # moments of the core (cv2.moments' formulas, origin at the box corner)
        m10 = m01 = m20 = m02 = m11 = 0.0
        for y in range(by1 - by + 1):
            for x in range(bx1 - bx + 1):
                if mask[(by + y) * ww + bx + x] == 2:
                    m10 += x
                    m01 += y
                    m20 += x * x
                    m02 += y * y
                    m11 += x * y
        cxm = m10 / area
        cym = m01 / area
        mu20 = m20 - m10 * cxm
        mu11 = m11 - m10 * cym
        mu02 = m02 - m01 * cym
        # shape: each pixel a unit square (1/12 px^2), so that a tiny blob is no line
        cxx = mu20 / area + 1.0 / 12
        cyy = mu02 / area + 1.0 / 12
        cxy = mu11 / area
        tr = cxx + cyy
        det = cxx * cyy - cxy * cxy
        disc = sqrt(max(0.25 * tr * tr - det, 0.0))
        lam_max = 0.5 * tr + disc
        lam_min = max(0.5 * tr - disc, 1e-12)
        diameter = 4.0 * sqrt(lam_min)
        roundness = sqrt(lam_min / lam_max)
        fill = area / (4.0 * 3.141592653589793 * sqrt(lam_min * lam_max))
        margin = max(MARGIN_PX, <int>ceil(0.5 * diameter))
        need = margin + 3 + max(max(lx - bx, bx1 - lx), max(ly - by, by1 - ly))
        if ((lx >= need or wx0 == 0) and (ww - 1 - lx >= need or wx1 == W)
                and (ly >= need or wy0 == 0) and (wh - 1 - ly >= need or wy1 == H)):
            break
        if area > p.max_elong * p.d_max * p.d_max or need > p.half_limit:  # a glare blob
            has_core[0] = 1
            store_core(f, mask, ww, wx0, wy0, bx, by, bx1 - bx + 1, by1 - by + 1)
            return 0
        half = need

    has_core[0] = 1
    bw = bx1 - bx + 1
    bh = by1 - by + 1
    store_core(f, mask, ww, wx0, wy0, bx, by, bw, bh)
    cdef double peak = peak_val - bg
    cdef int touches = ((bx == 0 and wx0 == 0) or (by == 0 and wy0 == 0)
                        or (bx1 == ww - 1 and wx1 == W) or (by1 == wh - 1 and wy1 == H))
    if (peak < p.min_contrast
            or not (p.d_min - SIZE_TOL_PX <= diameter <= p.d_max + SIZE_TOL_PX)
            or roundness * p.max_elong < 1.0
            or fill < p.min_fill
            or (touches and p.reject_border)):
        return 0

    # support of the centre: the blob down to 10 % of its peak (or 1.5 noise
    # sigmas), at most ``margin`` beyond the core, grown by 2 px; low pixels beyond
    # that reach and other blobs masked out, a neighbour above half maximum split
    # off by distance
    cdef double sigma = max((<double>kth(hist, (3 * n) // 4) - <double>kth(hist, n // 4)) / 1.349, 0.7)
    cdef float low_thr = <float>(bg + max(1.5 * sigma, 0.1 * peak))
    cdef int n_mask = 0, n_low = 0, n_low_near = 0
    for i in range(<int>npx):
        n_mask += mask[i] != 0
        low[i] = sm[i] > low_thr
        n_low += low[i]
    # the centre's rectangle: ``margin + 3`` beyond the core's box (``near`` and the
    # support lie inside it), and the same 2 px larger (what a 5x5 dilation reaches)
    cdef int e = margin + 3
    cdef int rx0 = max(0, bx - e), ry0 = max(0, by - e)
    cdef int rx1 = min(ww, bx1 + 1 + e), ry1 = min(wh, by1 + 1 + e)
    cdef int rw = rx1 - rx0, rh = ry1 - ry0
    cdef int qx0 = max(0, rx0 - 2), qy0 = max(0, ry0 - 2)
    cdef int qx1 = min(ww, rx1 + 2), qy1 = min(wh, ry1 + 2)
    for y in range(qy0, qy1):
        for x in range(qx0, qx1):
            core[y * ww + x] = mask[y * ww + x] == 2
    dilate_square(core, near, tmp, ww, qx0, qy0, qx1, qy1, margin, colsum)
    for y in range(qy0, qy1):
        for x in range(qx0, qx1):
            i = y * ww + x
            low_near[i] = low[i] & near[i]
            n_low_near += low_near[i]
    dilate_disc5(low_near, sup, tmp, ww, rx0, ry0, rx1, ry1)
    cdef int has_neighbour = n_mask > area
    if has_neighbour or n_low > n_low_near:
        for y in range(qy0, qy1):  # others: low pixels beyond reach, other cores
            for x in range(qx0, qx1):
                i = y * ww + x
                low[i] = (low[i] and not near[i]) or mask[i] == 1
        dilate_disc5(low, near, tmp, ww, qx0, qy0, qx1, qy1)  # near is not needed any more
        for y in range(ry0, ry1):
            for x in range(rx0, rx1):
                sup[y * ww + x] &= 1 - near[y * ww + x]
        if has_neighbour:
            d_own = <double*>malloc(2 * npx * sizeof(double))
            if d_own == NULL:
                with gil:
                    raise MemoryError()
            d_other = d_own + npx
            for i in range(<int>npx):
                core[i] = mask[i] == 2
                tmp[i] = mask[i] == 1
            edt(core, d_own, ww, wh)
            edt(tmp, d_other, ww, wh)
            for y in range(ry0, ry1):
                for x in range(rx0, rx1):
                    i = y * ww + x
                    sup[i] &= d_own[i] < d_other[i]
            free(d_own)
        for y in range(ry0, ry1):
            for x in range(rx0, rx1):
                sup[y * ww + x] |= core[y * ww + x]

    # intensity-weighted centroid of max(I - bg - 0.1 peak, 0) on the support
    cdef double s0 = 0.0, s10 = 0.0, s01 = 0.0, wgt, rowsum, rowx
    cdef double off = bg + 0.1 * peak
    cdef const unsigned char* row
    for y in range(rh):
        row = f.img + <size_t>(wy0 + ry0 + y) * W + wx0 + rx0
        rowsum = 0.0
        rowx = 0.0
        for x in range(rw):
            if sup[(ry0 + y) * ww + rx0 + x]:
                wgt = <double>row[x] - off
                if wgt > 0:
                    rowsum += wgt
                    rowx += wgt * x
        s0 += rowsum
        s10 += rowx
        s01 += rowsum * y
    # flatness: share of the core above 75 % of the peak (uint8 > floor, as cv2.threshold)
    cdef double t75 = bg + 0.75 * peak, flatness = 0.0
    cdef int ithr, cnt = 0
    if t75 < 255:
        ithr = <int>floor(max(t75, -1.0))
        for y in range(by, by1 + 1):
            for x in range(bx, bx1 + 1):
                if core[y * ww + x] and f.img[<size_t>(wy0 + y) * W + wx0 + x] > ithr:
                    cnt += 1
        flatness = <double>cnt / area
    cdef double quality = (roundness * min(fill, 1.0) * min(1.0, flatness / 0.6)
                           * min(1.0, peak / (3.0 * p.min_contrast)))

    buf_reserve(&f.rows, NCOL * sizeof(double))
    cdef double* r = <double*>(f.rows.p + f.rows.n)
    f.rows.n += NCOL * sizeof(double)
    r[0] = s10 / s0 + rx0 + wx0 if s0 > 0 else NAN
    r[1] = s01 / s0 + ry0 + wy0 if s0 > 0 else NAN
    r[2] = diameter
    r[3] = peak
    r[4] = roundness
    r[5] = bg
    r[6] = area
    r[7] = fill
    r[8] = cxx
    r[9] = cxy
    r[10] = cyy
    r[11] = quality
    r[12] = flatness
    r[13] = rx0 + wx0
    r[14] = ry0 + wy0
    r[15] = rx1 + wx0
    r[16] = ry1 + wy0
    r[17] = cxm + bx - rx0
    r[18] = cym + by - ry0
    r[19] = f.region
    r[20] = NAN  # set by core.markers when a disc model is fitted
    if f.want_support:
        buf_reserve(&f.supports, <size_t>rw * rh)
        for y in range(rh):
            memcpy(f.supports.p + f.supports.n + <size_t>y * rw, sup + (ry0 + y) * ww + rx0, rw)
        f.supports.n += <size_t>rw * rh
    return 0


# ------------------------------------------------------------------ one region

cdef inline bint near_hit(const int* hits, int py0, int py1, int y, int d) noexcept nogil:
    """Whether a row of [y - d, y + d] (within the pre-scan's [py0, py1)) has a hit;
    ``hits`` as in :func:`search_region`."""
    cdef int a = max(py0, y - d), b = min(py1, y + d + 1)
    return b > a and hits[b - py0] > hits[a - py0]


cdef int search_region(Frame* f, int x0, int y0, int x1, int y1, double thr) except -1 nogil:
    """Seeds (local maxima above ``thr``) of one region, each blob measured once.

    Only the box of the pixels above ``thr - 1`` (2 px larger, within the
    region) is smoothed: a 3x3 mean above ``thr`` needs such a pixel within
    1 px (inside the region or just beyond it), and its neighbours are within
    2 px.
    """
    cdef int x, y, i, j, k, a, b, dx, dy, nx, ny, n_seeds = 0, n_found = 0, has_core
    cdef int W = f.W, r = f.prm.ring_r
    cdef int cx0 = NO_PIXEL, cy0 = NO_PIXEL, cx1 = -1, cy1 = -1
    cdef double lower = thr - 1.0
    cdef const unsigned char* row
    # the 3x3 means of the region reach 1 px beyond it; a row is only looked at
    # pixel by pixel when its maximum (a loop the compiler vectorises) is a hit
    cdef int sx0 = max(0, x0 - 1), sx1 = min(W, x1 + 1)
    cdef int ilower = <int>floor(lower) if lower >= -1.0 else -1  # uint8 > lower
    cdef unsigned char m
    # hits[k]: the rows of the pre-scan [py0, py0 + k) with a pixel above lower
    cdef int py0 = max(0, y0 - 1), py1 = min(f.H, y1 + 1), smax = 0
    cdef int* hits = <int*>malloc((py1 - py0 + 1) * sizeof(int))
    if hits == NULL:
        with gil:
            raise MemoryError()
    hits[0] = 0
    for y in range(py0, py1):
        row = f.img + <size_t>y * W
        m = 0
        for x in range(sx0, sx1):
            m = row[x] if row[x] > m else m
        hits[y - py0 + 1] = hits[y - py0] + (m > ilower)
        if m <= ilower:
            continue
        cy0 = min(cy0, y)
        cy1 = y
        for x in range(sx0, sx1):
            if row[x] > ilower:
                cx0 = min(cx0, x)
                break
        for x in range(sx1 - 1, sx0 - 1, -1):
            if row[x] > ilower:
                cx1 = max(cx1, x)
                break
    if cy1 < 0:
        free(hits)
        return 0
    # the smoothed part of the region: [x0, x1) x [y0, y1) from here on
    x0, y0 = max(x0, cx0 - 2), max(y0, cy0 - 2)
    x1, y1 = min(x1, cx1 + 3), min(y1, cy1 + 3)
    cdef int rw = x1 - x0, rh = y1 - y0
    cdef size_t npx = <size_t>rw * rh
    cdef float* sm = <float*>malloc(npx * sizeof(float) + <size_t>(rw + 2) * sizeof(int))
    if sm == NULL:
        free(hits)
        with gil:
            raise MemoryError()
    cdef int* colsum = <int*>(sm + npx)
    cdef Seed* seeds = NULL
    cdef unsigned char* taken = NULL
    cdef float v, vmax = -1.0, fthr = <float>thr
    cdef const float* nb
    cdef float fmin8 = <float>(0.8 * f.prm.min_contrast)
    cdef int ismax
    cdef unsigned char ring[8]
    cdef unsigned char t
    cdef const Core* cores
    try:
        # Only rows with a hit within 2 rows are smoothed: a mean above thr needs a hit
        # within 1 row, and the local-maximum test reads the rows beside it. The others
        # are never read (no mean above thr either, so vmax is the same).
        for y in range(rh):
            if near_hit(hits, py0, py1, y + y0, 2):
                smax = max(smax, smooth(f, x0, y + y0, x1, y + y0 + 1, sm + y * rw, colsum))
        vmax = <float>smax * NINTH
        if <double>vmax <= thr:  # no seed (most full-frame regions: a noise pixel above thr)
            return 0
        seeds = <Seed*>malloc(npx * sizeof(Seed))
        if seeds == NULL:
            with gil:
                raise MemoryError()
        # local maxima above thr (compared with their 8 neighbours inside the region)
        for y in range(rh):
            if not near_hit(hits, py0, py1, y + y0, 1):
                continue  # no mean above thr in this row
            for x in range(rw):
                v = sm[y * rw + x]
                if not v > fthr:
                    continue
                if 0 < y < rh - 1 and 0 < x < rw - 1:  # inside: the 8 neighbours, no bounds
                    nb = sm + (y - 1) * rw + x - 1  # the neighbour above left
                    if (nb[0] > v or nb[1] > v or nb[2] > v or nb[rw] > v or nb[rw + 2] > v
                            or nb[2 * rw] > v or nb[2 * rw + 1] > v or nb[2 * rw + 2] > v):
                        continue
                    seeds[n_seeds].v = v
                    seeds[n_seeds].y = y + y0
                    seeds[n_seeds].x = x + x0
                    n_seeds += 1
                    continue
                ismax = 1
                for dy in range(-1, 2):
                    ny = y + dy
                    if ny < 0 or ny >= rh:
                        continue
                    for dx in range(-1, 2):
                        nx = x + dx
                        if 0 <= nx < rw and sm[ny * rw + nx] > v:
                            ismax = 0
                if ismax:
                    seeds[n_seeds].v = v
                    seeds[n_seeds].y = y + y0
                    seeds[n_seeds].x = x + x0
                    n_seeds += 1
        if n_seeds > 1:
            # cheap pre-check of the local contrast against 8 pixels at the distance of
            # the measurement ring, so that a bright textured area (lit skin) does not
            # cost one measurement per noise maximum
            j = 0
            for i in range(n_seeds):
                for k in range(8):
                    ring[k] = f.img[<size_t>clampi(seeds[i].y + r * RING_DY[k], 0, f.H - 1) * W
                                    + clampi(seeds[i].x + r * RING_DX[k], 0, W - 1)]
                for a in range(1, 8):  # insertion sort of 8 values
                    t = ring[a]
                    b = a - 1
                    while b >= 0 and ring[b] > t:
                        ring[b + 1] = ring[b]
                        b -= 1
                    ring[b + 1] = t
                if seeds[i].v - (<float>0.5) * (<float>ring[3] + <float>ring[4]) >= fmin8:
                    seeds[j] = seeds[i]
                    j += 1
            n_seeds = j
        qsort(seeds, n_seeds, sizeof(Seed), cmp_seed)  # brightest first, then raster order
        taken = <unsigned char*>malloc(npx)
        if taken == NULL:
            with gil:
                raise MemoryError()
        memset(taken, 0, npx)
        cores = <const Core*>f.cores.p
        for i in range(<int>(f.cores.n // sizeof(Core))):
            mark_core(f, &cores[i], taken, x0, y0, x1, y1)
        for i in range(n_seeds):
            if taken[(seeds[i].y - y0) * rw + seeds[i].x - x0]:
                continue
            measure(f, seeds[i].x, seeds[i].y, &has_core)
            taken[(seeds[i].y - y0) * rw + seeds[i].x - x0] = 1
            if has_core:
                if has_core == 1:  # a new core (2: one measured before)
                    cores = <const Core*>f.cores.p  # the buffer may have moved
                    mark_core(f, &cores[f.cores.n // sizeof(Core) - 1], taken, x0, y0, x1, y1)
                n_found += 1
                if n_found >= f.prm.max_seeds:
                    break
    finally:
        free(hits)
        free(sm)
        free(seeds)
        free(taken)
    return 0


# ------------------------------------------------------------------ entry point

cdef void frame_init(Frame* f, const unsigned char[:, ::1] image, double diameter_px_min,
                     double diameter_px_max, double min_contrast, double max_elongation,
                     double min_fill, bint reject_border, int ring_radius_px, int half_limit_px,
                     int max_seeds_per_region, bint want_support) noexcept:
    memset(f, 0, sizeof(Frame))
    f.img = &image[0, 0]
    f.H = image.shape[0]
    f.W = image.shape[1]
    f.prm.d_min = diameter_px_min
    f.prm.d_max = diameter_px_max
    f.prm.min_contrast = min_contrast
    f.prm.max_elong = max_elongation
    f.prm.min_fill = min_fill
    f.prm.reject_border = reject_border
    f.prm.ring_r = ring_radius_px
    f.prm.half_limit = half_limit_px
    f.prm.max_seeds = max_seeds_per_region
    f.want_support = want_support


cdef void frame_free(Frame* f) noexcept:
    free(f.cores.p)
    free(f.core_bits.p)
    free(f.rows.p)
    free(f.supports.p)
    free(f.work.p)


cdef int check_regions(const int[:, ::1] regions, int W, int H) except -1:
    cdef int k, x0, y0, x1, y1
    if regions.shape[0] > 0 and regions.shape[1] != 4:
        raise ValueError(f"regions must have shape (R, 4), got {tuple(regions.shape)}")
    for k in range(regions.shape[0]):
        x0, y0, x1, y1 = regions[k, 0], regions[k, 1], regions[k, 2], regions[k, 3]
        if not (0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H):
            raise ValueError(f"region {k} = {(x0, y0, x1, y1)} is not inside the image")
    return 0


cdef int search_all(Frame* f, const int* regions, int R, double thr) except -1 nogil:
    """:func:`search_region` on each of the ``R`` regions (``x0, y0, x1, y1`` rows), in order."""
    cdef int k
    for k in range(R):
        f.region = k
        search_region(f, regions[4 * k], regions[4 * k + 1], regions[4 * k + 2],
                      regions[4 * k + 3], thr)
    return 0


def search(const unsigned char[:, ::1] image, const int[:, ::1] regions, double thr,
           double diameter_px_min, double diameter_px_max, double min_contrast,
           double max_elongation, double min_fill, bint reject_border, int ring_radius_px,
           int half_limit_px, int max_seeds_per_region, bint want_support):
    """Find and measure the blobs of ``regions`` (rows ``x0, y0, x1, y1``, half-open).

    Regions are searched in order; a seed inside the core of a blob measured
    before (in any region) is skipped.  Returns ``(rows, supports)``: a
    float64 array ``(N, len(COLUMNS))`` and, when ``want_support``, the
    support mask of each blob on its rectangle (uint8 arrays), else ``None``.
    """
    cdef Frame f
    cdef int nb, i, rw, rh, R = regions.shape[0]
    cdef size_t off = 0
    cdef double[:, ::1] rv
    cdef unsigned char[:, ::1] sv
    check_regions(regions, image.shape[1], image.shape[0])
    frame_init(&f, image, diameter_px_min, diameter_px_max, min_contrast, max_elongation,
               min_fill, reject_border, ring_radius_px, half_limit_px, max_seeds_per_region,
               want_support)
    try:
        if R > 0:
            with nogil:  # once for all regions: each hand-over of the GIL costs
                search_all(&f, &regions[0, 0], R, thr)
        nb = <int>(f.rows.n // (NCOL * sizeof(double)))
        rows = np.empty((nb, NCOL), dtype=np.float64)
        if nb:
            rv = rows
            memcpy(&rv[0, 0], f.rows.p, f.rows.n)
        supports = None
        if want_support:
            supports = []
            for i in range(nb):
                rw = <int>(rows[i, 15] - rows[i, 13])
                rh = <int>(rows[i, 16] - rows[i, 14])
                s = np.empty((rh, rw), dtype=np.uint8)
                sv = s
                memcpy(&sv[0, 0], f.supports.p + off, <size_t>rw * rh)
                off += <size_t>rw * rh
                supports.append(s)
        return rows, supports
    finally:
        frame_free(&f)


def measure_regions(const unsigned char[:, ::1] image, const int[:, ::1] regions,
                    const double[:, ::1] pts, const int[::1] point_region, double r2,
                    int noise_step, double min_contrast, double diameter_px_min,
                    double diameter_px_max, double max_elongation, double min_fill,
                    bint reject_border, int ring_radius_px, int half_limit_px,
                    int max_seeds_per_region, bint refine, int max_iter, double pad_px,
                    double min_roundness, double max_hidden):
    """One frame's windowed detection in one call, the GIL released once: the image's
    median and noise (:func:`background_and_noise` at ``noise_step``), the seed
    threshold ``median + max(min_contrast / 2, 4 sigma)``, :func:`search` of the
    ``regions`` without supports, :func:`select` against ``pts`` (``point_region``
    their region, ``r2`` the squared radius) and, when ``refine``, :func:`refine_rows`
    of the kept rows with the threshold as dark level and the other blobs the searched
    ones (edges 1).  The same numbers as those calls one after the other
    (``tests/core/test_markers.py``).

    Returns ``(rows (N, len(COLUMNS)), threshold, sigma)``.
    """
    cdef Frame f
    cdef int R = regions.shape[0], K = pts.shape[0], H = image.shape[0], W = image.shape[1]
    cdef int nb = 0, n_kept = 0, i, cap = 1
    cdef double bg = 0.0, sigma = 0.0, thr = 0.0
    cdef double* all_rows
    cdef double* kept_p = NULL
    cdef double* xy = NULL
    cdef double* buf = NULL
    cdef Py_ssize_t* keep = NULL
    cdef double[:, ::1] kv
    if noise_step < 1:
        raise ValueError(f"noise_step must be >= 1, got {noise_step}")
    if K > 0 and (pts.shape[1] != 2 or point_region.shape[0] < K):
        raise ValueError("pts must have shape (K, 2) and point_region K entries")
    check_regions(regions, W, H)
    if R == 0:
        return np.zeros((0, NCOL)), 0.0, 0.0
    frame_init(&f, image, diameter_px_min, diameter_px_max, min_contrast, max_elongation,
               min_fill, reject_border, ring_radius_px, half_limit_px, max_seeds_per_region,
               False)
    try:
        with nogil:
            bg_noise_c(&image[0, 0], H, W, noise_step, &bg, &sigma)
            thr = bg + max(0.5 * min_contrast, 4.0 * sigma)
            search_all(&f, &regions[0, 0], R, thr)
            nb = <int>(f.rows.n // (NCOL * sizeof(double)))
            all_rows = <double*>f.rows.p
            if nb > 0:
                keep = <Py_ssize_t*>malloc(nb * sizeof(Py_ssize_t))
                kept_p = <double*>malloc(nb * NCOL * sizeof(double))
                xy = <double*>malloc(2 * nb * sizeof(double))
                if keep == NULL or kept_p == NULL or xy == NULL:
                    with gil:
                        raise MemoryError()
                n_kept = select_c(all_rows, nb, &pts[0, 0] if K > 0 else NULL, K,
                                  &point_region[0] if K > 0 else NULL, r2, keep)
                for i in range(n_kept):
                    memcpy(kept_p + i * NCOL, all_rows + keep[i] * NCOL, NCOL * sizeof(double))
                if refine and n_kept > 0:
                    for i in range(nb):
                        xy[2 * i] = all_rows[i * NCOL]
                        xy[2 * i + 1] = all_rows[i * NCOL + 1]
                    cap = refine_cap(kept_p, n_kept, pad_px)
                    buf = <double*>malloc(3 * cap * sizeof(double))
                    if buf == NULL:
                        with gil:
                            raise MemoryError()
                    refine_c(&image[0, 0], W, H, kept_p, n_kept, xy, nb, max_iter, thr, pad_px,
                             min_roundness, sigma, 1, max_hidden, buf, cap)
        rows = np.empty((n_kept, NCOL), dtype=np.float64)
        if n_kept:
            kv = rows
            memcpy(&kv[0, 0], kept_p, n_kept * NCOL * sizeof(double))
        return rows, thr, sigma
    finally:
        frame_free(&f)
        free(keep)
        free(kept_p)
        free(xy)
        free(buf)


# ------------------------------------------------------------------ candidates

cdef void bg_noise_c(const unsigned char* img, int H, int W, int step, double* bg,
                     double* sigma) noexcept nogil:
    """:func:`background_and_noise` on a C-contiguous image, ``step >= 1``."""
    cdef int hist[256]
    cdef int parts[4][256]  # four counts, so that equal neighbours do not wait on each other
    cdef int x, y, n, q25, q50, v
    cdef int ny = (H + step - 1) // step, nx = (W + step - 1) // step
    cdef const unsigned char* row
    memset(parts, 0, sizeof(parts))
    for y in range(ny):
        row = img + <size_t>(y * step) * W
        x = 0
        while x + 3 < nx:
            parts[0][row[x * step]] += 1
            parts[1][row[(x + 1) * step]] += 1
            parts[2][row[(x + 2) * step]] += 1
            parts[3][row[(x + 3) * step]] += 1
            x += 4
        while x < nx:
            parts[0][row[x * step]] += 1
            x += 1
    for v in range(256):
        hist[v] = parts[0][v] + parts[1][v] + parts[2][v] + parts[3][v]
    n = ny * nx
    q25 = kth(hist, (n + 3) // 4 - 1)
    q50 = kth(hist, (n + 1) // 2 - 1)
    bg[0] = <double>q50
    sigma[0] = max((q50 - q25) / 0.6745, 0.7)


def background_and_noise(const unsigned char[:, ::1] image, int step):
    """Median and noise sigma (gray levels) of ``image[::step, ::step]``.

    Sigma comes from the lower half only (median minus first quartile), since
    the bright blobs are outliers on the upper side; at least 0.7 (the
    quantisation floor).
    """
    cdef double bg = 0.0, sigma = 0.0
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    with nogil:
        bg_noise_c(&image[0, 0], image.shape[0], image.shape[1], step, &bg, &sigma)
    return bg, sigma


def pool_mask(const unsigned char[:, ::1] image, int t, int pool):
    """``(ceil(H / pool), ceil(W / pool))`` uint8: 1 where a pixel of the cell is > t."""
    cdef int H = image.shape[0], W = image.shape[1], x, y, cx, cy, y0, y1, x1, whole
    if pool < 1:
        raise ValueError(f"pool must be >= 1, got {pool}")
    cdef int hp = (H + pool - 1) // pool, wp = (W + pool - 1) // pool
    cdef unsigned char m, tc = <unsigned char>max(0, min(t, 255))
    cdef unsigned int word
    cdef const unsigned char* row
    out = np.zeros((hp, wp), dtype=np.uint8)
    cdef unsigned char[:, ::1] o = out
    if t >= 255:  # no pixel is above
        return out
    if t < 0:
        out[:] = 1
        return out
    cdef unsigned char* colmax = <unsigned char*>malloc(W + 4)
    if colmax == NULL:
        raise MemoryError()
    # whole 4-px cells read as one 32-bit word each (pool 4, the detector's)
    whole = W // 4 if pool == 4 else 0
    with nogil:
        for cy in range(hp):
            # the column maxima of the cell row, then their maximum: loops the
            # compiler vectorises; cells are only looked at in rows that have a hit
            y0 = cy * pool
            y1 = min(H, y0 + pool)
            memcpy(colmax, &image[y0, 0], W)
            for y in range(y0 + 1, y1):
                row = &image[y, 0]
                for x in range(W):
                    colmax[x] = row[x] if row[x] > colmax[x] else colmax[x]
            m = 0
            for x in range(W):
                m = colmax[x] if colmax[x] > m else m
            if m <= tc:
                continue
            for x in range(W):  # 1 above the threshold, 0 not (vectorised)
                colmax[x] = 1 if colmax[x] > tc else 0
            for cx in range(whole):
                memcpy(&word, colmax + 4 * cx, 4)
                o[cy, cx] = 1 if word != 0 else 0
            for cx in range(whole, wp):
                x1 = min(W, cx * pool + pool)
                for x in range(cx * pool, x1):
                    if colmax[x]:
                        o[cy, cx] = 1
                        break
    free(colmax)
    return out


def merged_windows(const double[:, ::1] pts, double reach, int H, int W):
    """Square windows of half-size ``reach`` around the points, overlapping ones merged
    into their bounding box (repeatedly, first pair first), clipped to the image.

    Returns ``(regions (R, 4) int32 [x0, y0, x1, y1] half-open, region of each
    point (K,) int32)``; a window narrower than 3 px is dropped (its points get -1).
    """
    cdef int K = pts.shape[0], i, j, n, merged, k
    boxes = np.empty((max(K, 1), 4), dtype=np.float64)
    owner = np.arange(K, dtype=np.int32)
    cdef double[:, ::1] b = boxes
    cdef int[::1] own = owner
    cdef double ax0, ay0, ax1, ay1
    for i in range(K):
        b[i, 0] = pts[i, 0] - reach
        b[i, 1] = pts[i, 1] - reach
        b[i, 2] = pts[i, 0] + reach
        b[i, 3] = pts[i, 1] + reach
    n = K
    merged = 1
    while merged and n > 1:
        merged = 0
        for i in range(n):
            for j in range(i + 1, n):
                if b[i, 0] <= b[j, 2] and b[j, 0] <= b[i, 2] and b[i, 1] <= b[j, 3] and b[j, 1] <= b[i, 3]:
                    b[i, 0] = min(b[i, 0], b[j, 0])
                    b[i, 1] = min(b[i, 1], b[j, 1])
                    b[i, 2] = max(b[i, 2], b[j, 2])
                    b[i, 3] = max(b[i, 3], b[j, 3])
                    for k in range(K):  # box j joins box i; later boxes move up
                        if own[k] == j:
                            own[k] = i
                        elif own[k] > j:
                            own[k] -= 1
                    for k in range(j, n - 1):
                        b[k, 0], b[k, 1], b[k, 2], b[k, 3] = b[k + 1, 0], b[k + 1, 1], b[k + 1, 2], b[k + 1, 3]
                    n -= 1
                    merged = 1
                    break
            if merged:
                break
    regions = np.empty((n, 4), dtype=np.int32)
    cdef int[:, ::1] r = regions
    renumber = np.empty(max(n, 1), dtype=np.int32)
    cdef int[::1] ren = renumber
    cdef int x0, y0, x1, y1, m = 0
    for i in range(n):
        ren[i] = -1
    for i in range(n):
        x0 = max(0, <int>floor(b[i, 0]))
        x1 = min(W, <int>ceil(b[i, 2]) + 1)
        y0 = max(0, <int>floor(b[i, 1]))
        y1 = min(H, <int>ceil(b[i, 3]) + 1)
        if x1 - x0 >= 3 and y1 - y0 >= 3:
            r[m, 0], r[m, 1], r[m, 2], r[m, 3] = x0, y0, x1, y1
            ren[i] = m
            m += 1
    for k in range(K):
        own[k] = ren[own[k]]
    return regions[:m], owner


cdef int select_c(const double* rows, int N, const double* pts, int K,
                  const int* point_region, double r2, Py_ssize_t* keep) noexcept nogil:
    """:func:`select` on C arrays (``rows`` N x NCOL, ``pts`` K x 2); the kept indices go
    to ``keep`` (N of them at most), their number is returned."""
    cdef int i, j, k, n_kept = 0, region, ok
    cdef double x, y, d2, best
    for i in range(N):
        x = rows[i * NCOL]
        y = rows[i * NCOL + 1]
        if K > 0 and x == x and y == y:  # (a NaN centre is not judged, as np.min would not)
            region = <int>rows[i * NCOL + 19]
            best = EDT_INF
            for k in range(K):
                if point_region[k] == region:
                    d2 = (pts[2 * k] - x) * (pts[2 * k] - x) + (pts[2 * k + 1] - y) * (pts[2 * k + 1] - y)
                    if d2 < best:
                        best = d2
            if best > r2:
                continue
        ok = 1
        for j in range(n_kept):
            k = <int>keep[j]
            if (x - rows[k * NCOL]) * (x - rows[k * NCOL]) + (y - rows[k * NCOL + 1]) * (y - rows[k * NCOL + 1]) < 1.0:
                ok = 0
                break
        if ok:
            keep[n_kept] = i
            n_kept += 1
    return n_kept


def any_touching(const double[:, ::1] xy, const double[::1] diam, double gap):
    """True if two of the blobs (centres ``xy`` (N, 2), diameters ``diam``) are closer
    than their mean diameter + ``gap``: ``core.markers._CameraDetections._keep_patches``'
    test, with its operations in its order."""
    cdef Py_ssize_t n = xy.shape[0], i, j
    cdef double xi, yi, dx, dy, lim
    if diam.shape[0] != n:
        raise ValueError(f"diam has {diam.shape[0]} entries for {n} points")
    for i in range(n):
        xi, yi = xy[i, 0], xy[i, 1]
        for j in range(i + 1, n):
            dx, dy = xy[j, 0] - xi, xy[j, 1] - yi
            lim = 0.5 * (diam[i] + diam[j]) + gap
            if dx < lim and -dx < lim and dx * dx + dy * dy < lim * lim:
                return True
    return False


def select(const double[:, ::1] rows, const double[:, ::1] pts, const int[::1] point_region,
           double r2):
    """Indices of the rows to keep, in order: a blob whose centre lies farther than
    ``sqrt(r2)`` from every point of its region is dropped (when points are given),
    and of two centres closer than 1 px the first is kept."""
    cdef int N = rows.shape[0], K = pts.shape[0], n_kept = 0
    if N > 0 and rows.shape[1] != NCOL:
        raise ValueError(f"rows must have {NCOL} columns, got {rows.shape[1]}")
    if K > 0 and (pts.shape[1] != 2 or point_region.shape[0] < K):
        raise ValueError("pts must have shape (K, 2) and point_region K entries")
    keep = np.empty(N, dtype=np.intp)
    cdef Py_ssize_t[::1] kp = keep
    if N > 0:
        n_kept = select_c(&rows[0, 0], N, &pts[0, 0] if K > 0 else NULL, K,
                          &point_region[0] if K > 0 else NULL, r2, &kp[0])
    return keep[:n_kept]


# ------------------------------------------------------------------ disc over a planar background

DEF NPAR = 8   # cx, cy, R, s, A, B0, Bx, By
DEF NE = 11   # cx, cy, R, s, A, B0, Bx, By, theta, c, F: a disc and a straight skin edge
DEF FIT_COLS = 14
DEF HALO_PX = 3  # the second, wider border of the dark-room test (see fit_one)
FIT_COLUMNS = (
    "x", "y", "radius", "edge_sigma", "level", "background", "background_dx", "background_dy",
    "residual_rms", "interior_fill", "pixels", "iterations", "edge_model", "hidden_share",
)
cdef double SQRT1_2 = 0.7071067811865476
cdef double INV_SQRT_2PI = 0.3989422804014327


cdef double disc_pass(const double* xs, const double* ys, const double* zs, int n,
                      const double* p, double xc0, double yc0,
                      double* jtj, double* jtr) noexcept nogil:
    """Sum of squared residuals of the model at ``p``; with ``jtj`` (NPAR x NPAR, upper
    triangle) and ``jtr`` (NPAR) accumulated when they are not NULL."""
    cdef int i, a, b
    cdef double dx, dy, r, u, Phi, phi, pl, m, res, g, cost = 0.0, ex, ey
    cdef double J[NPAR]
    if jtj != NULL:
        memset(jtj, 0, NPAR * NPAR * sizeof(double))
        memset(jtr, 0, NPAR * sizeof(double))
    cdef double inv_s = 1.0 / p[3], e2, t, au
    cdef int first
    for i in range(n):
        dx = xs[i] - p[0]
        dy = ys[i] - p[1]
        r = sqrt(dx * dx + dy * dy) + 1e-9
        u = (p[2] - r) * inv_s
        au = fabs(u)
        ex = xs[i] - xc0
        ey = ys[i] - yc0
        pl = p[5] + p[6] * ex + p[7] * ey
        if au < 6.0:
            # Phi(u) = erfc(-u / sqrt 2) / 2 (Abramowitz & Stegun 7.1.26, error < 1.5e-7),
            # sharing exp(-u^2 / 2) with the density
            e2 = exp(-0.5 * u * u)
            t = 1.0 / (1.0 + 0.3275911 * SQRT1_2 * au)
            Phi = 0.5 * t * (0.254829592 + t * (-0.284496736 + t * (1.421413741
                  + t * (-1.453152027 + t * 1.061405429)))) * e2
            if u > 0:
                Phi = 1.0 - Phi
            phi = e2 * INV_SQRT_2PI
            first = 0
        else:
            Phi = 1.0 if u > 0 else 0.0
            phi = 0.0
            first = 4  # the centre, radius and edge have no influence here
        m = pl + (p[4] - pl) * Phi
        res = zs[i] - m
        cost += res * res
        if jtj == NULL:
            continue
        g = (p[4] - pl) * phi * inv_s
        J[0] = g * dx / r
        J[1] = g * dy / r
        J[2] = g
        J[3] = -g * u
        J[4] = Phi
        J[5] = 1.0 - Phi
        J[6] = ex * (1.0 - Phi)
        J[7] = ey * (1.0 - Phi)
        for a in range(first, NPAR):
            jtr[a] += J[a] * res
            for b in range(a, NPAR):
                jtj[a * NPAR + b] += J[a] * J[b]
    return cost


cdef int solve_damped(const double* jtj, const double* jtr, double lam, double* delta,
                      int n) noexcept nogil:
    """``(JtJ + lam diag(JtJ)) delta = Jtr`` for ``n`` (at most ``NE``) unknowns, by
    Cholesky; 0 when it is not positive definite."""
    cdef double L[NE * NE]
    cdef double y[NE]
    cdef int a, b, k
    cdef double s
    for a in range(n):
        for b in range(a + 1):
            s = jtj[b * n + a]
            if a == b:
                s += lam * jtj[a * n + a] + 1e-9
            for k in range(b):
                s -= L[a * n + k] * L[b * n + k]
            if a == b:
                if s <= 0:
                    return 0
                L[a * n + a] = sqrt(s)
            else:
                L[a * n + b] = s / L[b * n + b]
    for a in range(n):
        s = jtr[a]
        for k in range(a):
            s -= L[a * n + k] * y[k]
        y[a] = s / L[a * n + a]
    for a in range(n - 1, -1, -1):
        s = y[a]
        for k in range(a + 1, n):
            s -= L[k * n + a] * delta[k]
        delta[a] = s / L[a * n + a]
    return 1


#: Edge models of :func:`edge_pass`
DEF EDGE_FRONT = 1   # skin in front of the marker beyond the edge (a finger hides part of it)
DEF EDGE_BEHIND = 2  # the background steps at the edge, under the marker
DEF EDGE_MAX_SIGMA = 1.2  # px: blurrier blobs (motion streaks) are no disc to cut by an edge
DEF EDGE_MIN_RADIUS = 4.0  # px: smaller discs hold too few pixels to place an edge as well


cdef inline void normal_cdf(double u, double* Phi, double* phi) noexcept nogil:
    """``Phi(u)`` (Abramowitz & Stegun 7.1.26) and the density ``phi(u)``; 0/1 beyond 6."""
    cdef double au = fabs(u), e2, t
    if au >= 6.0:
        Phi[0] = 1.0 if u > 0 else 0.0
        phi[0] = 0.0
        return
    e2 = exp(-0.5 * u * u)
    t = 1.0 / (1.0 + 0.3275911 * SQRT1_2 * au)
    Phi[0] = 0.5 * t * (0.254829592 + t * (-0.284496736 + t * (1.421413741
             + t * (-1.453152027 + t * 1.061405429)))) * e2
    if u > 0:
        Phi[0] = 1.0 - Phi[0]
    phi[0] = e2 * INV_SQRT_2PI


cdef double edge_pass(const double* xs, const double* ys, const double* zs, int n,
                      const double* p, double xc0, double yc0, int mode,
                      double* jtj, double* jtr) noexcept nogil:
    """:func:`disc_pass` for a disc and a straight edge ``cos(theta) (x - cx) + sin(theta)
    (y - cy) = c`` blurred like the disc, with the level ``F`` on its far side: skin in
    front of the marker there (``EDGE_FRONT``: ``m = H F + (1 - H) (P + (A - P) Phi)``)
    or a step of the background under it (``EDGE_BEHIND``: ``B = H F + (1 - H) P``,
    ``m = B + (A - B) Phi``); ``H = Phi(e)`` the edge's share of the pixel."""
    cdef int i, a, b
    cdef double dx, dy, r, u, Phi, phi, pl, m, res, cost = 0.0, ex, ey, D, Bk, g, gh
    cdef double e, H, h, de_th
    cdef double J[NE]
    cdef double inv_s = 1.0 / p[3]
    cdef double nx = cos(p[8]), ny = sin(p[8])
    if jtj != NULL:
        memset(jtj, 0, NE * NE * sizeof(double))
        memset(jtr, 0, NE * sizeof(double))
    for i in range(n):
        dx = xs[i] - p[0]
        dy = ys[i] - p[1]
        r = sqrt(dx * dx + dy * dy) + 1e-9
        u = (p[2] - r) * inv_s
        normal_cdf(u, &Phi, &phi)
        ex = xs[i] - xc0
        ey = ys[i] - yc0
        pl = p[5] + p[6] * ex + p[7] * ey
        e = (nx * dx + ny * dy - p[9]) * inv_s
        normal_cdf(e, &H, &h)
        if mode == EDGE_FRONT:
            D = pl + (p[4] - pl) * Phi
            m = H * p[10] + (1.0 - H) * D
        else:
            Bk = H * p[10] + (1.0 - H) * pl
            m = Bk + (p[4] - Bk) * Phi
        res = zs[i] - m
        cost += res * res
        if jtj == NULL:
            continue
        de_th = (-ny * dx + nx * dy) * inv_s
        if mode == EDGE_FRONT:
            g = (1.0 - H) * (p[4] - pl) * phi * inv_s  # d m / d (R - r) through the disc
            gh = (p[10] - D) * h  # d m / d e
            J[4] = (1.0 - H) * Phi
            J[5] = (1.0 - H) * (1.0 - Phi)
        else:
            g = (p[4] - Bk) * phi * inv_s
            gh = (p[10] - pl) * (1.0 - Phi) * h
            J[4] = Phi
            J[5] = (1.0 - H) * (1.0 - Phi)
        J[0] = g * dx / r - gh * nx * inv_s
        J[1] = g * dy / r - gh * ny * inv_s
        J[2] = g
        J[3] = -g * u - gh * e * inv_s
        J[6] = ex * J[5]
        J[7] = ey * J[5]
        J[8] = gh * de_th
        J[9] = -gh * inv_s
        J[10] = H if mode == EDGE_FRONT else H * (1.0 - Phi)
        for a in range(NE):
            jtr[a] += J[a] * res
            for b in range(a, NE):
                jtj[a * NE + b] += J[a] * J[b]
    return cost


cdef double fit_edge(const double* xs, const double* ys, const double* zs, int n, double* p,
                     double xc0, double yc0, int mode, int max_iter) noexcept nogil:
    """Levenberg-Marquardt on :func:`edge_pass` from ``p`` (``NE`` values, in place);
    the final cost."""
    cdef double q[NE]
    cdef double delta[NE]
    cdef double jtj[NE * NE]
    cdef double jtr[NE]
    cdef double jtj_new[NE * NE]
    cdef double jtr_new[NE]
    cdef double lam = 1e-3, cost, cost_new
    cdef int it = 0, tries, a, ok
    cost = edge_pass(xs, ys, zs, n, p, xc0, yc0, mode, jtj, jtr)
    while it < max_iter:
        it += 1
        ok = 0
        for tries in range(6):
            if not solve_damped(jtj, jtr, lam, delta, NE):
                lam *= 10.0
                continue
            for a in range(NE):
                q[a] = p[a] + delta[a]
            q[3] = min(max(q[3], 0.25), 4.0)
            q[2] = max(q[2], 0.5)
            cost_new = edge_pass(xs, ys, zs, n, q, xc0, yc0, mode, jtj_new, jtr_new)
            if cost_new < cost:
                memcpy(p, q, NE * sizeof(double))
                memcpy(jtj, jtj_new, NE * NE * sizeof(double))
                memcpy(jtr, jtr_new, NE * sizeof(double))
                cost = cost_new
                lam = max(lam * 0.1, 1e-7)
                ok = 1
                break
            lam *= 10.0
        if not ok or (fabs(delta[0]) < 1e-3 and fabs(delta[1]) < 1e-3):
            break
    return cost


cdef double cut_share(double R, double c) noexcept nogil:
    """Share of a disc of radius ``R`` beyond a chord at distance ``c`` from its centre."""
    cdef double b
    if c >= R:
        return 0.0
    if c <= -R:
        return 1.0
    b = c / R
    return (acos(b) - b * sqrt(1.0 - b * b)) / M_PI


cdef int border_p90(const unsigned char* img, int W, int x0, int y0, int x1, int y1,
                    int* hist) noexcept nogil:
    """90th percentile (gray level) of the border pixels of the box ``[x0, x1) x [y0, y1)``."""
    cdef int x, y, n
    memset(hist, 0, 256 * sizeof(int))
    for x in range(x0, x1):
        hist[img[<size_t>y0 * W + x]] += 1
        hist[img[<size_t>(y1 - 1) * W + x]] += 1
    for y in range(y0 + 1, y1 - 1):
        hist[img[<size_t>y * W + x0]] += 1
        hist[img[<size_t>y * W + x1 - 1]] += 1
    n = 2 * (x1 - x0) + 2 * (y1 - y0 - 2)
    return kth(hist, (9 * n) // 10)


cdef int fit_one(const unsigned char* img, int W, int H, double cx, double cy, double r0,
                 double half_size, double bg0, double level0, const double* others, int K,
                 int max_iter, double dark_level, int edges, double max_hidden,
                 double* xs, double* ys, double* zs, double* o) noexcept nogil:
    """One disc fit (see :func:`fit_discs`); writes ``FIT_COLS`` values to ``o``, which
    the caller filled with NaN.  ``xs``, ``ys``, ``zs`` hold the window's pixels."""
    cdef int k, x, y, x0, y0, x1, y1, n, it, hs, tries, n_in, n_bright, a, ok
    cdef int fx0, fy0, fx1, fy1, mode = 0, kk
    cdef double d_own, dk, cost, cost_new, lam, dx, dy, r, pl
    cdef double sx, sy, w, Phi, phi, th_r, th_g, cost_e
    cdef double pe[NE]
    cdef double best[NE]
    cdef double p[NPAR]
    cdef double q[NPAR]
    cdef double delta[NPAR]
    cdef double jtj[NPAR * NPAR]
    cdef double jtr[NPAR]
    cdef double jtj_new[NPAR * NPAR]
    cdef double jtr_new[NPAR]
    cdef int hist[256]
    if not (cx == cx and cy == cy):
        return 0
    hs = <int>ceil(half_size)
    x0 = max(0, <int>floor(cx + 0.5) - hs)
    y0 = max(0, <int>floor(cy + 0.5) - hs)
    x1 = min(W, <int>floor(cx + 0.5) + hs + 1)
    y1 = min(H, <int>floor(cy + 0.5) + hs + 1)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return 0
    if dark_level >= 0:
        if border_p90(img, W, x0, y0, x1, y1, hist) <= dark_level:
            o[11] = 0
            return 0
        # A soft blob (a glint) brightens the border with its own halo. When the border
        # HALO_PX farther out is dark and holds no other blob, it stands on the dark room
        # all the same, where the centroid is exact: no fit. Lit skin or a finger's edge
        # that reaches the first border reaches the wider one as much or more.
        fx0 = max(0, x0 - HALO_PX)
        fy0 = max(0, y0 - HALO_PX)
        fx1 = min(W, x1 + HALO_PX)
        fy1 = min(H, y1 + HALO_PX)
        ok = fx0 < x0 and fy0 < y0 and fx1 > x1 and fy1 > y1  # not cut by the image edge
        for k in range(K):
            if not ok:
                break
            dx = others[2 * k] - cx
            dy = others[2 * k + 1] - cy
            if (dx * dx + dy * dy > 0.25 and fx0 <= others[2 * k] + 0.5 < fx1
                    and fy0 <= others[2 * k + 1] + 0.5 < fy1):
                ok = 0
        if ok and border_p90(img, W, fx0, fy0, fx1, fy1, hist) <= dark_level:
            o[11] = 0
            return 0
    n = 0
    for y in range(y0, y1):
        for x in range(x0, x1):
            d_own = (x - cx) * (x - cx) + (y - cy) * (y - cy)
            ok = 1
            for k in range(K):
                dk = (x - others[2 * k]) * (x - others[2 * k]) + (y - others[2 * k + 1]) * (y - others[2 * k + 1])
                if dk < d_own and ((others[2 * k] - cx) * (others[2 * k] - cx)
                                   + (others[2 * k + 1] - cy) * (others[2 * k + 1] - cy)) > 0.25:
                    ok = 0
                    break
            if ok:
                xs[n] = x
                ys[n] = y
                zs[n] = img[<size_t>y * W + x]
                n += 1
    if n < 3 * NPAR:
        return 0
    p[0] = cx
    p[1] = cy
    p[2] = max(r0, 1.0)
    p[3] = 0.7
    p[4] = level0
    p[5] = bg0
    p[6] = 0.0
    p[7] = 0.0
    lam = 1e-3
    cost = disc_pass(xs, ys, zs, n, p, cx, cy, jtj, jtr)
    it = 0
    while it < max_iter:
        it += 1
        ok = 0
        for tries in range(6):
            if not solve_damped(jtj, jtr, lam, delta, NPAR):
                lam *= 10.0
                continue
            for a in range(NPAR):
                q[a] = p[a] + delta[a]
            q[3] = min(max(q[3], 0.25), 4.0)
            q[2] = max(q[2], 0.5)
            cost_new = disc_pass(xs, ys, zs, n, q, cx, cy, jtj_new, jtr_new)
            if cost_new < cost:
                memcpy(p, q, NPAR * sizeof(double))
                memcpy(jtj, jtj_new, NPAR * NPAR * sizeof(double))
                memcpy(jtr, jtr_new, NPAR * sizeof(double))
                cost = cost_new
                lam = max(lam * 0.1, 1e-7)
                ok = 1
                break
            lam *= 10.0
        if not ok or (fabs(delta[0]) < 1e-3 and fabs(delta[1]) < 1e-3):
            break
    o[12] = 0
    o[13] = 0.0
    if edges and p[3] <= EDGE_MAX_SIGMA and p[2] >= EDGE_MIN_RADIUS:
        # A straight skin edge near the marker: a step of the background under it (from
        # the plane's gradient, either side) or skin in front of part of it (from where
        # the disc's rim is darker than the fitted disc). The best of the three models;
        # the one in front only when its edge reaches within 0.5 px of the disc.
        sx = 0.0
        sy = 0.0
        for k in range(n):
            dx = xs[k] - p[0]
            dy = ys[k] - p[1]
            r = sqrt(dx * dx + dy * dy)
            if p[2] - 2.5 < r < p[2] + 0.5:
                normal_cdf((p[2] - r) / p[3], &Phi, &phi)
                pl = p[5] + p[6] * (xs[k] - cx) + p[7] * (ys[k] - cy)
                w = pl + (p[4] - pl) * Phi - zs[k]
                if w > 0:
                    sx += w * dx
                    sy += w * dy
        th_r = atan2(sy, sx)
        th_g = atan2(p[7], p[6])
        for a in range(NPAR):
            best[a] = p[a]
        best[8] = 0.0
        best[9] = 0.0
        best[10] = 0.0
        cost_e = cost
        for kk in range(3):
            for a in range(NPAR):
                pe[a] = p[a]
            pe[10] = p[5]
            if kk < 2:
                pe[8] = th_g + kk * M_PI
                pe[9] = p[2] + 1.0
                cost_new = fit_edge(xs, ys, zs, n, pe, cx, cy, EDGE_BEHIND, max_iter)
            else:
                pe[8] = th_r
                pe[9] = p[2] - 0.3
                cost_new = fit_edge(xs, ys, zs, n, pe, cx, cy, EDGE_FRONT, max_iter)
                if pe[2] - pe[9] < -0.5:
                    continue  # the edge passes beside the disc: no part of it hidden
            if cost_new < cost_e:
                cost_e = cost_new
                memcpy(best, pe, NE * sizeof(double))
                mode = EDGE_BEHIND if kk < 2 else EDGE_FRONT
        if mode:
            o[12] = mode
            o[13] = cut_share(best[2], best[9]) if mode == EDGE_FRONT else 0.0
            if o[13] <= max_hidden:  # else the plain fit's centre, with the share it hides
                for a in range(NPAR):
                    p[a] = best[a]
                cost = cost_e
    n_in = 0
    n_bright = 0
    for k in range(n):
        dx = xs[k] - p[0]
        dy = ys[k] - p[1]
        r = sqrt(dx * dx + dy * dy)
        if r < p[2] - 1.5:
            n_in += 1
            pl = p[5] + p[6] * (xs[k] - cx) + p[7] * (ys[k] - cy)
            n_bright += zs[k] > pl + 0.5 * (p[4] - pl)
    for a in range(NPAR):
        o[a] = p[a]
    o[8] = sqrt(cost / n)
    o[9] = <double>n_bright / n_in if n_in > 0 else NAN
    o[10] = n
    o[11] = it
    return 1


def fit_discs(const unsigned char[:, ::1] image, const double[:, ::1] seeds,
              const double[:, ::1] others, int max_iter, double dark_level, int edges=0):
    """Fit an opaque blurred disc over a planar background to each seed's window.

    Model of a pixel at ``(x, y)``: ``P + (A - P) Phi((R - r) / s)`` with ``r``
    the distance to the centre ``(cx, cy)``, ``Phi`` the normal CDF and ``P =
    B0 + Bx (x - x0) + By (y - y0)`` the background plane (``(x0, y0)`` the
    seed): the marker *replaces* what is behind it, so a gradient or an edge
    of lit skin under it does not pull the centre as it pulls a centroid.
    Levenberg-Marquardt from the seed, at most ``max_iter`` steps.

    Parameters
    ----------
    image : (H, W) uint8
    seeds : (N, 6) float64
        ``x, y, radius, half_size, background, level``: starting centre and
        radius (px), half-size of the square window (px), and starting
        background and marker levels (gray levels).
    others : (K, 2) float64
        Centres of other blobs: window pixels nearer to one of them than to
        the seed are left out (a seed's own centre, within 0.5 px, is ignored).
    max_iter : int
    dark_level : float
        A window whose border is at most this bright at its 90th percentile
        (gray levels) lies on the dark background, where the centroid is
        already exact: it is not fitted (NaN centre, 0 steps); so is a window
        whose border only the blob's own halo brightens (a soft glint): the
        border ``HALO_PX`` (3) px farther out is that dark and holds no other
        blob's centre.  -1 fits every window.
    edges : int
        1: after the plain fit of a sharp disc (edge sigma at most 1.2 px: not a
        motion streak) of radius 4 px or more (smaller ones hold too few pixels to
        place an edge as well), also fit a straight skin edge with the disc
        (:func:`edge_pass`): a step of the background under the marker (the
        plane's gradient as its normal, either way) and skin in front of part
        of it (the normal towards where the rim is darker than the plain fit),
        and keep the best of the three; the edge in front only when it reaches
        within 0.5 px of the disc. 0: the plain fit only.

    Returns
    -------
    (N, len(FIT_COLUMNS)) float64
        ``FIT_COLUMNS``: the fitted parameters, the residual RMS (gray levels),
        ``interior_fill`` (share of the pixels more than 1.5 px inside the
        fitted rim that are brighter than half way between background and
        marker), the number of pixels and of steps (of the plain fit), the
        model kept (0 plain, 1 skin in front, 2 a step behind) and the share of
        the disc the skin in front hides; NaN centre when the window is too
        small or dark, or has too few pixels.
    """
    cdef int N = seeds.shape[0], K = others.shape[0], H = image.shape[0], W = image.shape[1]
    cdef int i, hs, cap = 1
    if seeds.shape[0] > 0 and seeds.shape[1] != 6:
        raise ValueError(f"seeds must have shape (N, 6), got {tuple(seeds.shape)}")
    if others.shape[0] > 0 and others.shape[1] != 2:
        raise ValueError(f"others must have shape (K, 2), got {tuple(others.shape)}")
    out = np.full((N, FIT_COLS), np.nan)
    cdef double[:, ::1] o = out
    for i in range(N):
        hs = <int>ceil(seeds[i, 3]) if seeds[i, 3] == seeds[i, 3] else 0
        cap = max(cap, (2 * hs + 3) * (2 * hs + 3))
    cdef double* buf = <double*>malloc(3 * cap * sizeof(double))
    if buf == NULL:
        raise MemoryError()
    cdef const double* oth = &others[0, 0] if K > 0 else NULL
    try:
        with nogil:
            for i in range(N):
                fit_one(&image[0, 0], W, H, seeds[i, 0], seeds[i, 1], seeds[i, 2], seeds[i, 3],
                        seeds[i, 4], seeds[i, 5], oth, K, max_iter, dark_level, edges, 1.0,
                        buf, buf + cap, buf + 2 * cap, &o[i, 0])
    finally:
        free(buf)
    return out


cdef int refine_cap(const double* rows, int N, double pad_px) noexcept nogil:
    """Pixels of the largest fit window of :func:`refine_c` over ``rows``."""
    cdef int i, hs, cap = 1
    cdef double half
    for i in range(N):
        half = 0.5 * rows[i * NCOL + 2] / max(rows[i * NCOL + 4], 0.1) + pad_px
        hs = <int>ceil(half) if half == half else 0
        cap = max(cap, (2 * hs + 3) * (2 * hs + 3))
    return cap


cdef void refine_c(const unsigned char* img, int W, int H, double* rows, int N,
                   const double* oth, int K, int max_iter, double dark_level, double pad_px,
                   double min_roundness, double noise_sigma, int edges, double max_hidden,
                   double* buf, int cap) noexcept nogil:
    """:func:`refine_rows` on C arrays (``rows`` N x NCOL, ``oth`` K x 2); ``buf`` holds
    ``3 * refine_cap(rows, N, pad_px)`` doubles."""
    cdef int i, k
    cdef double o[FIT_COLS]
    cdef double diam, rnd, moved, contrast
    cdef double* r
    for i in range(N):
        r = rows + i * NCOL
        diam = r[2]
        rnd = r[4]
        if not rnd >= min_roundness:
            r[20] = INFINITY  # not a disc: a streak, or cut or merged discs
            continue
        for k in range(FIT_COLS):
            o[k] = NAN
        if not fit_one(img, W, H, r[0], r[1], 0.5 * diam,
                       0.5 * diam / max(rnd, 0.1) + pad_px, r[5],
                       r[5] + r[3], oth, K, max_iter, dark_level, edges,
                       max_hidden, buf, buf + cap, buf + 2 * cap, o):
            continue
        moved = sqrt((o[0] - r[0]) * (o[0] - r[0]) + (o[1] - r[1]) * (o[1] - r[1]))
        contrast = o[4] - o[5]
        if not (moved <= 0.25 * diam + 1.0 and contrast > 0
                and fabs(o[2] / (0.5 * diam) - 1.0) < 0.5):
            continue
        r[0] = o[0]
        r[1] = o[1]
        r[20] = sqrt(max(o[8] * o[8] - noise_sigma * noise_sigma, 0.0)) / contrast
        if o[13] > max_hidden:
            r[20] = INFINITY  # a larger part hidden than the edge model is trusted for


def refine_rows(const unsigned char[:, ::1] image, double[:, ::1] rows,
                const double[:, ::1] others, int max_iter, double dark_level, double pad_px,
                double min_roundness, double noise_sigma, int edges=1,
                double max_hidden=1.0):
    """Move the centres of detection ``rows`` (``COLUMNS``, in place) to the fitted
    opaque disc (:func:`fit_discs`) and set their ``fit_residual`` (the residual RMS
    beyond the image noise ``noise_sigma``, over the fitted contrast), for round blobs (``roundness >= min_roundness``) off the
    dark background; the window reaches ``pad_px`` beyond the blob's half length.  A
    fit that moved the centre by more than a quarter diameter + 1 px, found no
    contrast or a radius off by half is not used. ``edges`` as in :func:`fit_discs`;
    a marker whose fitted skin edge in front hides more than ``max_hidden`` of its
    disc keeps the plain fit's centre and gets an infinite residual (set aside)."""
    cdef int N = rows.shape[0], K = others.shape[0], H = image.shape[0], W = image.shape[1]
    cdef int cap = 1
    if N > 0 and rows.shape[1] != NCOL:
        raise ValueError(f"rows must have {NCOL} columns, got {rows.shape[1]}")
    if others.shape[0] > 0 and others.shape[1] != 2:
        raise ValueError(f"others must have shape (K, 2), got {tuple(others.shape)}")
    if N == 0:
        return
    cap = refine_cap(&rows[0, 0], N, pad_px)
    cdef double* buf = <double*>malloc(3 * cap * sizeof(double))
    if buf == NULL:
        raise MemoryError()
    cdef const double* oth = &others[0, 0] if K > 0 else NULL
    try:
        with nogil:
            refine_c(&image[0, 0], W, H, &rows[0, 0], N, oth, K, max_iter, dark_level, pad_px,
                     min_roundness, noise_sigma, edges, max_hidden, buf, cap)
    finally:
        free(buf)

"""ORB descriptors from a numba kernel, equal to OpenCV's for the keypoints OpenCV's ORB detects.

OpenCV's ORB describes a keypoint by 256 intensity tests between pairs of pixels of the level
smoothed by a 7x7 Gaussian (sigma 2), the pairs rotated by the keypoint's orientation. Its
``compute`` copies the level with a border and smooths the copy at every call, and hands the
keypoints through Python objects both ways. Here the level is smoothed once by ``smooth`` (a
separable filter with the Gaussian's float kernel: its values are the ones ORB's tests compare,
where ``cv2.GaussianBlur``'s fixed-point rounding differs by one here and there, and it is the
cheaper of the two) and ``describe`` runs the tests in a kernel, at the keypoints' own orientations.

The 256 test pairs are not a table from anywhere: :func:`intensity_tests` reads them off the
installed OpenCV by describing random images (each test's pair is the one pair of pixels whose
comparisons agree with that bit in every image) and checks them against OpenCV's descriptors at
random orientations before they are used. Where numba is missing or the check fails,
:func:`compiled_orb_available` is False and the extractor keeps OpenCV's ``compute``.

``select_grid`` is the compiled twin of the extractor's grid selection. ``detect_level`` is what
OpenCV's single-level ORB does after its FAST (the best FAST scores, their Harris scores, the best
of those, their orientations), on arrays instead of Python keypoint objects, with the same results
in the same order; its twin is ``ORB.detect`` itself (``OrbExtractor._extract_opencv`` calls it).
"""
from __future__ import annotations

import logging
from functools import lru_cache

import cv2
import numpy as np

from memgs_ros.core.geometry.view import DepthUnits
from memgs_ros.core.runtime.cpu import numba_available

_log = logging.getLogger(__name__)

PATCH_RADIUS = 15  # half of ORB's 31 px patch: the test pairs lie within it
# Adding and subtracting 1.5 * 2^23 rounds a float32 to the nearest integer, halves to even (as
# OpenCV's rounding does), for |x| < 2^22.
_ROUND_MAGIC = np.float32(12582912.0)
_DEG_TO_RAD = np.float32(np.pi / 180.0)
_SMOOTH_KERNEL = cv2.getGaussianKernel(7, 2.0, cv2.CV_64F)  # ORB's descriptor smoothing, 7x7, sigma 2


def _select_grid(pts, resp, n, cell, gx, gy):
    """Twin of ``OrbExtractor._select_indices`` (see there): indices [K] (ascending) of the keypoints
    (level-0 positions pts [N, 2] float32, responses [N] float32) the grid keeps, N > n."""
    m = pts.shape[0]
    cid = np.empty(m, np.int64)
    for i in range(m):
        cid[i] = min(np.int64(pts[i, 1] // cell), gy - 1) * gx + min(np.int64(pts[i, 0] // cell), gx - 1)
    order = np.argsort(-resp, kind="mergesort")  # strongest first, then by index
    per_cell = max(1, n // (gx * gy))
    in_cell = np.zeros(gx * gy, np.int64)
    chosen = np.zeros(m, np.bool_)
    total = 0
    for i in order:
        if in_cell[cid[i]] < per_cell:
            chosen[i] = True
            total += 1
        in_cell[cid[i]] += 1
    if total < n:  # the budget left goes to the strongest leftovers
        for i in order:
            if total == n:
                break
            if not chosen[i]:
                chosen[i] = True
                total += 1
    elif total > n:  # more cells than budget: the weakest chosen go
        for i in np.argsort(resp, kind="mergesort"):
            if total == n:
                break
            if chosen[i]:
                chosen[i] = False
                total -= 1
    return np.flatnonzero(chosen)


def _describe(flat, centres, steps, cos_a, sin_a, tests):
    """Descriptors [N, 32] uint8: bit j of keypoint i is 1 where the smoothed levels (flat [sum
    H * W] uint8; keypoint i at flat[centres[i]] of a level with rows of steps[i]) are darker at the
    first pixel of test j than at the second, the pair tests [4, 256] float32 (x1, y1, x2, y2)
    rotated by the keypoint's angle (cos_a, sin_a [N] float32) and rounded to pixels."""
    n = centres.shape[0]
    out = np.empty((n, 32), np.uint8)
    x1, y1, x2, y2 = tests[0], tests[1], tests[2], tests[3]
    o1 = np.empty(256, np.int64)
    o2 = np.empty(256, np.int64)
    magic = _ROUND_MAGIC
    for i in range(n):
        a = cos_a[i]
        b = sin_a[i]
        step = steps[i]
        for j in range(256):  # rotated offsets first: this loop vectorises
            r1 = (x1[j] * b + y1[j] * a + magic) - magic
            c1 = (x1[j] * a - y1[j] * b + magic) - magic
            r2 = (x2[j] * b + y2[j] * a + magic) - magic
            c2 = (x2[j] * a - y2[j] * b + magic) - magic
            o1[j] = np.int64(np.int32(r1)) * step + np.int64(np.int32(c1))
            o2[j] = np.int64(np.int32(r2)) * step + np.int64(np.int32(c2))
        centre = centres[i]
        for byte in range(32):
            value = 0
            for t in range(8):  # branch-free: the comparisons' outcomes are coin flips
                j = byte * 8 + t
                value |= np.int64(flat[np.uint64(centre + o1[j])] < flat[np.uint64(centre + o2[j])]) << t
            out[i, byte] = value
    return out


# ORB's detection after FAST (OpenCV's single-level ``ORB.detect``), for ``detect_level``: keep the
# best FAST scores, score those by Harris, keep the best Harris scores, orient by the intensity
# centroid. Its order is the order ORB's ``KeyPointsFilter.retainBest`` leaves (libstdc++'s
# ``nth_element`` and ``partition``, ported step by step below), so that everything downstream
# sees the same keypoints in the same order.
_HARRIS_K = np.float32(0.04)
_HARRIS_SCALE = np.float32(1.0) / np.float32(4 * 7 * 255.0)  # 1 / ((1 << 2) * blockSize * 255), blockSize 7
_HARRIS_SCALE4 = _HARRIS_SCALE * _HARRIS_SCALE * _HARRIS_SCALE * _HARRIS_SCALE
_EPS32 = np.float32(2.220446049250313e-16)  # (float)DBL_EPSILON in OpenCV's fastAtan2
_DEG = np.float32(180.0 / np.pi)
_ATAN_P1 = np.float32(0.9997878412794807) * _DEG
_ATAN_P3 = np.float32(-0.3258083974640975) * _DEG
_ATAN_P5 = np.float32(0.1555786518463281) * _DEG
_ATAN_P7 = np.float32(-0.04432655554792128) * _DEG
_F90, _F180, _F360 = np.float32(90.0), np.float32(180.0), np.float32(360.0)


def _umax(half: int) -> np.ndarray:
    """Half-width of ORB's circular orientation patch per row (OpenCV's ``umax``, made symmetric)."""
    umax = np.zeros(half + 2, np.int64)
    root2 = np.float32(np.sqrt(np.float32(2.0)))
    vmax = int(np.floor(np.float32(half) * root2 / np.float32(2) + np.float32(1)))
    vmin = int(np.ceil(np.float32(half) * root2 / np.float32(2)))
    for v in range(vmax + 1):
        umax[v] = int(np.rint(np.sqrt(float(half * half - v * v))))
    v0 = 0
    for v in range(half, vmin - 1, -1):
        while umax[v0] == umax[v0 + 1]:
            v0 += 1
        umax[v] = v0
        v0 += 1
    return umax


_UMAX = _umax(PATCH_RADIUS)


def _adjust_heap(a, key, first, hole, length, value):
    """libstdc++'s ``__adjust_heap`` then ``__push_heap`` on a[first:first + length], ordered by key descending."""
    top = hole
    child = hole
    while child < (length - 1) // 2:
        child = 2 * (child + 1)
        if key[a[first + child]] > key[a[first + child - 1]]:
            child -= 1
        a[first + hole] = a[first + child]
        hole = child
    if (length & 1) == 0 and child == (length - 2) // 2:
        child = 2 * (child + 1)
        a[first + hole] = a[first + child - 1]
        hole = child - 1
    parent = (hole - 1) // 2
    while hole > top and key[a[first + parent]] > key[value]:
        a[first + hole] = a[first + parent]
        hole = parent
        parent = (hole - 1) // 2
    a[first + hole] = value


def _nth_element(a, key, first, nth, last):
    """libstdc++'s ``std::nth_element(a + first, a + nth, a + last)`` with ``key[i] > key[j]`` as the
    order (OpenCV's ``KeypointResponseGreater``): the same permutation of a, step by step."""
    if first == last or nth == last:
        return
    n = last - first
    depth = 0
    while n > 1:
        n >>= 1
        depth += 1
    depth *= 2
    while last - first > 3:
        if depth == 0:  # heap select, then the nth in place
            middle = nth + 1
            length = middle - first
            if length >= 2:
                parent = (length - 2) // 2
                while True:
                    _adjust_heap(a, key, first, parent, length, a[first + parent])
                    if parent == 0:
                        break
                    parent -= 1
            for i in range(middle, last):
                if key[a[i]] > key[a[first]]:
                    value = a[i]
                    a[i] = a[first]
                    _adjust_heap(a, key, first, 0, length, value)
            a[first], a[nth] = a[nth], a[first]
            return
        depth -= 1
        # median of (first + 1, mid, last - 1) moved to first, then the unguarded partition
        mid = first + (last - first) // 2
        x, y, z = first + 1, mid, last - 1
        xy, yz, xz = key[a[x]] > key[a[y]], key[a[y]] > key[a[z]], key[a[x]] > key[a[z]]
        if xy:
            m = y if yz else (z if xz else x)
        else:
            m = x if xz else (z if yz else y)
        a[first], a[m] = a[m], a[first]
        lo, hi = first + 1, last
        pivot = key[a[first]]
        while True:
            while key[a[lo]] > pivot:
                lo += 1
            hi -= 1
            while pivot > key[a[hi]]:
                hi -= 1
            if not lo < hi:
                break
            a[lo], a[hi] = a[hi], a[lo]
            lo += 1
        if lo <= nth:
            first = lo
        else:
            last = lo
    # insertion sort of what is left
    for i in range(first + 1, last):
        value = a[i]
        if key[value] > key[a[first]]:
            for j in range(i, first, -1):
                a[j] = a[j - 1]
            a[first] = value
        else:
            j = i
            while key[value] > key[a[j - 1]]:
                a[j] = a[j - 1]
                j -= 1
            a[j] = value


def _retain_best(a, count, key, n):
    """OpenCV's ``KeyPointsFilter::retainBest`` on a[:count]: the n best by key, and every one tied
    with the nth, in the order ``nth_element`` and ``std::partition`` leave; the new count."""
    if count <= n:
        return count
    if n == 0:
        return 0
    _nth_element(a, key, 0, n - 1, count)
    threshold = key[a[n - 1]]
    lo, hi = n, count  # libstdc++'s bidirectional ``partition``: keep key >= threshold in front
    while True:
        while lo != hi and key[a[lo]] >= threshold:
            lo += 1
        if lo == hi:
            return lo
        hi -= 1
        while lo != hi and not key[a[hi]] >= threshold:
            hi -= 1
        if lo == hi:
            return lo
        a[lo], a[hi] = a[hi], a[lo]
        lo += 1


def _harris(flat, centre, step, pix):
    """ORB's Harris score (7x7 block, k 0.04) at ``centre`` of the level flat [H * W] uint8 (row
    ``step``); float32 as OpenCV's. Its derivatives are OpenCV's 3x3 Sobel, taken as a difference
    then a [1, 2, 1] sum on the 9x9 pixels read once into ``pix`` [9, 9] int32; the integer sums
    are exact in any order."""
    for r in range(9):
        row = np.uint64(centre + (r - 4) * step - 4)
        for q in range(9):
            pix[r, q] = flat[row + np.uint64(q)]
    a = 0
    b = 0
    c = 0
    for r in range(1, 8):
        for q in range(1, 8):
            ix = ((pix[r - 1, q + 1] - pix[r - 1, q - 1]) + 2 * (pix[r, q + 1] - pix[r, q - 1])
                  + (pix[r + 1, q + 1] - pix[r + 1, q - 1]))
            iy = ((pix[r + 1, q - 1] - pix[r - 1, q - 1]) + 2 * (pix[r + 1, q] - pix[r - 1, q])
                  + (pix[r + 1, q + 1] - pix[r - 1, q + 1]))
            a += ix * ix
            b += iy * iy
            c += ix * iy
    fa, fb, fc = np.float32(a), np.float32(b), np.float32(c)
    s = fa + fb
    return (fa * fb - fc * fc - _HARRIS_K * s * s) * _HARRIS_SCALE4


def _fast_atan2(y, x):
    """OpenCV's ``fastAtan2`` (degrees, float32 polynomial)."""
    ax, ay = abs(x), abs(y)
    if ax >= ay:
        c = ay / (ax + _EPS32)
        c2 = c * c
        r = (((_ATAN_P7 * c2 + _ATAN_P5) * c2 + _ATAN_P3) * c2 + _ATAN_P1) * c
    else:
        c = ax / (ay + _EPS32)
        c2 = c * c
        r = _F90 - (((_ATAN_P7 * c2 + _ATAN_P5) * c2 + _ATAN_P3) * c2 + _ATAN_P1) * c
    if x < 0:
        r = _F180 - r
    if y < 0:
        r = _F360 - r
    return r


def _orientation(flat, centre, step, umax):
    """ORB's intensity-centroid angle (degrees) of the circular patch (half-widths ``umax`` per row)
    around ``centre`` of the level flat [H * W] uint8 (row ``step``); the integer moments summed row
    by row (exact in any order)."""
    half = umax.shape[0] - 2
    m01 = 0
    m10 = 0
    for v in range(-half, half + 1):
        d = half if v == 0 else umax[abs(v)]
        row = np.uint64(centre + v * step)
        total = 0
        moment = 0
        for u in range(1, d + 1):
            right = np.int64(flat[row + np.uint64(u)])
            left = np.int64(flat[row - np.uint64(u)])
            total += right + left
            moment += u * (right - left)
        total += np.int64(flat[row])
        m01 += v * total
        m10 += moment
    return _fast_atan2(np.float32(m01), np.float32(m10))


# FAST's circle of 16 pixels (x, y) in OpenCV's order (``makeOffsets``), then its first 9 again
# so that every arc of 9 is a run of the array.
_FAST_CIRCLE = np.array([(0, 3), (1, 3), (2, 2), (3, 1), (3, 0), (3, -1), (2, -2), (1, -3), (0, -3), (-1, -3),
                         (-2, -2), (-3, -1), (-3, 0), (-3, 1), (-2, 2), (-1, 3)], np.int64)
_FAST_RING = np.concatenate([_FAST_CIRCLE, _FAST_CIRCLE[:9]])


def _fast_score(flat, centre, step, threshold, ring, d):
    """OpenCV's FAST score (``cornerScore<16>``) of the corner at ``centre`` of a level flat [H * W]
    uint8 (row ``step``), found at ``threshold``: the largest difference by which an arc of 9 of
    the circle ``ring`` [25, 2] is all brighter or all darker than the centre, less one; d [25]
    int64 is scratch."""
    v = np.int64(flat[centre])
    for k in range(25):
        d[k] = v - np.int64(flat[centre + ring[k, 1] * step + ring[k, 0]])
    a0 = np.int64(threshold)
    for k in range(0, 16, 2):
        a = min(d[k + 1], d[k + 2], d[k + 3])
        if a <= a0:
            continue
        a = min(a, d[k + 4], d[k + 5], d[k + 6], d[k + 7], d[k + 8])
        a0 = max(a0, min(a, d[k]), min(a, d[k + 9]))
    b0 = -a0
    for k in range(0, 16, 2):
        b = max(d[k + 1], d[k + 2], d[k + 3], d[k + 4], d[k + 5])
        if b >= b0:
            continue
        b = max(b, d[k + 6], d[k + 7], d[k + 8])
        b0 = min(b0, max(b, d[k]), max(b, d[k + 9]))
    return -b0 - 1


def _fast_scores(flat, offsets, widths, xy, starts, threshold, ring):
    """FAST scores [N] float32 of the corners xy [N, 2] (level positions; level k's at
    xy[starts[k]:starts[k + 1]]) on the levels at flat[offsets[k]:] of rows widths[k]."""
    out = np.empty(xy.shape[0], np.float32)
    d = np.empty(25, np.int64)
    for k in range(offsets.shape[0]):
        w = widths[k]
        for i in range(starts[k], starts[k + 1]):
            centre = offsets[k] + np.int64(xy[i, 1]) * w + np.int64(xy[i, 0])
            out[i] = np.float32(_fast_score(flat, centre, w, threshold, ring, d))
    return out


def _detect_level(flat, offset, w, h, xy, score, first, last, n, edge, umax, idx, response, angle, orient,
                  threshold, ring):
    """OpenCV's single-level ORB detection after its FAST (positions xy[first:last] [., 2] float32,
    scores [.] float32, in FAST's order) on the level at flat[offset:] [h, w] uint8, keeping n:
    writes the indices into xy in ORB's order, their Harris responses and angles (float32) to
    idx, response and angle from ``first`` on (angles only where ``orient``); returns how many.
    ``threshold`` >= 0: the scores are not given but computed (``_fast_score`` at that threshold,
    with FAST's ``ring``), and only where ORB ranks by them: when the level has more corners than
    it keeps, which on fr1/rpy is a level or two of eight."""
    a = idx[first:last]
    count = 0
    if 2 * edge < w and 2 * edge < h:
        for i in range(first, last):  # KeyPointsFilter::runByImageBorder, order kept
            if edge <= xy[i, 0] < w - edge and edge <= xy[i, 1] < h - edge:
                a[count] = i
                count += 1
    if threshold >= 0 and count > 2 * n:
        d = np.empty(25, np.int64)
        for q in range(count):
            i = a[q]
            score[i] = np.float32(_fast_score(flat, offset + np.int64(xy[i, 1]) * w + np.int64(xy[i, 0]), w,
                                              threshold, ring, d))
    count = _retain_best(a, count, score, 2 * n)
    pix = np.empty((9, 9), np.int32)
    for k in range(count):
        i = a[k]
        response[i] = _harris(flat, offset + np.int64(np.rint(xy[i, 1])) * w + np.int64(np.rint(xy[i, 0])), w, pix)
    count = _retain_best(a, count, response, n)
    for k in range(count if orient else 0):
        i = a[k]
        centre = offset + np.int64(np.rint(xy[i, 1])) * w + np.int64(np.rint(xy[i, 0]))
        angle[i] = _orientation(flat, centre, w, umax)
    return count


def _detect_select(flat, offsets, widths, heights, xy, score, starts, counts, edge, umax, scales, n, cell, gx, gy,
                   threshold, ring):
    """ORB's detection after FAST on every level (``_detect_level``; FAST's corners of level k are
    xy[starts[k]:starts[k + 1]], level positions) and the grid's selection of at most n
    (``_select_grid``) in one call. Returns the kept keypoints in level order, each level in ORB's
    order, as (level-0 positions [K, 2] float32 (level positions times scales[level], as OpenCV
    scales them), level positions [K, 2], levels [K], angles [K] degrees) and how many ORB kept."""
    N = xy.shape[0]
    idx = np.empty(N, np.int64)
    response = np.zeros(N, np.float32)
    angle = np.empty(0, np.float32)  # unused: the chosen ones are oriented below
    kept = np.empty(N, np.int64)
    level = np.empty(N, np.int64)
    m = 0
    for k in range(offsets.shape[0]):
        first = starts[k]
        c = _detect_level(flat, offsets[k], widths[k], heights[k], xy, score, first, starts[k + 1], counts[k],
                          edge, umax, idx, response, angle, False, threshold, ring)
        for q in range(c):
            kept[m] = idx[first + q]
            level[m] = k
            m += 1
    pts = np.empty((m, 2), np.float32)
    resp = np.empty(m, np.float32)
    for q in range(m):
        sc = scales[level[q]]
        pts[q, 0] = xy[kept[q], 0] * sc
        pts[q, 1] = xy[kept[q], 1] * sc
        resp[q] = response[kept[q]]
    chosen = _select_grid(pts, resp, n, cell, gx, gy) if m > n else np.arange(m)
    K = chosen.shape[0]
    out_pts = np.empty((K, 2), np.float32)
    out_xy = np.empty((K, 2), np.float32)
    out_level = np.empty(K, np.int64)
    out_angle = np.empty(K, np.float32)
    for q in range(K):  # oriented once chosen: half of ORB's keypoints go to the grid's leftovers
        c = chosen[q]
        i = kept[c]
        k = level[c]
        out_pts[q] = pts[c]
        out_xy[q] = xy[i]
        out_level[q] = k
        w = widths[k]
        out_angle[q] = _orientation(flat, offsets[k] + np.int64(np.rint(xy[i, 1])) * w + np.int64(np.rint(xy[i, 0])),
                                    w, umax)
    return out_pts, out_xy, out_level, out_angle, m


def _centres(xy, octave, offsets, widths):
    """Body of :func:`level_centres`."""
    out = np.empty(xy.shape[0], np.int64)
    for i in range(xy.shape[0]):
        k = octave[i]
        out[i] = offsets[k] + np.int64(np.rint(xy[i, 1])) * widths[k] + np.int64(np.rint(xy[i, 0]))
    return out


def _depths(pts, octave, shift, depth_img, units, scale, lo, hi, uv_raw, depth):
    """Body of :func:`keypoint_depths`: depth_img [H, W] float32 metres or (``units``) uint16 units,
    ``scale`` per metre, 0 = none, turned into metres as ``view.depth_to_metres`` does; [0, 0] for
    none."""
    h, w = depth_img.shape
    for i in range(pts.shape[0]):
        s = shift[octave[i]]
        u = np.float32(np.float64(pts[i, 0]) + s)
        v = np.float32(np.float64(pts[i, 1]) + s)
        uv_raw[i, 0] = u
        uv_raw[i, 1] = v
        d = np.nan
        if h > 0:
            ui = min(max(np.int64(np.rint(u)), 0), w - 1)
            vi = min(max(np.int64(np.rint(v)), 0), h - 1)
            raw = depth_img[vi, ui]
            if units:
                m = np.nan if raw == 0 else np.float64(np.float32(raw) / scale)
            else:
                m = np.float64(raw)
            if np.isfinite(m) and m >= lo and m <= hi:
                d = m
        depth[i] = d


if numba_available():
    import numba

    _jit = numba.njit(cache=True, nogil=True)
    _select_grid = _jit(_select_grid)
    _describe = _jit(_describe)
    _adjust_heap = _jit(_adjust_heap)
    _nth_element = _jit(_nth_element)
    _retain_best = _jit(_retain_best)
    _harris = _jit(_harris)
    _fast_atan2 = _jit(_fast_atan2)
    _orientation = _jit(_orientation)
    _detect_level = _jit(_detect_level)
    _detect_select = _jit(_detect_select)
    _fast_score = _jit(_fast_score)
    _fast_scores = _jit(_fast_scores)
    _centres = _jit(_centres)
    _depths_units = _jit(_depths)  # the camera's 16-bit units; one dispatcher per dtype, one signature each
    _depths = _jit(_depths)


def select_grid(pts: np.ndarray, resp: np.ndarray, n: int, cell: float, width: int, height: int) -> np.ndarray:
    """Compiled ``OrbExtractor._select_indices``: indices [K] of the keypoints (level-0 positions
    pts [N, 2], responses [N]) a grid of ``cell`` px cells keeps, at most ``n``, ascending."""
    if len(pts) <= n:
        return np.arange(len(pts))
    gx, gy = max(1, int(np.ceil(width / cell))), max(1, int(np.ceil(height / cell)))
    return _select_grid(np.ascontiguousarray(pts, np.float32), np.ascontiguousarray(resp, np.float32), int(n),
                        np.float32(cell), gx, gy)


def detect_level(level: np.ndarray, xy: np.ndarray, score: np.ndarray, n: int, edge: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What OpenCV's single-level ORB (``nfeatures`` n, ``edgeThreshold`` edge, patch 31, Harris
    score) keeps of the FAST corners (level positions xy [N, 2], scores [N], in the order FAST
    found them) on ``level`` [H, W] uint8: (indices [K] into xy, Harris responses [K], angles [K]
    in degrees), in ORB's order; the same keypoints ``ORB.detect`` returns without its Python
    keypoint objects, its image copy with a border and its second FAST."""
    h, w = level.shape
    xy = np.ascontiguousarray(xy, np.float32).reshape(-1, 2)
    N = len(xy)
    idx = np.empty(N, np.int64)
    response = np.zeros(N, np.float32)
    angle = np.zeros(N, np.float32)
    count = _detect_level(np.ascontiguousarray(level).ravel(), 0, w, h, xy, np.ascontiguousarray(score, np.float32),
                          0, N, int(n), int(edge), _UMAX, idx, response, angle, True, -1, _FAST_RING)
    kept = idx[:count].copy()
    return kept, response[kept], angle[kept]


def detect_and_select(flat: np.ndarray, shapes: np.ndarray, xy: np.ndarray, score: np.ndarray | None,
                      starts: np.ndarray, counts: np.ndarray, edge: int, scales: np.ndarray, n: int, cell: float,
                      width: int, height: int, threshold: int = -1
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """``detect_level`` on every level of a pyramid and the grid's selection (``select_grid``) in
    one call. flat: the levels one after another (``features._PyramidLayout``), shapes [L, 3] (offset, height,
    width); xy [N, 2] float32 FAST's corners of all levels, level k's at xy[starts[k]:starts[k + 1]]
    (starts [L + 1]), scores [N] (or None: computed where needed, as :func:`fast_scores` does, for
    corners FAST found at ``threshold``); counts [L]: ORB's n of each level; scales [L] float32. Returns
    (level-0 positions [K, 2], level positions [K, 2], levels [K], angles [K]) of the kept keypoints
    in level order (each level in ORB's order) and how many ORB kept before the grid."""
    gx, gy = max(1, int(np.ceil(width / cell))), max(1, int(np.ceil(height / cell)))
    # Contiguous columns: one layout for any number of levels (a column of one row is contiguous,
    # of several strided, and numba would compile each).
    level_offset, level_h, level_w = (np.ascontiguousarray(c, np.int64) for c in np.asarray(shapes).T)
    if score is None:
        if threshold < 0:
            raise ValueError("detect_and_select needs the corners' scores or FAST's threshold")
        score = np.empty(len(xy), np.float32)
    else:
        threshold = -1
    return _detect_select(flat, level_offset, level_w, level_h, np.ascontiguousarray(xy, np.float32),
                          np.ascontiguousarray(score, np.float32), np.ascontiguousarray(starts, np.int64),
                          np.ascontiguousarray(counts, np.int64), int(edge), _UMAX,
                          np.ascontiguousarray(scales, np.float32), int(n), np.float32(cell), gx, gy,
                          int(threshold), _FAST_RING)


def level_centres(xy: np.ndarray, octave: np.ndarray, offsets: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Where each keypoint lies in a pyramid laid out level after level (``OrbExtractor``'s
    layout): offsets[octave] + rint(y) * widths[octave] + rint(x), [K] int64, for level positions
    xy [K, 2] float32 and octaves [K]; offsets, widths [L] int64 per level. One compiled pass where
    numba is, else ``_level_centres_reference``."""
    if not numba_available():
        return _level_centres_reference(xy, octave, offsets, widths)
    return _centres(np.ascontiguousarray(xy, np.float32), np.ascontiguousarray(octave, np.int64),
                    np.ascontiguousarray(offsets, np.int64), np.ascontiguousarray(widths, np.int64))


def _level_centres_reference(xy: np.ndarray, octave: np.ndarray, offsets: np.ndarray, widths: np.ndarray
                             ) -> np.ndarray:
    """numpy twin of :func:`level_centres`."""
    pix = np.rint(np.asarray(xy, np.float32)).astype(np.int64)
    return offsets[octave] + pix[:, 1] * widths[octave] + pix[:, 0]


def keypoint_depths(pts: np.ndarray, octave: np.ndarray, centre_shift: np.ndarray,
                    depth_m: np.ndarray | DepthUnits | None, shape: tuple[int, ...], depth_range: tuple[float, float]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints' detected pixels and depths: (uv_raw [K, 2] float32: level-0 positions pts [K, 2]
    float32 plus centre_shift[octave] [L] float64, summed in float64; depth [K] float64: the depth
    in metres (depth_m [H, W] float32, or the camera's units read where needed) at the nearest
    pixel (rounded half to even, clipped into ``shape`` (H, W)), NaN where not finite, outside
    ``depth_range`` (metres, inclusive) or without depth). One compiled pass where numba is, else
    ``_keypoint_depths_reference``."""
    if depth_m is not None and tuple(depth_m.shape) != tuple(shape[:2]):
        raise ValueError(f"depth {tuple(depth_m.shape)} does not match the image {tuple(shape[:2])}")
    if not numba_available():
        return _keypoint_depths_reference(pts, octave, centre_shift, depth_m, shape, depth_range)
    n = len(pts)
    uv_raw, depth = np.empty((n, 2), np.float32), np.empty(n, np.float64)
    kernel, img, scale = _depths, _NO_DEPTH, np.float32(1.0)
    if isinstance(depth_m, DepthUnits) and depth_m.raw.dtype == np.uint16:  # read at the keypoints
        # Read-only, as the node's views on its messages are: the one signature the warm-up compiles.
        kernel, img, scale = _depths_units, np.ascontiguousarray(depth_m.raw).view(), np.float32(depth_m.scale)
        img.flags.writeable = False
    elif depth_m is not None:  # metres (float units converted whole)
        metres = depth_m.metres() if isinstance(depth_m, DepthUnits) else depth_m
        img = np.ascontiguousarray(metres, np.float32)
        img = img if img.flags.writeable else img.copy()
    kernel(np.ascontiguousarray(pts, np.float32), np.ascontiguousarray(octave, np.int64),
           np.ascontiguousarray(centre_shift, np.float64), img, img.dtype == np.uint16, scale,
           float(depth_range[0]), float(depth_range[1]), uv_raw, depth)
    return uv_raw, depth


_NO_DEPTH = np.zeros((0, 0), np.float32)


def _keypoint_depths_reference(pts: np.ndarray, octave: np.ndarray, centre_shift: np.ndarray,
                               depth_m: np.ndarray | DepthUnits | None, shape: tuple[int, ...],
                               depth_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """numpy twin of :func:`keypoint_depths`."""
    shift = centre_shift[octave]
    uv_raw = (pts.astype(np.float64) + shift[:, None]).astype(np.float32)
    depth = np.full(len(pts), np.nan)
    if depth_m is not None:
        ui = np.clip(np.round(uv_raw[:, 0]).astype(np.int64), 0, shape[1] - 1)
        vi = np.clip(np.round(uv_raw[:, 1]).astype(np.int64), 0, shape[0] - 1)
        metres = depth_m.metres() if isinstance(depth_m, DepthUnits) else depth_m
        d = metres[vi, ui].astype(np.float64)
        ok = np.isfinite(d) & (d >= depth_range[0]) & (d <= depth_range[1])
        depth[ok] = d[ok]
    return uv_raw, depth


def fast_scores(flat: np.ndarray, shapes: np.ndarray, xy: np.ndarray, starts: np.ndarray, threshold: int
                ) -> np.ndarray:
    """The scores [N] float32 OpenCV's FAST gives its corners (``KeyPoint.response``), from the
    corners' positions: xy [N, 2] float32 (level k's at xy[starts[k]:starts[k + 1]]) on the pyramid
    ``flat`` with ``shapes`` [L, 3] (offset, height, width), found at ``threshold``: the check
    (:func:`fast_scores_agree`) that the scores :func:`detect_and_select` computes, on the levels
    where it needs them, are OpenCV's. (Scoring every corner in a pass of its own cost more than
    reading OpenCV's keypoint objects: the levels had left the cache.)"""
    level_offset, _, level_w = (np.ascontiguousarray(c, np.int64) for c in np.asarray(shapes).T)
    return _fast_scores(flat, level_offset, level_w, np.ascontiguousarray(xy, np.float32),
                        np.ascontiguousarray(starts, np.int64), int(threshold), _FAST_RING)


@lru_cache(maxsize=1)
def fast_scores_agree() -> bool:
    """Whether :func:`fast_scores` gives OpenCV's FAST responses, checked once per process on random
    images at two thresholds (a few milliseconds); where not, the extractor reads OpenCV's."""
    if not numba_available():
        return False
    rng = np.random.default_rng(3)
    for threshold in (7, 20):
        img = cv2.GaussianBlur(rng.integers(0, 256, (240, 320), dtype=np.uint8), (3, 3), 0)
        kps = cv2.FastFeatureDetector_create(threshold, True).detect(img)  # type: ignore[attr-defined]
        if len(kps) == 0:
            return False
        xy = np.asarray(cv2.KeyPoint_convert(kps), np.float32).reshape(-1, 2)  # type: ignore[attr-defined]
        ref = np.array([k.response for k in kps], np.float32)
        ours = fast_scores(img.ravel(), np.array([[0, 240, 320]]), xy, np.array([0, len(xy)]), threshold)
        if not np.array_equal(ours, ref):
            _log.info("FAST scores stay OpenCV's: %d of %d differ", int((ours != ref).sum()), len(ref))
            return False
    return True


def smooth(level: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """The level [H, W] uint8 smoothed as ORB smooths it before its intensity tests (into ``out``
    [H, W] uint8 when given)."""
    return cv2.sepFilter2D(level, -1, _SMOOTH_KERNEL, _SMOOTH_KERNEL, dst=out, borderType=cv2.BORDER_REFLECT_101)


_REACH: dict[int, tuple[np.ndarray, int]] = {}


def _reach(tests: np.ndarray) -> int:
    """The farthest test pixel from the keypoint, any rotation, px (per pattern array, computed once:
    the extractor describes eight levels a frame with the same one)."""
    hit = _REACH.get(id(tests))
    if hit is None or hit[0] is not tests:
        hit = _REACH[id(tests)] = (tests, int(np.ceil(np.hypot(tests[0::2], tests[1::2]).max())))
    return hit[1]


def describe(smoothed: np.ndarray, pix: np.ndarray, angle_deg: np.ndarray, tests: np.ndarray) -> np.ndarray:
    """ORB descriptors [K, 32] uint8 of keypoints at pixels ``pix`` [K, 2] int64 (x, y), oriented
    ``angle_deg`` [K] (OpenCV's keypoint angles), on the level ``smooth`` made [H, W] uint8.
    ValueError when a keypoint is too near the border for its rotated tests (ORB keeps its
    keypoints 19 px inside, beyond the farthest test's 18.4 px)."""
    h, w = smoothed.shape
    reach = _reach(tests)
    if len(pix) and (pix.min() < reach or pix[:, 0].max() >= w - reach or pix[:, 1].max() >= h - reach):
        raise ValueError(f"ORB keypoints must lie {reach} px inside the {w}x{h} level for their tests")
    centres = np.ascontiguousarray(pix[:, 1], np.int64) * w + pix[:, 0]
    return describe_at(np.ascontiguousarray(smoothed).ravel(), centres, np.full(len(pix), w, np.int64), angle_deg,
                       tests)


def describe_at(flat: np.ndarray, centres: np.ndarray, steps: np.ndarray, angle_deg: np.ndarray, tests: np.ndarray
                ) -> np.ndarray:
    """``describe`` on smoothed levels laid one after another in flat [sum H * W] uint8: keypoint i
    at flat[centres[i]] [K] of a level with rows of steps[i] [K] pixels, at least 19 px inside
    its level (unchecked: ``describe`` checks)."""
    rad = np.asarray(angle_deg, np.float32) * _DEG_TO_RAD  # float32, as ORB converts it
    # cos and sin rounded once to float32, as ORB's are: numpy's float32 cos can be an ulp off,
    # which moves a rotated test pixel that sits on a half.
    rad64 = rad.astype(np.float64)
    return _describe(flat, np.ascontiguousarray(centres, np.int64), np.ascontiguousarray(steps, np.int64),
                     np.cos(rad64).astype(np.float32), np.sin(rad64).astype(np.float32), tests)


# ---------------------------------------------------------------------------- the test pattern

def _probe_descriptors(rng: np.random.Generator, ref_orb: cv2.ORB, offsets: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's descriptor bits [S, 256] at unrotated keypoints of a random image, and the smoothed
    image's values [S, P] at ``offsets`` [P, 2] around each keypoint."""
    img = rng.integers(0, 256, (320, 320), dtype=np.uint8)
    centres = [(float(x), float(y)) for y in range(64, 257, 32) for x in range(64, 257, 32)]
    kept, desc = ref_orb.compute(img, [cv2.KeyPoint(x, y, 31.0, 0.0) for x, y in centres])
    if desc is None or len(kept) != len(centres):
        raise ValueError("OpenCV's ORB dropped probe keypoints")
    s = smooth(img).astype(np.int16)
    values = np.stack([s[int(k.pt[1]) + offsets[:, 1], int(k.pt[0]) + offsets[:, 0]] for k in kept])
    return np.unpackbits(np.asarray(desc, np.uint8), axis=1, bitorder="little"), values


def _derive_test_pattern(seed: int = 0, rounds: int = 3) -> np.ndarray:
    """The pixel pairs [4, 256] float32 (x1, y1, x2, y2) of OpenCV's ORB tests, read off its output;
    ValueError when they cannot be pinned down."""
    rng = np.random.default_rng(seed)
    ref_orb = cv2.ORB_create(nfeatures=1, nlevels=1, edgeThreshold=31, patchSize=31)  # type: ignore[attr-defined]  # missing from OpenCV's stubs
    r = PATCH_RADIUS
    offsets = np.array([(x, y) for y in range(-r, r + 1) for x in range(-r, r + 1)], np.int64)
    p = len(offsets)
    alive: list[set[int]] | None = None
    for _ in range(rounds):
        bits: list[np.ndarray] = []
        values: list[np.ndarray] = []
        while sum(len(b) for b in bits) < 64:
            b, v = _probe_descriptors(rng, ref_orb, offsets)
            bits.append(b)
            values.append(v)
        bit = np.concatenate(bits)[:64]
        val = np.concatenate(values)[:64]
        # Each candidate pair's 64 comparisons as one word, and each test's 64 observed bits.
        signature = np.zeros((p, p), np.uint64)
        observed = np.zeros(256, np.uint64)
        for s in range(64):
            signature |= (val[s][:, None] < val[s][None, :]).astype(np.uint64) << np.uint64(s)
            observed |= bit[s].astype(np.uint64) << np.uint64(s)
        flat = signature.ravel()
        order = np.argsort(flat, kind="stable")
        ranked = flat[order]
        lo = np.searchsorted(ranked, observed, "left")
        hi = np.searchsorted(ranked, observed, "right")
        found = [set(order[a:b].tolist()) for a, b in zip(lo, hi)]
        alive = found if alive is None else [x & y for x, y in zip(alive, found)]
    assert alive is not None
    if any(len(a) != 1 for a in alive):
        raise ValueError(f"{sum(len(a) != 1 for a in alive)} of ORB's 256 tests not pinned down")
    pairs = np.array([next(iter(a)) for a in alive])
    first, second = offsets[pairs // p], offsets[pairs % p]
    return np.ascontiguousarray(np.stack([first[:, 0], first[:, 1], second[:, 0], second[:, 1]]), np.float32)


def _check_test_pattern(tests: np.ndarray, seed: int = 1, n: int = 2000) -> int:
    """Descriptors (of ``n`` at random positions and angles on a random image) where ``describe``
    with these tests and OpenCV's ORB disagree."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (400, 400), dtype=np.uint8), (3, 3), 0)
    xy = rng.integers(48, 352, (n, 2))
    angles = rng.uniform(0.0, 360.0, n).astype(np.float32)
    ref_orb = cv2.ORB_create(nfeatures=1, nlevels=1, edgeThreshold=31, patchSize=31)  # type: ignore[attr-defined]  # missing from OpenCV's stubs
    probes = [cv2.KeyPoint(float(x), float(y), 31.0, float(a)) for (x, y), a in zip(xy, angles)]
    kept, ref = ref_orb.compute(img, probes)
    if ref is None or len(kept) != n:
        return n
    pix = np.rint([k.pt for k in kept]).astype(np.int64)
    ours = describe(smooth(img), pix, np.array([k.angle for k in kept], np.float32), tests)
    return int((ours != ref).any(axis=1).sum())


@lru_cache(maxsize=1)
def intensity_tests() -> np.ndarray | None:
    """OpenCV's ORB test pairs [4, 256] float32, derived and checked once per process (~0.5 s), or
    None where they could not be (the extractor then keeps OpenCV's ORB)."""
    try:
        tests = _derive_test_pattern()
        wrong = _check_test_pattern(tests)
    except (ValueError, cv2.error) as err:
        _log.info("ORB descriptors stay OpenCV's: %s", err)
        return None
    if wrong:
        _log.info("ORB descriptors stay OpenCV's: the derived tests disagree on %d of 2000 descriptors", wrong)
        return None
    return tests


def warm_up() -> None:
    """Read off the tests (which compiles, or loads from the disk cache, the descriptor kernel) and
    compile the grid selection and the detection after FAST, so that the first tracked frame pays
    for none of them."""
    if compiled_orb_available():
        fast_scores_agree()
        select_grid(np.zeros((3, 2), np.float32), np.ones(3, np.float32), 1, 16.0, 96, 96)
        detect_level(np.zeros((64, 64), np.uint8), np.full((1, 2), 32.0, np.float32), np.ones(1, np.float32), 1, 19)
        detect_and_select(np.zeros(64 * 64, np.uint8), np.array([[0, 64, 64]]), np.full((1, 2), 32.0, np.float32),
                          np.ones(1, np.float32), np.array([0, 1]), np.ones(1, np.int64), 19,
                          np.ones(1, np.float32), 1, 16.0, 64, 64)
    if numba_available():
        one = np.zeros((1, 2), np.float32)
        level_centres(one, np.zeros(1, np.int64), np.zeros(1, np.int64), np.ones(1, np.int64))
        units = np.ones((2, 2), np.uint16)
        units.flags.writeable = False  # as the tracker node's view on a message
        for depth in (None, np.ones((2, 2), np.float32), DepthUnits(units, 1000.0)):
            keypoint_depths(one, np.zeros(1, np.int64), np.zeros(1), depth, (2, 2), (0.1, 6.0))


def compiled_orb_available() -> bool:
    """Whether :func:`describe`, :func:`select_grid` and :func:`detect_level` can stand in for
    OpenCV's ``compute``, the extractor's numpy selection and OpenCV's ``detect`` here."""
    return numba_available() and intensity_tests() is not None


__all__ = ["compiled_orb_available", "describe", "describe_at", "detect_and_select", "detect_level", "fast_scores",
           "fast_scores_agree", "intensity_tests", "select_grid", "smooth", "warm_up"]

"""ORB's keypoint detection after FAST, and the extractor's grid selection, in numba kernels.

``detect_level`` is what OpenCV's single-level ORB does after its FAST (the best FAST scores, their
Harris scores, the best of those, their orientations), on arrays instead of Python keypoint objects,
with the same results in the same order; its twin is ``ORB.detect`` itself
(``OrbExtractor._extract_opencv`` calls it). ``detect_and_select`` runs it on every pyramid level and
the grid's choice (``select_grid``, the compiled twin of the extractor's numpy selection) in one call;
``fast_scores`` gives FAST's own scores where ``detect_and_select`` needs them. The descriptors and
the test pattern are ``orb``'s.
"""
from __future__ import annotations

import logging
from functools import lru_cache

import cv2
import numpy as np

from memgs_ros.core.runtime.cpu import numba_available

_log = logging.getLogger(__name__)

PATCH_RADIUS = 15  # half of ORB's 31 px patch: the test pairs lie within it


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


if numba_available():
    import numba

    _jit = numba.njit(cache=True, nogil=True)
    _select_grid = _jit(_select_grid)
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


__all__ = ["PATCH_RADIUS", "detect_and_select", "detect_level", "fast_scores", "fast_scores_agree", "select_grid"]

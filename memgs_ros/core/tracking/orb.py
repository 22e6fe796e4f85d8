"""ORB keypoints and descriptors from numba kernels, equal to OpenCV's ORB on the same pyramid level.

What OpenCV's single-level ORB does on a pyramid level, and so what this module reproduces:
FAST corners (3x3 non-maximum suppression), those within ``edge`` px of the border dropped, the
strongest 2n by FAST score kept (ties at the cut kept too), Harris responses on those (7x7 block
of Sobel gradients, k = 0.04), the strongest n by response; the orientation of each keypoint is
the direction of its intensity centroid over a 31 px disc; its descriptor is 256 intensity tests
between pairs of pixels of the level smoothed by a 7x7 Gaussian (sigma 2), the pairs rotated by
the orientation.

FAST stays OpenCV's (its vectorised scan is ten times a scalar one). The rest runs in kernels on
arrays of keypoints, and orientation and descriptors only for the keypoints the caller keeps:
OpenCV's ORB orients every keypoint it detects, copies every level with a border twice (to
detect, then to describe) and hands every keypoint through Python objects.

The 256 test pairs are not a table from anywhere: :func:`intensity_tests` reads them off the
installed OpenCV by describing random images (each test's pair is the one pair of pixels whose
comparisons agree with that bit in every image) and checks them against OpenCV's descriptors at
random orientations before they are used. Where numba is missing or the check fails,
:func:`compiled_orb_available` is False and the extractor keeps OpenCV's ORB.
"""
from __future__ import annotations

import logging
from functools import lru_cache

import cv2
import numpy as np

from memgs_ros.core.runtime.cpu import numba_available

_log = logging.getLogger(__name__)

HARRIS_K = np.float32(0.04)
PATCH_RADIUS = 15  # half of ORB's 31 px patch: the orientation disc and the test pairs lie within it
# Adding and subtracting 1.5 * 2^23 rounds a float32 to the nearest integer, halves to even (as
# OpenCV's rounding does), for |x| < 2^22.
_ROUND_MAGIC = np.float32(12582912.0)
_DEG_TO_RAD = np.float32(np.pi / 180.0)
_SMOOTH_KERNEL = cv2.getGaussianKernel(7, 2.0, cv2.CV_64F)  # ORB's descriptor smoothing, 7x7, sigma 2


def _harris(img, xs, ys, k):
    """Harris responses [N] float32 at integer pixels (xs [N], ys [N]) of a uint8 image [H, W]:
    det - k trace^2 of the 7x7 sum of Sobel gradient products, scaled as OpenCV's ORB scales it."""
    n = xs.shape[0]
    out = np.empty(n, np.float32)
    scale = np.float32(1.0) / np.float32(4 * 7 * 255.0)
    scale4 = scale * scale * scale * scale
    for i in range(n):
        x0 = xs[i]
        y0 = ys[i]
        a = 0
        b = 0
        c = 0
        for y in range(y0 - 3, y0 + 4):
            up = img[y - 1]
            mid = img[y]
            dn = img[y + 1]
            for x in range(x0 - 3, x0 + 4):
                ix = ((np.int32(mid[x + 1]) - np.int32(mid[x - 1])) * 2 + (np.int32(up[x + 1]) - np.int32(up[x - 1]))
                      + (np.int32(dn[x + 1]) - np.int32(dn[x - 1])))
                iy = ((np.int32(dn[x]) - np.int32(up[x])) * 2 + (np.int32(dn[x - 1]) - np.int32(up[x - 1]))
                      + (np.int32(dn[x + 1]) - np.int32(up[x + 1])))
                a += ix * ix
                b += iy * iy
                c += ix * iy
        fa = np.float32(a)
        fb = np.float32(b)
        fc = np.float32(c)
        out[i] = (fa * fb - fc * fc - k * (fa + fb) * (fa + fb)) * scale4
    return out


# FAST's 16 pixels on a radius-3 circle, in order around it (dx, dy).
_CIRCLE = np.array([(0, -3), (1, -3), (2, -2), (3, -1), (3, 0), (3, 1), (2, 2), (1, 3),
                    (0, 3), (-1, 3), (-2, 2), (-3, 1), (-3, 0), (-3, -1), (-2, -2), (-1, -3)], np.int64)


def _fast_scores(img, xy, circle):
    """FAST-9 scores [N] float32 of corners xy [N, 2] float32 of ``img``: the largest threshold at
    which 9 contiguous circle pixels are all brighter, or all darker, than the centre, less one
    (OpenCV's score; its keypoint objects carry it, but reading it there costs more)."""
    n = xy.shape[0]
    out = np.empty(n, np.float32)
    d = np.empty(16, np.int32)
    for i in range(n):
        x = np.int64(xy[i, 0])
        y = np.int64(xy[i, 1])
        c = np.int32(img[y, x])
        for k in range(16):
            d[k] = np.int32(img[y + circle[k, 1], x + circle[k, 0]]) - c
        best = 0
        for start in range(16):
            lo = d[start]
            hi = d[start]
            for j in range(1, 9):
                v = d[(start + j) & 15]
                lo = min(lo, v)
                hi = max(hi, v)
            best = max(best, lo, -hi)
        out[i] = best - 1
    return out


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


def _nth_largest_cut(score, n):
    """The n-th largest of score [N] (n < N): what keeps the best n, ties at the cut included."""
    return np.partition(score, score.shape[0] - n)[score.shape[0] - n]


def _detect(img, xy, n, edge, k):
    """Keypoints of ``img`` [H, W] uint8 among FAST corners xy [N, 2] float32 (row-major order):
    those at least ``edge`` px inside, the best 2n by FAST score (ties kept), then the best n (ties
    kept) by Harris response. Returns (pixels [K, 2] int64, responses [K] float32)."""
    h, w = img.shape
    m = xy.shape[0]
    keep = np.empty(m, np.int64)
    count = 0
    for i in range(m):
        if edge <= xy[i, 0] < w - edge and edge <= xy[i, 1] < h - edge:
            keep[count] = i
            count += 1
    keep = keep[:count]
    if 0 < 2 * n < count:
        s = _fast_scores(img, xy[keep], _CIRCLE)
        cut = _nth_largest_cut(s, 2 * n)
        keep = keep[s >= cut]
    xs = np.empty(keep.shape[0], np.int64)
    ys = np.empty(keep.shape[0], np.int64)
    for i in range(keep.shape[0]):
        xs[i] = np.int64(xy[keep[i], 0])
        ys[i] = np.int64(xy[keep[i], 1])
    response = _harris(img, xs, ys, k)
    if 0 < n < response.shape[0]:
        best = response >= _nth_largest_cut(response, n)
        xs, ys, response = xs[best], ys[best], response[best]
    pix = np.empty((xs.shape[0], 2), np.int64)
    pix[:, 0] = xs
    pix[:, 1] = ys
    return pix, response


def _moments(img, xs, ys, half_width):
    """First intensity moments (m01, m10) [N] float32 over the disc around each pixel: row v of
    the disc spans |u| <= half_width[|v|]. Rows v and -v are summed together."""
    n = xs.shape[0]
    m01 = np.empty(n, np.float32)
    m10 = np.empty(n, np.float32)
    for i in range(n):
        x0 = xs[i]
        y0 = ys[i]
        row = img[y0]
        a = 0
        for u in range(-half_width[0], half_width[0] + 1):
            a += u * np.int32(row[x0 + u])
        b = 0
        for v in range(1, half_width.shape[0]):
            above = img[y0 - v]
            below = img[y0 + v]
            w = half_width[v]
            s = 0
            for u in range(-w, w + 1):
                p = np.int32(below[x0 + u])
                q = np.int32(above[x0 + u])
                s += p - q
                a += u * (p + q)
            b += v * s
        m10[i] = a
        m01[i] = b
    return m01, m10


def _describe(smoothed, xs, ys, cos_a, sin_a, tests):
    """Descriptors [N, 32] uint8: bit j of keypoint i is 1 where the smoothed image [H, W] is darker
    at the first pixel of test j than at the second, the pair tests [4, 256] float32 (x1, y1, x2,
    y2) rotated by the keypoint's angle (cos_a, sin_a [N] float32) and rounded to pixels."""
    n = xs.shape[0]
    out = np.empty((n, 32), np.uint8)
    step = smoothed.shape[1]
    flat = smoothed.ravel()
    x1, y1, x2, y2 = tests[0], tests[1], tests[2], tests[3]
    o1 = np.empty(256, np.int32)
    o2 = np.empty(256, np.int32)
    magic = _ROUND_MAGIC
    for i in range(n):
        a = cos_a[i]
        b = sin_a[i]
        for j in range(256):  # rotated offsets first: this loop vectorises
            r1 = (x1[j] * b + y1[j] * a + magic) - magic
            c1 = (x1[j] * a - y1[j] * b + magic) - magic
            r2 = (x2[j] * b + y2[j] * a + magic) - magic
            c2 = (x2[j] * a - y2[j] * b + magic) - magic
            o1[j] = np.int32(r1) * step + np.int32(c1)
            o2[j] = np.int32(r2) * step + np.int32(c2)
        centre = ys[i] * step + xs[i]
        for byte in range(32):
            value = 0
            for t in range(8):
                j = byte * 8 + t
                if flat[centre + o1[j]] < flat[centre + o2[j]]:
                    value |= 1 << t
            out[i, byte] = value
    return out


if numba_available():
    import numba

    _jit = numba.njit(cache=True, nogil=True)
    _harris = _jit(_harris)
    _fast_scores = _jit(_fast_scores)
    _select_grid = _jit(_select_grid)
    _nth_largest_cut = _jit(_nth_largest_cut)
    _detect = _jit(_detect)
    _moments = _jit(_moments)
    _describe = _jit(_describe)


def disc_half_widths(radius: int = PATCH_RADIUS) -> np.ndarray:
    """Half widths [radius + 1] int64 of a digital disc symmetric under swapping x and y: rows up
    to 45 degrees are round(sqrt(r^2 - v^2)); the steeper rows are the transposes of those columns."""
    corner = int(np.floor(radius * np.sqrt(2.0) / 2.0 + 1.0))
    w = [int(np.round(np.sqrt(radius * radius - v * v))) for v in range(corner + 1)]
    out = np.array(w + [0] * (radius - corner), np.int64)
    for v in range(int(np.ceil(radius * np.sqrt(2.0) / 2.0)), radius + 1):
        out[v] = max(u for u in range(corner + 1) if w[u] >= v)
    return out


_HALF_WIDTHS = disc_half_widths()


def fast_corners(fast: cv2.FastFeatureDetector, level: np.ndarray, edge: int) -> np.ndarray:
    """OpenCV's FAST corners [N, 2] float32 (x, y; row-major) of ``level`` [H, W] uint8 that can lie
    ``edge`` px inside it, or suppress one that does."""
    # FAST only there: ``edge`` - 1 px in, plus the 3 px its circle needs (11 % of level 0's pixels
    # and 35 % of the top level's go unscanned).
    m = max(edge - 4, 0)
    h, w = level.shape
    kps = fast.detect(level[m:h - m, m:w - m]) if h > 2 * m and w > 2 * m else ()
    if not kps:
        return np.zeros((0, 2), np.float32)
    return np.asarray(cv2.KeyPoint_convert(kps), np.float32).reshape(-1, 2) + np.float32(m)  # type: ignore[attr-defined]  # missing from OpenCV's stubs


def detect_level(fast: cv2.FastFeatureDetector, level: np.ndarray, n: int, edge: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The keypoints OpenCV's single-level ORB (``n`` features, FAST detector ``fast``, border
    ``edge`` px, Harris score) finds in ``level`` [H, W] uint8: pixels [K, 2] int64 (x, y) in FAST's
    row-major order and their Harris responses [K] float32."""
    xy = fast_corners(fast, level, edge)
    if len(xy) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.float32)
    return _detect(level, xy, n, edge, HARRIS_K)


def select_grid(pts: np.ndarray, resp: np.ndarray, n: int, cell: float, width: int, height: int) -> np.ndarray:
    """Compiled ``OrbExtractor._select_indices``: indices [K] of the keypoints (level-0 positions
    pts [N, 2], responses [N]) a grid of ``cell`` px cells keeps, at most ``n``, ascending."""
    if len(pts) <= n:
        return np.arange(len(pts))
    gx, gy = max(1, int(np.ceil(width / cell))), max(1, int(np.ceil(height / cell)))
    return _select_grid(np.ascontiguousarray(pts, np.float32), np.ascontiguousarray(resp, np.float32), int(n),
                        np.float32(cell), gx, gy)


def smooth(level: np.ndarray) -> np.ndarray:
    """The level [H, W] uint8 smoothed as ORB smooths it before its intensity tests."""
    return cv2.sepFilter2D(level, -1, _SMOOTH_KERNEL, _SMOOTH_KERNEL, borderType=cv2.BORDER_REFLECT_101)


def describe_level(level: np.ndarray, pix: np.ndarray, tests: np.ndarray) -> np.ndarray:
    """ORB descriptors [K, 32] uint8 of keypoints at pixels ``pix`` [K, 2] int64 of ``level`` (at
    least ``PATCH_RADIUS`` + 6 px inside it), oriented by their intensity centroids."""
    xs, ys = np.ascontiguousarray(pix[:, 0]), np.ascontiguousarray(pix[:, 1])
    m01, m10 = _moments(level, xs, ys, _HALF_WIDTHS)
    angle = cv2.phase(m10, m01, angleInDegrees=True).reshape(-1) * _DEG_TO_RAD  # OpenCV's fast atan2, as ORB
    return _describe(smooth(level), xs, ys, np.cos(angle), np.sin(angle), tests)


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


def _check_test_pattern(tests: np.ndarray, seed: int = 1) -> int:
    """Descriptors (of 400 at random positions and angles on a random image) where these tests and
    OpenCV's ORB disagree."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (400, 400), dtype=np.uint8), (3, 3), 0)
    xy = rng.integers(48, 352, (400, 2))
    angles = rng.uniform(0.0, 360.0, 400).astype(np.float32)
    ref_orb = cv2.ORB_create(nfeatures=1, nlevels=1, edgeThreshold=31, patchSize=31)  # type: ignore[attr-defined]  # missing from OpenCV's stubs
    probes = [cv2.KeyPoint(float(x), float(y), 31.0, float(a)) for (x, y), a in zip(xy, angles)]
    kept, ref = ref_orb.compute(img, probes)
    if ref is None or len(kept) != len(xy):
        return len(xy)
    rad = np.array([k.angle for k in kept], np.float32) * _DEG_TO_RAD
    pix = np.array([k.pt for k in kept]).round().astype(np.int64)
    ours = _describe(smooth(img), pix[:, 0].copy(), pix[:, 1].copy(), np.cos(rad), np.sin(rad), tests)
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
        _log.info("ORB descriptors stay OpenCV's: the derived tests disagree on %d of 400 descriptors", wrong)
        return None
    return tests


def warm_up() -> None:
    """Compile (or load from the disk cache) the kernels on a small image, and read off the tests,
    so that the first tracked frame pays for neither."""
    if not compiled_orb_available():
        return
    tests = intensity_tests()
    assert tests is not None
    img = cv2.GaussianBlur(np.random.default_rng(0).integers(0, 256, (96, 96), dtype=np.uint8), (3, 3), 0)
    fast = cv2.FastFeatureDetector_create(10, True)  # type: ignore[attr-defined]  # missing from OpenCV's stubs
    pix, _ = detect_level(fast, img, 4, 24)
    if len(pix):
        describe_level(img, pix, tests)
    select_grid(np.zeros((3, 2), np.float32), np.ones(3, np.float32), 1, 16.0, 96, 96)


def compiled_orb_available() -> bool:
    """Whether :func:`detect_level` and :func:`describe_level` can stand in for OpenCV's ORB here."""
    return numba_available() and intensity_tests() is not None


__all__ = ["compiled_orb_available", "describe_level", "detect_level", "disc_half_widths", "fast_corners",
           "intensity_tests", "select_grid", "smooth", "warm_up"]

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

``select_grid`` is the compiled twin of the extractor's grid selection.
"""
from __future__ import annotations

import logging
from functools import lru_cache

import cv2
import numpy as np

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
    _select_grid = _jit(_select_grid)
    _describe = _jit(_describe)


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
    rad = np.asarray(angle_deg, np.float32) * _DEG_TO_RAD  # float32, as ORB converts it
    # cos and sin rounded once to float32, as ORB's are: numpy's float32 cos can be an ulp off,
    # which moves a rotated test pixel that sits on a half.
    rad64 = rad.astype(np.float64)
    return _describe(smoothed, np.ascontiguousarray(pix[:, 0], np.int64), np.ascontiguousarray(pix[:, 1], np.int64),
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
    compile the grid selection, so that the first tracked frame pays for neither."""
    if compiled_orb_available():
        select_grid(np.zeros((3, 2), np.float32), np.ones(3, np.float32), 1, 16.0, 96, 96)


def compiled_orb_available() -> bool:
    """Whether :func:`describe` and :func:`select_grid` can stand in for OpenCV's ``compute`` and the
    extractor's numpy selection here."""
    return numba_available() and intensity_tests() is not None


__all__ = ["compiled_orb_available", "describe", "intensity_tests", "select_grid", "smooth", "warm_up"]

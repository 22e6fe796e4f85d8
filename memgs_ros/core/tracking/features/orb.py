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

The detection after FAST and the grid selection are ``orb_detect``'s; ``level_centres`` and
``keypoint_depths`` (where each keypoint lies in the pyramid, and its depth) run beside them.
"""
from __future__ import annotations

import logging
from functools import lru_cache

import cv2
import numpy as np

from memgs_ros.core.geometry.view import DepthUnits
from memgs_ros.core.runtime.cpu import numba_available
from memgs_ros.core.tracking.features.orb_detect import (
    PATCH_RADIUS,
    detect_and_select,
    detect_level,
    fast_scores_agree,
    select_grid,
)

_log = logging.getLogger(__name__)

# Adding and subtracting 1.5 * 2^23 rounds a float32 to the nearest integer, halves to even (as
# OpenCV's rounding does), for |x| < 2^22.
_ROUND_MAGIC = np.float32(12582912.0)
_DEG_TO_RAD = np.float32(np.pi / 180.0)
_SMOOTH_KERNEL = cv2.getGaussianKernel(7, 2.0, cv2.CV_64F)  # ORB's descriptor smoothing, 7x7, sigma 2


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
    _describe = _jit(_describe)
    _centres = _jit(_centres)
    _depths_units = _jit(_depths)  # the camera's 16-bit units; one dispatcher per dtype, one signature each
    _depths = _jit(_depths)


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


__all__ = ["compiled_orb_available", "describe", "describe_at", "intensity_tests", "keypoint_depths", "level_centres",
           "smooth", "warm_up"]

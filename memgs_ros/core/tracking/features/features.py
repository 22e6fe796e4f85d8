"""ORB features spread over the image, undistorted keypoints, and descriptor matching.

Images stay distorted (ORB sees what the sensor saw); only keypoint coordinates are
undistorted, so every downstream step uses a plain pinhole model with ``camera.K``.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from itertools import accumulate, chain
from operator import attrgetter

import cv2
import numpy as np
from scipy.spatial import cKDTree

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.view import DepthUnits
from memgs_ros.core.tracking.config import TrackerConfig
from memgs_ros.core.tracking.features import orb, orb_detect
from memgs_ros.core.tracking.kernel_calls import match_by_projection_kernel, numba_available, unroll_kernel

DESCRIPTOR_BYTES = 32
EDGE_PX = 19  # keypoints keep this far from a level's border (ORB's edgeThreshold)
_RESPONSE, _ANGLE = attrgetter("response"), attrgetter("angle")
# Bits set per byte value: Hamming distance of packed descriptors by table lookup.
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


@dataclass(frozen=True, eq=False)
class FrameFeatures:
    """ORB features of one image.

    uv_raw: [M, 2] float32 detected (distorted) pixel coordinates.
    uv: [M, 2] float64 undistorted pixel coordinates.
    octave: [M] int pyramid level.
    desc: [M, 32] uint8 ORB descriptors.
    depth_m: [M] float64 depth at the keypoint, NaN where invalid or absent.
    """

    uv_raw: np.ndarray
    uv: np.ndarray
    octave: np.ndarray
    desc: np.ndarray
    depth_m: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)


class OrbExtractor:
    """ORB keypoints distributed over a grid of cells (ORB-SLAM's idea, cheaper).

    One detection at ``fast_threshold`` over-asks for keypoints; each cell keeps its strongest
    share and the remaining budget goes to the strongest leftovers. Cells that found nothing
    are retried at ``fast_min_threshold`` only when the image is short of keypoints.

    ``extract`` builds the image pyramid once, in one buffer, and runs OpenCV's FAST on each level;
    what OpenCV's single-level ORB then does (keep the best FAST scores, score them by Harris, keep
    the best, orient them) and the grid's selection run in one numba call
    (``orb_detect.detect_and_select``), without ORB's copy of each level, its Python keypoint objects and
    their conversions. The chosen keypoints are described in one more call (``orb.describe_at``) on
    the levels smoothed once into a second buffer, as exact as OpenCV's ``compute``, which copies
    and smooths each level again. Where numba is missing, ``_extract_opencv`` runs the single-level
    ORBs and ``compute`` instead. OpenCV's multi-level ORB builds its pyramid a second time to
    describe (on fr1/rpy the extraction took 1.67 times OpenCV's own of 1000 features that way,
    1.35-1.38 with one pyramid and ``compute``, 1.23-1.27 with the descriptor kernel; measured
    alike in one session, 1.33 before the detection on arrays and 1.21-1.25 after).
    ``_extract_reference`` is that multi-level path; all give the same keypoints (positions within
    1e-3 px), octaves and descriptors, the per-level paths in the same order.
    """

    def __init__(self, cfg: TrackerConfig) -> None:
        self.cfg = cfg
        self._orb = self._make_orb(2 * cfg.n_features, cfg.n_levels, cfg.fast_threshold)
        self._orb_low = self._make_orb(2 * cfg.n_features, cfg.n_levels, cfg.fast_min_threshold)
        counts = level_shares(2 * cfg.n_features, cfg.scale_factor, cfg.n_levels)
        # Level k's scale, as OpenCV's ORB computes it (a float32 power).
        self._scales = [float(np.float32(cfg.scale_factor ** k)) for k in range(cfg.n_levels)]
        self._level_counts = [max(c, 1) for c in counts]
        self._level_counts_arr = np.array(self._level_counts, np.int64)
        self._scales_arr = np.array(self._scales, np.float32)
        self._centre_shift = 0.5 * (cfg.scale_factor ** np.arange(cfg.n_levels) - 1.0)  # per octave, see _finish
        self._level_orb = [self._make_orb(c, 1, cfg.fast_threshold) for c in self._level_counts]
        self._level_orb_low = [self._make_orb(c, 1, cfg.fast_min_threshold) for c in self._level_counts]
        # OpenCV's FAST as ORB runs it (9 of 16, non-maximum suppression), for ``orb_detect.detect_level``.
        self._fast = cv2.FastFeatureDetector_create(cfg.fast_threshold, True)  # type: ignore[attr-defined]  # missing from OpenCV's stubs
        self._fast_low = cv2.FastFeatureDetector_create(cfg.fast_min_threshold, True)  # type: ignore[attr-defined]
        # ORB's intensity tests for ``orb.describe``, where numba and the tests are at hand (else
        # OpenCV's ``compute`` describes).
        self._tests = orb.intensity_tests() if orb.compiled_orb_available() else None
        self._scores_in_kernel = self._tests is not None and orb_detect.fast_scores_agree()
        self._layout: _PyramidLayout | None = None  # the pyramid's buffers, reused frame to frame

    def _make_orb(self, n: int, levels: int, fast_threshold: int) -> cv2.ORB:
        return cv2.ORB_create(nfeatures=n, scaleFactor=self.cfg.scale_factor, nlevels=levels,  # type: ignore[attr-defined]  # missing from OpenCV's stubs
                              edgeThreshold=EDGE_PX, patchSize=31, fastThreshold=fast_threshold)

    def _select_indices(self, pts: np.ndarray, resp: np.ndarray, width: int, height: int) -> np.ndarray:
        """Indices of the keypoints (level-0 positions pts [N, 2], responses resp [N]) the grid keeps,
        ascending."""
        n = self.cfg.n_features
        if len(pts) <= n:
            return np.arange(len(pts))
        cell = self.cfg.grid_cell_px
        gx = max(1, int(np.ceil(width / cell)))
        gy = max(1, int(np.ceil(height / cell)))
        cid = (np.minimum(pts[:, 1] // cell, gy - 1) * gx + np.minimum(pts[:, 0] // cell, gx - 1)).astype(np.int64)
        # Rank within each cell by response (strongest first, then by index): two stable
        # argsorts give lexsort's order at half its cost.
        order = np.argsort(-resp, kind="stable")
        order = order[np.argsort(cid[order], kind="stable")]
        cid_sorted = cid[order]
        start = np.searchsorted(cid_sorted, cid_sorted, side="left")
        rank = np.empty(len(pts), dtype=np.int64)
        rank[order] = np.arange(len(pts)) - start
        per_cell = max(1, n // (gx * gy))
        chosen = rank < per_cell
        if chosen.sum() < n:
            rest = np.flatnonzero(~chosen)
            rest = rest[np.argsort(-resp[rest], kind="stable")][: n - int(chosen.sum())]
            chosen[rest] = True
        elif chosen.sum() > n:
            idx = np.flatnonzero(chosen)
            drop = idx[np.argsort(resp[idx], kind="stable")][: int(chosen.sum()) - n]
            chosen[drop] = False
        return np.flatnonzero(chosen)

    def _select(self, kps: list, width: int, height: int) -> list:
        """The grid's keypoints among OpenCV keypoints (level-0 positions)."""
        if len(kps) <= self.cfg.n_features:
            return list(kps)
        pts = cv2.KeyPoint_convert(kps)  # type: ignore[attr-defined]  # missing from OpenCV's stubs
        resp = np.array([k.response for k in kps], dtype=np.float32)
        return [kps[i] for i in self._select_indices(pts, resp, width, height).tolist()]

    def _pyramid(self, gray: np.ndarray) -> list[np.ndarray]:
        """The level images, each resized from the one before, at OpenCV ORB's sizes and interpolation
        (arrays of their own: the caller may keep them)."""
        layout = _PyramidLayout(gray.shape, self._scales)
        layout.levels[0][...] = gray
        layout.resize()
        return layout.levels

    def _reused_layout(self, shape: tuple[int, ...]) -> _PyramidLayout:
        """The extractor's pyramid buffers for an image of ``shape`` (H, W, ...), kept from frame to
        frame (their contents valid until the next extraction); its first level is the caller's to
        write."""
        if self._layout is None or self._layout.image_shape != shape[:2]:
            self._layout = _PyramidLayout(shape, self._scales)
        return self._layout

    def extract(self, gray: np.ndarray, camera: PinholeCamera, depth_m: np.ndarray | None,
                mask: np.ndarray | None = None) -> FrameFeatures:
        """Keypoints of ``gray`` [H, W] uint8; depth [H, W] float32 (registered to gray) or None.
        ``mask`` [H, W] uint8 (non-zero: where keypoints may lie) takes the reference path."""
        if mask is not None:
            return self._extract_reference(gray, camera, depth_m, mask)
        if self._tests is None:
            return self._extract_opencv(gray, camera, depth_m)
        layout = self._reused_layout(gray.shape)
        layout.levels[0][...] = gray
        return self._extract_levels(layout, camera, depth_m)

    def extract_rgb(self, rgb: np.ndarray, camera: PinholeCamera, depth_m: np.ndarray | DepthUnits | None
                    ) -> FrameFeatures:
        """``extract`` of the grey of ``rgb`` [H, W, 3] uint8 (RGB order), written straight into the
        pyramid's first level: the tracker's way, one grey image less to write and read a frame.
        ``depth_m`` may be the camera's raw image (``DepthUnits``): read at the keypoints alone."""
        if self._tests is None:
            return self._extract_opencv(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), camera, depth_m)
        layout = self._reused_layout(rgb.shape)
        cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY, dst=layout.levels[0])
        return self._extract_levels(layout, camera, depth_m)

    def _extract_levels(self, pyr: _PyramidLayout, camera: PinholeCamera, depth_m: np.ndarray | DepthUnits | None
                        ) -> FrameFeatures:
        """The compiled extraction on a pyramid whose first level is written: the other levels,
        detection (retried at ``fast_min_threshold`` when short of keypoints), smoothing, descriptors."""
        pyr.resize()
        found = self._detect(pyr, self._fast, self.cfg.fast_threshold, skip_short=True)
        if found is None or found[4] < self.cfg.n_features:
            found = self._detect(pyr, self._fast_low, self.cfg.fast_min_threshold)
        assert found is not None  # the retry is never skipped
        pts, xy, octave, angle, _ = found
        shape = pyr.image_shape
        if len(pts) == 0:
            return self._finish(shape, camera, depth_m, np.zeros((0, 2), np.float32), np.zeros(0, np.int64), None)
        for level, out in zip(pyr.levels, pyr.smoothed_levels):
            orb.smooth(level, out)
        centres = orb.level_centres(xy, octave, pyr.offsets, pyr.widths)
        assert self._tests is not None  # checked by the callers
        desc = orb.describe_at(pyr.smoothed, centres, pyr.widths[octave], angle, self._tests)
        return self._finish(shape, camera, depth_m, pts, octave, desc)

    def _detect(self, pyr: _PyramidLayout, fast: cv2.FastFeatureDetector, threshold: int, skip_short: bool = False
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int] | None:
        """OpenCV's FAST (at ``threshold``) on each level, then what each level's single-level ORB
        keeps of it and the grid's choice among those (``orb_detect.detect_and_select``): (level-0
        positions [K, 2] float32, level positions [K, 2], octaves [K], angles [K], how many ORB kept
        before the grid). ``skip_short``: None, without the selection, when FAST found fewer corners
        than ``n_features``: ORB keeps no more than FAST found, so the retry at the lower threshold
        is certain (14 of 200 fr1/rpy frames; 0.85 ms each)."""
        corners = [_fast_in_band(fast, level) for level in pyr.levels]
        starts = np.fromiter(accumulate(map(len, corners), initial=0), np.int64, len(corners) + 1)
        if skip_short and starts[-1] < self.cfg.n_features:
            return None
        xy = np.concatenate([_positions(c) for c in corners])
        xy += np.float32(_BAND_MARGIN)
        score = None  # computed in the kernel, for the levels where ORB ranks by it
        if not self._scores_in_kernel:  # read off OpenCV's keypoint objects instead (~3000 of them)
            score = np.fromiter(chain.from_iterable(map(_RESPONSE, c) for c in corners), np.float32, int(starts[-1]))
        h, w = pyr.image_shape
        return orb_detect.detect_and_select(pyr.flat, pyr.shapes, xy, score, starts, self._level_counts_arr, EDGE_PX,
                                     self._scales_arr, self.cfg.n_features, self.cfg.grid_cell_px, w, h, threshold)

    def _extract_opencv(self, gray: np.ndarray, camera: PinholeCamera, depth_m: np.ndarray | DepthUnits | None
                        ) -> FrameFeatures:
        """``extract`` where numba or the read-off tests are missing: the single-level ORBs detect
        on the one pyramid and describe by OpenCV's ``compute``, the numpy grid selects."""
        pyr = self._pyramid(gray)
        found = [det.detect(img, None) for det, img in zip(self._level_orb, pyr)]
        if sum(len(k) for k in found) < self.cfg.n_features:
            found = [det.detect(img, None) for det, img in zip(self._level_orb_low, pyr)]
        sizes = [len(k) for k in found]
        if sum(sizes) == 0:
            return self._finish(gray.shape, camera, depth_m, np.zeros((0, 2), np.float32), np.zeros(0, np.int64), None)
        pts = np.concatenate([_positions(k) * np.float32(sc) for k, sc in zip(found, self._scales)])
        # Attributes read by C-level iteration (map and attrgetter): twice as fast as a generator.
        resp = np.fromiter(chain.from_iterable(map(_RESPONSE, level) for level in found), np.float32, len(pts))
        chosen = self._select_indices(pts, resp, gray.shape[1], gray.shape[0])
        first = np.cumsum([0, *sizes])
        bounds = np.searchsorted(chosen, first)
        uv, octave, desc = [], [], []
        for k, det in enumerate(self._level_orb):
            kps = [found[k][i] for i in (chosen[bounds[k]:bounds[k + 1]] - first[k]).tolist()]
            if not kps:
                continue
            kept, d = det.compute(pyr[k], kps)
            if not kept or d is None:
                continue
            xy = _positions(kept)
            uv.append(xy * np.float32(self._scales[k]))
            octave.append(np.full(len(xy), k, np.int64))
            desc.append(d)
        if not uv:
            return self._finish(gray.shape, camera, depth_m, np.zeros((0, 2), np.float32), np.zeros(0, np.int64),
                                None)
        return self._finish(gray.shape, camera, depth_m, np.concatenate(uv), np.concatenate(octave),
                            np.concatenate(desc))

    def _extract_reference(self, gray: np.ndarray, camera: PinholeCamera, depth_m: np.ndarray | None,
                           mask: np.ndarray | None = None) -> FrameFeatures:
        """Reference twin of ``extract``: OpenCV's multi-level ORB detects, the grid selects, and
        the same ORB describes (building its pyramid a second time)."""
        kps = list(self._orb.detect(gray, mask))
        if len(kps) < self.cfg.n_features:
            kps = list(self._orb_low.detect(gray, mask))
        kps = self._select(kps, gray.shape[1], gray.shape[0])
        desc = None
        described: Sequence[cv2.KeyPoint] = kps
        if kps:
            described, desc = self._orb.compute(gray, kps)
        if not described or desc is None:
            return self._finish(gray.shape, camera, depth_m, np.zeros((0, 2), np.float32), np.zeros(0, np.int64), None)
        octave = np.array([k.octave for k in described], dtype=np.int64)
        return self._finish(gray.shape, camera, depth_m, cv2.KeyPoint_convert(described), octave, desc)  # type: ignore[attr-defined]

    def _finish(self, shape: tuple[int, ...], camera: PinholeCamera, depth_m: np.ndarray | DepthUnits | None,
                pts: np.ndarray, octave: np.ndarray, desc: np.ndarray | None) -> FrameFeatures:
        """FrameFeatures from level-0 keypoint positions pts [M, 2] (as OpenCV scales them), octaves
        [M] and descriptors [M, 32] (None when M = 0) of an image of ``shape`` (H, W, ...)."""
        if desc is None or len(pts) == 0:
            empty2 = np.zeros((0, 2))
            return FrameFeatures(empty2.astype(np.float32), empty2, np.zeros(0, np.int64),
                                 np.zeros((0, DESCRIPTOR_BYTES), np.uint8), np.zeros(0))
        # OpenCV scales level coordinates by s = scale^octave without the pixel-centre shift;
        # the centre of level pixel x is at (x + 0.5) s - 0.5 in level 0, a bias of 0.5 (s - 1)
        # (1.3 px at level 7) that differs between octaves of the same point.
        uv_raw, depth = orb.keypoint_depths(pts, octave, self._centre_shift, depth_m, shape[:2],
                                            (self.cfg.min_depth_m, self.cfg.max_depth_m))
        return FrameFeatures(uv_raw, undistort_points(uv_raw, camera), octave, np.ascontiguousarray(desc), depth)


class _PyramidLayout:
    """An image pyramid at OpenCV ORB's level sizes, laid out level after level in one buffer
    (``flat`` [sum H * W] uint8, ``levels`` [H, W] views on it), with a second buffer of the same
    layout for the smoothed levels; ``shapes`` [L, 3] (offset, height, width), and its offset and
    width columns contiguous, for the kernels."""

    def __init__(self, image_shape: tuple[int, ...], scales: list[float]) -> None:
        h, w = self.image_shape = (int(image_shape[0]), int(image_shape[1]))
        # sizes rounded from float32 quotients, as OpenCV's
        f32 = np.float32
        self.sizes = [(w, h)] + [(round(float(f32(w) / f32(s))), round(float(f32(h) / f32(s)))) for s in scales[1:]]
        shapes = np.zeros((len(self.sizes), 3), np.int64)
        shapes[:, 1], shapes[:, 2] = [sh for _, sh in self.sizes], [sw for sw, _ in self.sizes]
        shapes[1:, 0] = np.cumsum(shapes[:-1, 1] * shapes[:-1, 2])
        self.shapes = shapes
        self.offsets, self.widths = np.ascontiguousarray(shapes[:, 0]), np.ascontiguousarray(shapes[:, 2])
        size = int(shapes[-1, 0] + shapes[-1, 1] * shapes[-1, 2])
        self.flat, self.smoothed = np.empty(size, np.uint8), np.empty(size, np.uint8)
        self.levels = [self.flat[o:o + lh * lw].reshape(lh, lw) for o, lh, lw in shapes.tolist()]
        self.smoothed_levels = [self.smoothed[o:o + lh * lw].reshape(lh, lw) for o, lh, lw in shapes.tolist()]

    def resize(self) -> None:
        """Each level from the one before (the first one written), as OpenCV's ORB resizes."""
        for k in range(1, len(self.levels)):
            cv2.resize(self.levels[k - 1], self.sizes[k], dst=self.levels[k], interpolation=cv2.INTER_LINEAR_EXACT)


# FAST runs on a level's band less this margin: the corners ORB keeps lie EDGE_PX or more inside
# the border, and FAST's non-maximum suppression of a corner reads its neighbours' scores, each
# from the pixels up to 3 px around it; 4 px outside the kept band give them all, so the band's
# corners and scores are those of the whole level, at a fifth fewer Python keypoint objects.
_BAND_MARGIN = EDGE_PX - 4


def _fast_in_band(fast: cv2.FastFeatureDetector, level: np.ndarray) -> Sequence[cv2.KeyPoint]:
    """FAST's corners of ``level`` [H, W] that may lie in ORB's band (positions less
    ``_BAND_MARGIN``; the ring outside the band is filtered with the rest later); none where the
    level has no band."""
    h, w = level.shape
    if min(w, h) <= 2 * EDGE_PX:
        return ()
    m = _BAND_MARGIN
    return fast.detect(level[m:h - m, m:w - m])


def _positions(kps: Sequence[cv2.KeyPoint]) -> np.ndarray:
    """Keypoint positions [N, 2] float32 (OpenCV returns an empty tuple for none)."""
    if len(kps) == 0:
        return np.zeros((0, 2), np.float32)
    return np.asarray(cv2.KeyPoint_convert(kps), np.float32).reshape(-1, 2)  # type: ignore[attr-defined]  # missing from OpenCV's stubs


def level_shares(n: int, scale_factor: float, levels: int) -> list[int]:
    """How OpenCV's ORB splits ``n`` keypoints over ``levels`` pyramid levels: a geometric share
    per level (ratio 1 / scale_factor, rounded, in float32 as OpenCV does), the rest to the top."""
    factor = np.float32(1.0 / scale_factor)
    share = np.float32(n) * (np.float32(1.0) - factor) / (np.float32(1.0) - np.float32(float(factor) ** levels))
    out: list[int] = []
    for _ in range(levels - 1):
        out.append(int(np.round(share)))
        share = np.float32(share * factor)
    out.append(max(n - sum(out), 0))
    return out


def undistort_points(uv_raw: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """Distorted pixels [M, 2] to undistorted pixels [M, 2] (float64) of the same K."""
    if len(uv_raw) == 0 or not camera.has_distortion:
        return np.asarray(uv_raw, dtype=np.float64).reshape(-1, 2).copy()
    out = cv2.undistortPoints(np.asarray(uv_raw, np.float64).reshape(-1, 1, 2), camera.K,
                              camera.dist_coeffs, P=camera.K)
    return out.reshape(-1, 2)


def unroll_rolling_shutter(feats: FrameFeatures, K: np.ndarray, omega_c: np.ndarray, readout_s: float,
                           height: int) -> FrameFeatures:
    """Keypoints moved to where a global shutter at the centre row's time would have seen them
    (see ``_unroll_rolling_shutter``, the reference): by ``kernel_calls.unroll_kernel`` when numba is
    available (one pass over the keypoints instead of some twenty numpy temporaries)."""
    if len(feats) == 0 or readout_s == 0.0 or not np.any(omega_c):
        return feats
    if not numba_available():
        return _unroll_rolling_shutter(feats, K, omega_c, readout_s, height)
    return replace(feats, uv=unroll_kernel(feats.uv_raw, feats.uv, K, omega_c, readout_s, height))


def _unroll_rolling_shutter(feats: FrameFeatures, K: np.ndarray, omega_c: np.ndarray, readout_s: float,
                            height: int) -> FrameFeatures:
    """Keypoints moved to where a global shutter at the centre row's time would have seen them.

    A rolling shutter exposes row v at ``(v - (height - 1) / 2) / height * readout_s`` after the
    centre row; while the camera turns at ``omega_c`` [3] (rad/s, camera frame) a keypoint seen at
    time s lies on the ray ``Exp(omega_c s) K^-1 (u, v, 1)`` of the centre-row camera. Rotation
    only: the camera's translation in one readout (about a millimetre) is far below pixel noise.
    K: [3, 3]; returns a copy with ``uv`` [M, 2] corrected (``uv_raw``, depth and the rest kept).
    """
    if len(feats) == 0 or readout_s == 0.0 or not np.any(omega_c):
        return feats
    s = (feats.uv_raw[:, 1].astype(np.float64) - 0.5 * (height - 1)) / height * readout_s  # [M] s
    rv = s[:, None] * np.asarray(omega_c, dtype=np.float64)[None, :]  # [M, 3] rotation vectors
    theta2 = np.einsum("ij,ij->i", rv, rv)
    # Rodrigues with series coefficients: angles here are a few hundredths of a radian at most.
    a = 1.0 - theta2 / 6.0 + theta2 ** 2 / 120.0  # sin(t) / t
    b = 0.5 - theta2 / 24.0 + theta2 ** 2 / 720.0  # (1 - cos(t)) / t^2
    # Exp(rv) x = x + a rv x x + b rv x (rv x x), with x = (x0, x1, 1) the keypoint's ray; the
    # cross products written out per component (np.cross costs more than the rest together).
    r0, r1, r2 = rv[:, 0], rv[:, 1], rv[:, 2]
    x0 = (feats.uv[:, 0] - K[0, 2]) / K[0, 0]
    x1 = (feats.uv[:, 1] - K[1, 2]) / K[1, 1]
    c0, c1, c2 = r1 - r2 * x1, r2 * x0 - r0, r0 * x1 - r1 * x0  # rv x x
    y0 = x0 + a * c0 + b * (r1 * c2 - r2 * c1)
    y1 = x1 + a * c1 + b * (r2 * c0 - r0 * c2)
    y2 = 1.0 + a * c2 + b * (r0 * c1 - r1 * c0)
    uv = np.empty((len(feats), 2))
    uv[:, 0] = K[0, 0] * y0 / y2 + K[0, 2]
    uv[:, 1] = K[1, 1] * y1 / y2 + K[1, 2]
    return replace(feats, uv=uv)


def hamming_pairs(desc_a: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance of two packed descriptor arrays [P, 32] -> [P] int."""
    a = np.ascontiguousarray(desc_a).view(np.uint64)  # [P, 4]
    b = np.ascontiguousarray(desc_b).view(np.uint64)
    return np.bitwise_count(np.bitwise_xor(a, b)).sum(axis=1, dtype=np.int64)


def _hamming_pairs_table(desc_a: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """Reference twin of ``hamming_pairs`` (byte lookup table)."""
    x = np.bitwise_xor(desc_a, desc_b)
    return _POPCOUNT[x].sum(axis=1, dtype=np.int64)


# Grid cell of the compiled matcher, px: about the search radius, so a query visits 4-9 cells.
MATCH_CELL_PX = 16.0


def match_by_projection(proj_uv: np.ndarray, point_desc: np.ndarray, feats: FrameFeatures,
                        radius_px: np.ndarray | float, max_distance: int, ratio: float,
                        available: np.ndarray | None = None, max_candidates: int = 12,
                        kp_tree: cKDTree | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match projected map points to keypoints within a pixel radius.

    proj_uv: [P, 2] predicted undistorted pixels; point_desc: [P, 32]; radius_px: scalar or [P].
    available: [M] bool, keypoints that may still take a match (default all).
    max_candidates: nearest keypoints examined per point; kp_tree: a cKDTree of ``feats.uv``
    (used by the plain path only).
    Returns (point_index [K], keypoint_index [K], hamming [K]) sorted by keypoint index; one
    keypoint per point and one point per keypoint (the lower distance wins, then the lower point).
    Runs the numba kernel (``kernel_calls.match_by_projection_kernel``) when numba is available,
    else its plain twin ``_match_by_projection``.
    """
    if len(proj_uv) == 0 or len(feats) == 0 or not numba_available():
        return _match_by_projection(proj_uv, point_desc, feats, radius_px, max_distance, ratio, available,
                                    max_candidates, kp_tree)
    radius = np.broadcast_to(np.asarray(radius_px, dtype=np.float64), (len(proj_uv),))
    avail = np.ones(len(feats), dtype=bool) if available is None else available
    # Cells must cover the keypoints' extent; undistorted keypoints can leave the image a little.
    width = float(max(feats.uv[:, 0].max(), proj_uv[:, 0].max())) + 1.0
    height = float(max(feats.uv[:, 1].max(), proj_uv[:, 1].max())) + 1.0
    return match_by_projection_kernel(proj_uv, radius, point_desc, feats.uv, feats.desc, avail, max_distance,
                                      ratio, min(max_candidates, len(feats)), MATCH_CELL_PX,
                                      int(np.ceil(max(width, 1.0))), int(np.ceil(max(height, 1.0))))


def _match_by_projection(proj_uv: np.ndarray, point_desc: np.ndarray, feats: FrameFeatures,
                         radius_px: np.ndarray | float, max_distance: int, ratio: float,
                         available: np.ndarray | None = None, max_candidates: int = 12,
                         kp_tree: cKDTree | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain twin of ``match_by_projection`` (k-d tree and numpy): match projected map points to
    keypoints within a pixel radius.

    proj_uv: [P, 2] predicted undistorted pixels; point_desc: [P, 32]; radius_px: scalar or [P].
    available: [M] bool, keypoints that may still take a match (default all).
    max_candidates: nearest keypoints examined per point; kp_tree: a cKDTree of ``feats.uv`` to reuse.
    Returns (point_index [K], keypoint_index [K], hamming [K]); one keypoint per point and one
    point per keypoint (the lower distance wins).
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    if len(proj_uv) == 0 or len(feats) == 0:
        return empty
    radius = np.broadcast_to(np.asarray(radius_px, dtype=np.float64), (len(proj_uv),))
    # The k nearest keypoints within the largest radius (bounded work per map point), then
    # each point's own radius.
    k = min(max_candidates, len(feats))
    tree = kp_tree if kp_tree is not None else cKDTree(feats.uv)
    d, j = tree.query(proj_uv, k=k, distance_upper_bound=float(radius.max()))
    d, j = d.reshape(len(proj_uv), k), j.reshape(len(proj_uv), k)
    keep = d <= radius[:, None]
    pi = np.broadcast_to(np.arange(len(proj_uv))[:, None], keep.shape)[keep]
    ki = j[keep].astype(np.int64)
    if available is not None:
        ok = available[ki]
        pi, ki = pi[ok], ki[ok]
    if len(pi) == 0:
        return empty
    dist = hamming_pairs(point_desc[pi], feats.desc[ki])
    # Best and second best per map point.
    order = np.lexsort((dist, pi))
    pi, ki, dist = pi[order], ki[order], dist[order]
    first = np.ones(len(pi), dtype=bool)
    first[1:] = pi[1:] != pi[:-1]
    best_idx = np.flatnonzero(first)
    second_ok = np.zeros(len(best_idx), dtype=bool)
    nxt = best_idx + 1
    has_second = (nxt < len(pi))
    has_second[has_second] = pi[nxt[has_second]] == pi[best_idx[has_second]]
    second_dist = np.full(len(best_idx), 1e9)
    second_dist[has_second] = dist[nxt[has_second]]
    second_ok = dist[best_idx] <= ratio * second_dist
    good = (dist[best_idx] <= max_distance) & second_ok
    bp, bk, bd = pi[best_idx][good], ki[best_idx][good], dist[best_idx][good]
    # One point per keypoint: keep the closest descriptor.
    order = np.lexsort((bd, bk))
    bp, bk, bd = bp[order], bk[order], bd[order]
    first = np.ones(len(bk), dtype=bool)
    first[1:] = bk[1:] != bk[:-1]
    return bp[first], bk[first], bd[first]


def match_descriptors(desc_q: np.ndarray, desc_t: np.ndarray, ratio: float,
                      max_distance: int) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force matching with Lowe's ratio test and mutual uniqueness.

    desc_q: [Q, 32], desc_t: [T, 32] uint8. Returns (query_index [K], train_index [K]).
    """
    if len(desc_q) < 2 or len(desc_t) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    knn = bf.knnMatch(desc_q, desc_t, k=2)
    q, t, d = [], [], []
    for m in knn:
        if len(m) == 2 and m[0].distance <= ratio * m[1].distance and m[0].distance <= max_distance:
            q.append(m[0].queryIdx)
            t.append(m[0].trainIdx)
            d.append(m[0].distance)
    if not q:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    q_a, t_a, d_a = np.array(q), np.array(t), np.array(d)
    order = np.lexsort((d_a, t_a))
    q_a, t_a = q_a[order], t_a[order]
    first = np.ones(len(t_a), dtype=bool)
    first[1:] = t_a[1:] != t_a[:-1]
    return q_a[first], t_a[first]

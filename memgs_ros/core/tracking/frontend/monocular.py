"""Monocular tracker: two-view initialisation, then PnP tracking on triangulated points.

The map's scale is arbitrary (median depth of the first two-view reconstruction is 1) but
consistent within a segment; evaluate with Sim(3) alignment.
"""
from __future__ import annotations

import cv2
import numpy as np

from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.tracking.backend.ba_problem import build_problem
from memgs_ros.core.tracking.backend.bundle_adjustment import CHI2_MONO, local_bundle_adjustment
from memgs_ros.core.tracking.config import KeyframeInfo, TrackingState
from memgs_ros.core.tracking.features.features import FrameFeatures, match_by_projection, match_descriptors
from memgs_ros.core.tracking.frontend.feature_tracker import FeatureTracker, keyframe_info
from memgs_ros.core.tracking.frontend.local_map import SparseKeyframe, SparseMap

_MAX_INIT_AGE_FRAMES = 30  # restart from a new reference frame when initialisation takes longer
_MIN_COS_PARALLAX = 0.9998  # rays closer than ~1.1 deg give depth too uncertain to keep
_TRIANGULATION_NEIGHBOURS = 3
# A new keyframe's points are searched for in this many covisible keyframes (ORB-SLAM's fusion):
# a triangulated point otherwise starts with two observations, and local BA had too little to
# hold the scale (the synthetic mono case was bimodal, 1.9-11 cm; see docs/results.md, Tracking).
_FUSE_NEIGHBOURS = 5
_FUSE_RADIUS_PX = 3.0  # at level 0; scaled with the point's octave


def triangulate(P0: np.ndarray, P1: np.ndarray, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
    """Linear triangulation: projection matrices [3, 4], pixels [N, 2] each -> points [N, 3]."""
    Xh = cv2.triangulatePoints(P0, P1, uv0.T.astype(np.float64), uv1.T.astype(np.float64))
    w = Xh[3]
    w = np.where(np.abs(w) < 1e-12, 1e-12, w)
    return (Xh[:3] / w).T


def check_triangulated(X: np.ndarray, T0_cw: np.ndarray, T1_cw: np.ndarray, uv0: np.ndarray,
                       uv1: np.ndarray, K: np.ndarray, sigma0: np.ndarray, sigma1: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Good triangulations [N] bool (in front, small reprojection error, enough parallax) and cos parallax [N]."""
    good = np.all(np.isfinite(X), axis=1)
    cos = np.ones(len(X))
    for T, uv, sig in ((T0_cw, uv0, sigma0), (T1_cw, uv1, sigma1)):
        p = X @ T[:3, :3].T + T[:3, 3]
        z = p[:, 2]
        front = z > 0
        zs = np.where(front, z, 1.0)
        u = K[0, 0] * p[:, 0] / zs + K[0, 2]
        v = K[1, 1] * p[:, 1] / zs + K[1, 2]
        err2 = ((u - uv[:, 0]) ** 2 + (v - uv[:, 1]) ** 2) / sig ** 2
        good &= front & (err2 < CHI2_MONO)
    c0 = -T0_cw[:3, :3].T @ T0_cw[:3, 3]
    c1 = -T1_cw[:3, :3].T @ T1_cw[:3, 3]
    r0, r1 = X - c0, X - c1
    cos = np.einsum("ij,ij->i", r0, r1) / np.maximum(np.linalg.norm(r0, axis=1) * np.linalg.norm(r1, axis=1), 1e-12)
    good &= cos < _MIN_COS_PARALLAX
    return good, cos


class MonocularTracker(FeatureTracker):
    """Feature tracking without depth; see module docstring."""

    uses_depth = False
    ba_fixed_keyframes = 2  # fixing two keyframes also pins the scale, the seventh gauge freedom

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self._init_ref: tuple[Frame, FrameFeatures] | None = None
        self._init_age = 0

    # -- two-view initialisation ----------------------------------------------------------
    def _initialise(self, frame: Frame, feats: FrameFeatures
                    ) -> tuple[np.ndarray | None, KeyframeInfo | None, int, int]:
        cfg = self.cfg
        if self._init_ref is None or self._init_age > _MAX_INIT_AGE_FRAMES:
            self._init_ref = (frame, feats) if len(feats) >= cfg.mono_min_init_matches else None
            self._init_age = 0
            return None, None, 0, 0
        self._init_age += 1
        ref_frame, ref = self._init_ref
        q, t = match_descriptors(feats.desc, ref.desc, ratio=0.8, max_distance=cfg.max_descriptor_distance)
        if len(q) < cfg.mono_min_init_matches:
            if len(q) < cfg.mono_min_init_matches // 2:
                self._init_ref = (frame, feats)
                self._init_age = 0
            return None, None, len(q), 0
        uv0, uv1 = ref.uv[t], feats.uv[q]
        found = self._two_view(uv0, uv1, self._inv_sigma(ref.octave[t]) ** -1,
                               self._inv_sigma(feats.octave[q]) ** -1)
        if found is None:
            return None, None, len(q), 0
        T1, X, good = found
        info = self._start_map(ref_frame, ref, frame, feats, T1, X[good], t[good], q[good])
        return self._T_cw_last, info, len(q), int(good.sum())

    def _two_view(self, uv0: np.ndarray, uv1: np.ndarray, sig0: np.ndarray, sig1: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Relative pose T_cw of view 1 (view 0 at the origin), points [N, 3], good [N] bool."""
        cfg, K = self.cfg, self.K
        E, mask_e = cv2.findEssentialMat(uv0, uv1, K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
        H, mask_h = cv2.findHomography(uv0, uv1, cv2.RANSAC, 2.0)
        n_e = int(mask_e.sum()) if mask_e is not None else 0
        n_h = int(mask_h.sum()) if mask_h is not None else 0
        candidates: list[tuple[np.ndarray, np.ndarray]] = []
        if H is not None and n_h / max(n_h + n_e, 1) > cfg.mono_homography_ratio:
            _, Rs, ts, _ = cv2.decomposeHomographyMat(H, K)
            candidates = [(R, t.ravel()) for R, t in zip(Rs, ts)]
        elif E is not None and E.shape == (3, 3):
            R1, R2, t = cv2.decomposeEssentialMat(E)
            candidates = [(R, s * t.ravel()) for R in (R1, R2) for s in (1.0, -1.0)]
        best = None
        counts = []
        P0 = K @ np.eye(4)[:3]
        for R, t in candidates:
            if np.linalg.norm(t) < 1e-9:
                counts.append(0)
                continue
            t = t / np.linalg.norm(t)
            T1 = np.eye(4)
            T1[:3, :3], T1[:3, 3] = R, t
            X = triangulate(P0, K @ T1[:3], uv0, uv1)
            good, cos = check_triangulated(X, np.eye(4), T1, uv0, uv1, K, sig0, sig1)
            counts.append(int(good.sum()))
            if best is None or good.sum() > best[2].sum():
                best = (T1, X, good, cos)
        if best is None:
            return None
        T1, X, good, cos = best
        n_good = int(good.sum())
        counts.sort(reverse=True)
        ambiguous = len(counts) > 1 and counts[1] > 0.7 * n_good
        parallax_deg = np.degrees(np.arccos(np.clip(np.median(cos[good]), -1, 1))) if n_good else 0.0
        if n_good < cfg.mono_min_triangulated or ambiguous or parallax_deg < cfg.mono_min_parallax_deg:
            return None
        return T1, X, good

    def _start_map(self, ref_frame: Frame, ref: FrameFeatures, frame: Frame, feats: FrameFeatures,
                   T1: np.ndarray, X: np.ndarray, i_ref: np.ndarray, i_cur: np.ndarray) -> KeyframeInfo:
        # Median depth 1: the map's unit.
        med = float(np.median(X[:, 2]))
        X = X / med
        T1 = T1.copy()
        T1[:3, 3] /= med
        kf0 = self._make_keyframe(ref_frame, ref, np.eye(4))
        kf1 = self._make_keyframe(frame, feats, T1)
        ids = self.map.add_points(X, ref.desc[i_ref], ref.octave[i_ref], kf0.keyframe_id, i_ref)
        self.map.add_observations(ids, kf1.keyframe_id, i_cur)
        # Full BA of the two views (first fixed; monocular: no depth), then restore the unit median
        # depth. Here, on the tracking thread: nothing can be tracked before it.
        sp = build_problem(self.map.snapshot(), [kf0.keyframe_id, kf1.keyframe_id], np.array([True, False]),
                           ids, self.inv_sigma_levels)
        res = local_bundle_adjustment(sp.problem, self.K, self.bf, self.cfg.ba_huber_px, 20)
        X2, T2 = res.points_w, res.T_cw[1].copy()
        med2 = float(np.median(X2[:, 2]))
        if med2 > 0 and np.isfinite(res.final_cost):
            X2 = X2 / med2
            T2[:3, 3] /= med2
            self.map.commit_refinement([kf1.keyframe_id], T2[None], ids, X2, [])
        self.map.set_bad(ids[np.unique(sp.problem.obs_point[~res.obs_inlier])])
        self.state = TrackingState.OK
        self._T_cw_last = kf1.T_cw.copy()
        self._last_good_T_cw = kf1.T_cw.copy()
        self.motion.reset()
        self._lost_frames = 0
        self._local_kfs = [kf0.keyframe_id, kf1.keyframe_id]
        self._init_ref = None
        self._last_kf_id = kf1.keyframe_id
        self._frames_since_kf = 0
        info = keyframe_info(self.map, kf1)
        self._last_kf_info = info
        return info

    # -- new points by triangulation -------------------------------------------------------
    def _create_points(self, kf: SparseKeyframe, frame: Frame) -> None:
        own = kf.point_ids[kf.point_ids >= 0]
        neighbours = self.map.covisible(own, _TRIANGULATION_NEIGHBOURS, exclude=kf.keyframe_id)
        P_kf = self.K @ kf.T_cw[:3]
        for nb_id in neighbours:
            nb = self.map.keyframes.get(nb_id)
            if nb is None:
                continue
            a = np.flatnonzero(kf.point_ids < 0)
            b = np.flatnonzero(nb.point_ids < 0)
            if len(a) < 8 or len(b) < 8:
                continue
            q, t = match_descriptors(kf.feats.desc[a], nb.feats.desc[b], ratio=0.8,
                                     max_distance=self.cfg.max_descriptor_distance)
            if len(q) < 8:
                continue
            ia, ib = a[q], b[t]
            X = triangulate(P_kf, self.K @ nb.T_cw[:3], kf.feats.uv[ia], nb.feats.uv[ib])
            good, _ = check_triangulated(X, kf.T_cw, nb.T_cw, kf.feats.uv[ia], nb.feats.uv[ib], self.K,
                                         1.0 / self._inv_sigma(kf.feats.octave[ia]),
                                         1.0 / self._inv_sigma(nb.feats.octave[ib]))
            if not good.any():
                continue
            ia, ib, X = ia[good], ib[good], X[good]
            ids = self.map.add_points(X, kf.feats.desc[ia], kf.feats.octave[ia], kf.keyframe_id, ia)
            self.map.add_observations(ids, nb_id, ib)
        self._fuse_into_neighbours(kf)

    def _fuse_into_neighbours(self, kf: SparseKeyframe) -> None:
        """Add observations of ``kf``'s points in its covisible keyframes: each point not yet seen
        there is projected into the keyframe and matched, within a radius, to a keypoint that has
        no point yet."""
        own = kf.point_ids[kf.point_ids >= 0]
        own = own[self.map.good(own)]
        if len(own) == 0:
            return
        p_w, desc, octave = self.map.point_arrays(own)
        for nb_id in self.map.covisible(own, _FUSE_NEIGHBOURS, exclude=kf.keyframe_id):
            nb = self.map.keyframes.get(nb_id)
            if nb is None:
                continue
            cand = np.flatnonzero(~np.isin(own, nb.point_ids))
            uv, vis = self.matcher.project(p_w[cand], nb.T_cw)
            idx = cand[vis]
            if len(idx) == 0:
                continue
            radius = _FUSE_RADIUS_PX / self._inv_sigma(octave[idx])
            pi, ki, _ = match_by_projection(uv[vis], desc[idx], nb.feats, radius, self.cfg.max_descriptor_distance,
                                            self.cfg.match_ratio, available=nb.point_ids < 0)
            if len(pi):
                self.map.add_observations(own[idx[pi]], nb_id, ki)

    def _keyframe_ratio(self) -> float:
        return self.cfg.mono_keyframe_tracked_ratio

    def _ba_max_frames_behind(self) -> int:
        return self.cfg.mono_ba_max_frames_behind

    def _lost_timeout(self, frame: Frame, feats: FrameFeatures) -> np.ndarray | None:
        """Start over: a new segment (new scale) from a fresh two-view initialisation."""
        self.map = SparseMap(self.map.next_keyframe_id)
        self.segment_id += 1
        self.state = TrackingState.NOT_INITIALIZED
        self._init_ref = None
        self._T_cw_last = None
        return None

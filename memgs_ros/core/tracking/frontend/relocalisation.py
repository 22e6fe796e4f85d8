"""Relocalisation against stored keyframes: descriptor matching + PnP RANSAC + robust refinement.

The keyframes to try come from place recognition (the tracker's BoW keyframe database, best
score first); without a vocabulary, keyframes spread over the whole map.
"""
from __future__ import annotations

import cv2
import numpy as np

from memgs_ros.core.tracking.backend.bundle_adjustment import optimize_pose
from memgs_ros.core.tracking.config import TrackerConfig
from memgs_ros.core.tracking.features.features import FrameFeatures, match_descriptors
from memgs_ros.core.tracking.frontend.local_map import SparseMap

_MIN_CANDIDATE_MATCHES = 15
_MAX_PNP_CANDIDATES = 5


def candidate_keyframes(kf_ids: list[int], max_count: int) -> list[int]:
    """Up to ``max_count`` keyframe ids spread over the whole map, newest first."""
    ids = sorted(kf_ids, reverse=True)
    if len(ids) <= max_count:
        return ids
    pick = np.unique(np.linspace(0, len(ids) - 1, max_count).round().astype(int))
    return [ids[i] for i in pick]


def relocalise(smap: SparseMap, feats: FrameFeatures, K: np.ndarray, bf: float, cfg: TrackerConfig,
               inv_sigma_levels: np.ndarray, candidates: list[int] | None = None) -> tuple[np.ndarray, int] | None:
    """A pose T_cw [4, 4] for ``feats`` from the best-matching keyframe, with its inlier count.

    Strict on purpose (a wrong relocalisation is worse than staying lost): Lowe ratio 0.75,
    PnP RANSAC at ``ransac_reprojection_px``, then robust refinement must keep at least
    half of ``reloc_min_inliers``; the caller confirms against the local map. ``candidates``:
    keyframe ids to try (place recognition's answer); None = ``reloc_max_keyframes`` spread out.
    """
    if len(feats) < _MIN_CANDIDATE_MATCHES:
        return None
    if candidates is None:
        candidates = candidate_keyframes(list(smap.keyframes), cfg.reloc_max_keyframes)
    kfs = [smap.keyframes[i] for i in candidates if i in smap.keyframes]
    per_kf = []
    for kf in kfs:
        has = np.flatnonzero(kf.point_ids >= 0)
        pids = kf.point_ids[has]
        ok = smap.good(pids)
        per_kf.append((has[ok], pids[ok]))
    scored = []
    for kf, (kp_idx, pids) in zip(kfs, per_kf):
        if len(pids) < _MIN_CANDIDATE_MATCHES:
            continue
        q, t = match_descriptors(feats.desc, kf.feats.desc[kp_idx], ratio=0.75,
                                 max_distance=cfg.max_descriptor_distance)
        if len(q) >= _MIN_CANDIDATE_MATCHES:
            scored.append((len(q), q, pids[t]))
    scored.sort(key=lambda s: -s[0])
    need = max(cfg.reloc_min_inliers // 2, 10)
    for _, q, pids in scored[:_MAX_PNP_CANDIDATES]:
        p_w, _, _ = smap.point_arrays(pids)
        uv = feats.uv[q]
        found, rvec, tvec, inl = cv2.solvePnPRansac(
            p_w.astype(np.float64), uv.astype(np.float64), K, None,
            iterationsCount=cfg.ransac_iterations * 2, reprojectionError=cfg.ransac_reprojection_px,
            confidence=0.99, flags=cv2.SOLVEPNP_EPNP)
        if not found or inl is None or len(inl) < need:
            continue
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec.ravel()
        inv_sigma = inv_sigma_levels[np.clip(feats.octave[q], 0, len(inv_sigma_levels) - 1)]
        T, inlier = optimize_pose(T, p_w, uv, feats.depth_m[q], inv_sigma, K, bf)
        if inlier.sum() >= need:
            return T, int(inlier.sum())
    return None

"""The tracker's keyframe rules that read its map: whether a settled keyframe already sees a view,
and ORB-SLAM's culling of redundant keyframes (with the heir each culled keyframe hands on to).

The front-end (``feature_tracker.FeatureTracker``) calls them on its own map; they keep no state.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking.config import TrackerConfig
from memgs_ros.core.tracking.frontend.local_map import SparseKeyframe, SparseMap
from memgs_ros.core.tracking.frontend.pose_tracking import rotation_angle_deg

__all__ = ["Culled", "covered", "cull_around", "keyframe_needed"]


@dataclass(frozen=True, eq=False)
class Culled:
    """A keyframe culling removed: its id, its heir (the kept keyframe that shared the most points
    with it: what followed the culled keyframe follows the heir from now on) and its last T_wc [4, 4]."""

    kf_id: int
    heir_id: int
    T_wc: np.ndarray


def covered(smap: SparseMap, kf_ids: Iterable[int], T_cw: np.ndarray, settled_before_ns: int,
            max_deg: float, max_m: float) -> bool:
    """Whether one of ``kf_ids`` taken at or before ``settled_before_ns`` (a settled keyframe) sees
    from within ``max_deg`` and ``max_m`` (map units) of the pose T_cw [4, 4]; never with a bound <= 0."""
    if max_deg <= 0.0 or max_m <= 0.0:
        return False
    for kf_id in dict.fromkeys(kf_ids):
        kf = smap.keyframes.get(kf_id)
        if kf is None or kf.stamp_ns > settled_before_ns:
            continue
        d = T_cw @ invert_pose(kf.T_cw)
        if float(np.linalg.norm(d[:3, 3])) <= max_m and rotation_angle_deg(d[:3, :3]) <= max_deg:
            return True
    return False


def keyframe_needed(cfg: TrackerConfig, smap: SparseMap, T_cw: np.ndarray, last: SparseKeyframe, n_tracked: int,
                    frames_since_kf: int, weak: bool, local_kfs: list[int], settled_before_ns: int,
                    scale_unit: float = 1.0) -> bool:
    """Keyframes by need, for a frame at T_cw [4, 4] tracking ``n_tracked`` points ``frames_since_kf``
    frames after the last keyframe ``last``. Tracking that weakens (``weak``: fewer tracked points
    than ``keyframe_tracked_ratio`` of the reference keyframe's, too few close points) asks for one,
    and so do time (``keyframe_max_frames``) and motion from the last keyframe
    (``keyframe_max_rotation_deg`` / ``_translation_m``); but neither where a settled keyframe of
    ``local_kfs`` (taken at or before ``settled_before_ns``) already sees from nearby (``covered``:
    ``keyframe_weak_cover_*`` for weak tracking, ``keyframe_cover_*`` for time and motion). A place
    flown again is tracked on the points mapped there and adds none (the fr1/rpy head played five
    times, forward and back, with the shutter read in the flight's direction: 28 keyframes, then
    7 more in four passes, against 27-28 more each pass before). ``scale_unit``: metres per map unit."""
    if frames_since_kf < cfg.keyframe_min_frames or n_tracked < cfg.min_inliers:
        return False
    if weak:
        return not covered(smap, local_kfs, T_cw, settled_before_ns, cfg.keyframe_weak_cover_deg,
                           cfg.keyframe_weak_cover_m * scale_unit)
    d = T_cw @ invert_pose(last.T_cw)
    due = bool(frames_since_kf >= cfg.keyframe_max_frames
               or rotation_angle_deg(d[:3, :3]) > cfg.keyframe_max_rotation_deg
               or np.linalg.norm(d[:3, 3]) / scale_unit > cfg.keyframe_max_translation_m)
    return due and not covered(smap, local_kfs, T_cw, settled_before_ns, cfg.keyframe_cover_deg,
                               cfg.keyframe_cover_m * scale_unit)


def cull_around(smap: SparseMap, kf: SparseKeyframe, neighbours: int, ratio: float, observers: int) -> list[Culled]:
    """ORB-SLAM's keyframe culling around the new keyframe ``kf``: of its ``neighbours`` most
    covisible keyframes, those whose good points are at least ``ratio`` seen by ``observers`` other
    keyframes are removed (``SparseMap.cull_redundant_keyframes``), never ``kf`` nor the map's
    oldest (its anchor). Returns what was removed, each with its heir (an heir culled in the same
    pass hands on to its own; ``kf`` when the chain comes back round)."""
    if ratio <= 0.0:
        return []
    own = kf.point_ids[kf.point_ids >= 0]
    candidates = smap.covisible(own, neighbours, exclude=kf.keyframe_id)
    heirs: dict[int, tuple[int, np.ndarray]] = {}
    for c in candidates:
        ck = smap.keyframes[c]
        pts = ck.point_ids[ck.point_ids >= 0]
        heirs[c] = ((smap.covisible(pts, 1, exclude=c) or [kf.keyframe_id])[0], ck.T_wc)
    removed = smap.cull_redundant_keyframes(candidates, ratio, observers, {kf.keyframe_id, min(smap.keyframes)})
    gone, out = set(removed), []
    for r in removed:
        heir, seen = heirs[r][0], {r}
        while heir in gone:
            seen.add(heir)
            heir = heirs[heir][0]
            if heir in seen:
                heir = kf.keyframe_id
        out.append(Culled(r, heir, heirs[r][1]))
    return out

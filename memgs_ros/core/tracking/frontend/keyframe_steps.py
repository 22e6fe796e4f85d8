"""The tracker's keyframe steps (``FeatureTracker`` inherits them): whether the frame becomes a
keyframe, and what a new keyframe does to the map (new points, culled points and keyframes, the
keyframe cap) and to the back-end (local BA, place recognition); plus the hooks a tracker
overrides (how points are made, the keyframe ratio, the map's scale)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking.config import KeyframeInfo, TrackerConfig, TrackingState, TrackResult
from memgs_ros.core.tracking.frontend.keyframe_rules import covered, cull_around, keyframe_needed
from memgs_ros.core.tracking.frontend.local_map import SparseKeyframe, SparseMap

if TYPE_CHECKING:
    from memgs_ros.core.geometry.frame import Frame
    from memgs_ros.core.tracking.features.features import FrameFeatures
    from memgs_ros.core.tracking.frontend.corrections import BackendLink, KeyframesMoved
    from memgs_ros.core.tracking.frontend.pose_tracking import TrackOutcome

__all__ = ["KeyframeSteps", "LastView", "keyframe_info"]


def keyframe_info(smap: SparseMap, kf: SparseKeyframe) -> KeyframeInfo:
    """What the mapper gets of a keyframe: its pose, keypoints and the depth of their map points."""
    active = kf.point_ids >= 0
    depth = np.full(len(kf.point_ids), np.nan, dtype=np.float32)
    if active.any():
        p_w, _, _ = smap.point_arrays(kf.point_ids[active])
        depth[active] = (p_w @ kf.T_cw[2, :3] + kf.T_cw[2, 3]).astype(np.float32)
    return KeyframeInfo(kf.keyframe_id, kf.stamp_ns, invert_pose(kf.T_cw),
                        kf.feats.uv.astype(np.float32), depth, active)


@dataclass(frozen=True, eq=False)
class LastView:
    """The last tracked frame when it did not become a keyframe: what ``end_flight`` needs to make it one."""

    frame: Frame
    feats: FrameFeatures
    outcome: TrackOutcome


class KeyframeSteps:
    """Mixin of ``FeatureTracker``: its keyframe decision and insertion (see the module docstring)."""

    cfg: TrackerConfig
    map: SparseMap
    segment_id: int
    localize_only: bool
    keyframes_culled: int
    _link: BackendLink
    _last_kf_id: int
    _ref_kf_id: int
    _stamp_ns: int
    _frames_since_kf: int
    _keyframe_deferrals: int
    _local_kfs: list[int]
    _culled: list[tuple[int, int, np.ndarray]]
    _last_kf_info: KeyframeInfo | None
    _last_view: LastView | None
    state: TrackingState

    def _follow(self, moves: list[KeyframesMoved]) -> None:
        raise NotImplementedError

    def _commit_backend(self, wait: bool) -> np.ndarray:
        raise NotImplementedError

    def end_flight(self) -> TrackResult | None:
        """The flight's last view as a keyframe: the last frame, when it was tracked and did not
        become one, unless a keyframe of the local map (settled or not) sees from within
        ``keyframe_weak_cover_*``. Keyframes go in by time and motion, so the frames after the last
        one (up to ``keyframe_max_frames``, or ``keyframe_max_rotation_deg`` of turn) were never
        mapped: a flight's map ended short of its last view, and a map continued from it started
        there (the fr1/rpy head, frames 80-199 continuing a map of 0-119: the last keyframe was
        frame 191, the views of 192-199 rendered 3 dB below the one session's, whose frame 199 was
        a keyframe by chance). None when nothing is added (call once, after the last frame)."""
        last, self._last_view = self._last_view, None
        if last is None or self.localize_only or self.state != TrackingState.OK:
            return None
        T = self._commit_backend(wait=True)  # the last frame's pose, moved with the BA results
        cfg = self.cfg
        if len(last.outcome.point_ids) < cfg.min_inliers or covered(
                self.map, [self._ref_kf_id, *self._local_kfs], T, last.frame.stamp_ns,
                cfg.keyframe_weak_cover_deg, cfg.keyframe_weak_cover_m * self._scale_unit()):
            return None
        kf = self._insert_keyframe(last.frame, last.feats, T, last.outcome)
        return TrackResult(last.frame.stamp_ns, invert_pose(T), self.state, kf, last.outcome.n_matches,
                           len(last.outcome.point_ids), 0.0, self.segment_id, kf.keyframe_id)

    # -- hooks ----------------------------------------------------------------------------
    def _create_points(self, kf: SparseKeyframe, frame: Frame) -> None:
        raise NotImplementedError

    def _need_close_points(self, feats: FrameFeatures, kp_idx: np.ndarray) -> bool:
        return False

    def _scale_unit(self) -> float:
        """Metres per map unit for the translation gate (1 for RGB-D; mono overrides)."""
        return 1.0

    def _keyframe_ratio(self) -> float:
        return self.cfg.keyframe_tracked_ratio

    def _min_point_obs(self) -> int:
        return 2

    # -- steps ----------------------------------------------------------------------------
    def _need_keyframe(self, T_cw: np.ndarray, feats: FrameFeatures, outcome: TrackOutcome) -> bool:
        """``keyframe_rules.keyframe_needed``, judged against the reference keyframe (the one sharing
        the most tracked points) and covered by the local map's keyframes taken at least
        ``keyframe_cover_age_s`` before the frame (the stretch of the last seconds is being mapped:
        the fr1/rpy head sweeps back over its views: settled at 5 s it lost 2 of 28 keyframes and 0.24 dB)."""
        cfg = self.cfg
        last = self.map.keyframes.get(self._last_kf_id)
        ref = self.map.keyframes.get(self._ref_kf_id, last)
        if self.localize_only:
            return False
        if last is None or ref is None:
            return self._frames_since_kf >= cfg.keyframe_min_frames and len(outcome.point_ids) >= cfg.min_inliers
        weak = (len(outcome.point_ids) < self._keyframe_ratio() * self._reference_tracked(ref)
                or self._need_close_points(feats, outcome.kp_idx))
        return keyframe_needed(cfg, self.map, T_cw, last, len(outcome.point_ids), self._frames_since_kf, weak,
                               [self._ref_kf_id, *self._local_kfs],
                               self._stamp_ns - int(cfg.keyframe_cover_age_s * 1e9), self._scale_unit())

    def _reference_tracked(self, ref: SparseKeyframe) -> int:
        """Points of the reference keyframe seen by enough keyframes (ORB-SLAM's nMinObs)."""
        ids = ref.point_ids[ref.point_ids >= 0]
        return int((self.map.n_observations(ids) >= (3 if len(self.map.keyframes) > 2 else 2)).sum())

    def _make_keyframe(self, frame: Frame, feats: FrameFeatures, T_cw: np.ndarray) -> SparseKeyframe:
        kf = SparseKeyframe(self.map.new_keyframe_id(), frame.stamp_ns, T_cw.copy(), feats,
                            np.full(len(feats), -1, dtype=np.int64), self.segment_id)
        self.map.add_keyframe(kf)
        return kf

    def _insert_keyframe(self, frame: Frame, feats: FrameFeatures, T_cw: np.ndarray,
                         outcome: TrackOutcome) -> KeyframeInfo:
        kf = self._make_keyframe(frame, feats, T_cw)
        self.map.add_observations(outcome.point_ids, kf.keyframe_id, outcome.kp_idx)
        self._create_points(kf, frame)
        self.map.cull_points(kf.keyframe_id, self.cfg.point_min_found_ratio, self._min_point_obs())
        self._cap_keyframes(kf.keyframe_id)
        self._cull_keyframes(kf)
        return self._finish_keyframe(kf)

    def _cull_keyframes(self, kf: SparseKeyframe) -> None:
        """Culling around the new keyframe (``keyframe_rules.cull_around``): the culled ones leave the
        local map and the place-recognition databases, and wait for ``poll_culled_keyframes``."""
        c = self.cfg
        culled = cull_around(self.map, kf, c.local_map_keyframes, c.keyframe_cull_ratio, c.keyframe_cull_observers)
        if culled:
            self._culled += [(k.kf_id, k.heir_id, k.T_wc) for k in culled]
            self._local_kfs = [k for k in self._local_kfs if k in self.map.keyframes]
            self.keyframes_culled += len(culled)
            self._link.keyframes_removed([k.kf_id for k in culled], self.segment_id)

    def _cap_keyframes(self, newest_id: int) -> None:
        """Keep at most ``cfg.max_keyframes``, never one of the local map or the newest BA window."""
        if 0 < self.cfg.max_keyframes < len(self.map.keyframes):
            window = sorted(self.map.keyframes)[-self.cfg.ba_window:]
            protected = {*self._local_kfs, *window, newest_id, self._last_kf_id, self._ref_kf_id}
            self.map.cap_keyframes(self.cfg.max_keyframes, protected)

    def _finish_keyframe(self, kf: SparseKeyframe) -> KeyframeInfo:
        """Make ``kf`` the reference keyframe and hand it to the back-end (BA, place recognition)."""
        self._last_kf_id = self._ref_kf_id = kf.keyframe_id
        self._frames_since_kf = 0
        self._keyframe_deferrals = 0
        if kf.keyframe_id not in self._local_kfs:
            self._local_kfs.append(kf.keyframe_id)
        self._follow(self._link.keyframe_added(self.map, kf, self.segment_id))
        info = keyframe_info(self.map, kf)  # inline (acknowledged replay) back-end: the refined pose already
        self._last_kf_info = info
        return info

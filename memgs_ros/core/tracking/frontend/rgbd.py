"""RGB-D tracker: map points straight from measured depth at keypoints."""
from __future__ import annotations

import numpy as np

from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking.config import KeyframeInfo, TrackingState
from memgs_ros.core.tracking.features.features import FrameFeatures
from memgs_ros.core.tracking.frontend.feature_tracker import FeatureTracker
from memgs_ros.core.tracking.frontend.local_map import SparseKeyframe, SparseMap

_MIN_INIT_POINTS = 100  # keypoints with depth needed to start a map
_CLOSE_TRACKED = 100  # ORB-SLAM: insert a keyframe when few close points are tracked (and many
# close keypoints could become points: keyframe_min_new_points)


class RGBDTracker(FeatureTracker):
    """Frame-to-local-map ORB tracking with depth; see FeatureTracker for the per-frame steps."""

    uses_depth = True
    # With depth a keyframe does not need the previous window refined first (the wait was for
    # the monocular scale): a keyframe due while a local BA runs is deferred, not waited for.
    keyframe_waits_for_ba = False

    def _initialise(self, frame: Frame, feats: FrameFeatures
                    ) -> tuple[np.ndarray | None, KeyframeInfo | None, int, int]:
        T_cw = np.eye(4) if self._last_good_T_cw is None else self._last_good_T_cw
        info = self._start_map(frame, feats, T_cw)
        if info is None:
            return None, None, 0, 0
        n = int(info.keypoint_active.sum())
        return T_cw, info, n, n

    def _start_map(self, frame: Frame, feats: FrameFeatures, T_cw: np.ndarray) -> KeyframeInfo | None:
        if int(np.isfinite(feats.depth_m).sum()) < _MIN_INIT_POINTS:
            return None
        kf = self._make_keyframe(frame, feats, T_cw)
        self._create_points(kf, frame)
        self.state = TrackingState.OK
        self._T_cw_last = T_cw.copy()
        self._last_good_T_cw = T_cw.copy()
        self.motion.reset()
        self._lost_frames = 0
        self._local_kfs = [kf.keyframe_id]
        return self._finish_keyframe(kf)

    def _create_points(self, kf: SparseKeyframe, frame: Frame) -> None:
        f = kf.feats
        new = np.flatnonzero((kf.point_ids < 0) & np.isfinite(f.depth_m))
        if len(new) == 0:
            return
        p_c = self.camera.backproject(f.uv[new, 0], f.uv[new, 1], f.depth_m[new])
        T_wc = invert_pose(kf.T_cw)
        p_w = p_c @ T_wc[:3, :3].T + T_wc[:3, 3]
        self.map.add_points(p_w, f.desc[new], f.octave[new], kf.keyframe_id, new)

    def _need_close_points(self, feats: FrameFeatures, kp_idx: np.ndarray) -> bool:
        with_depth = np.isfinite(feats.depth_m)
        tracked = np.zeros(len(feats), dtype=bool)
        tracked[kp_idx] = True
        return (int((tracked & with_depth).sum()) < _CLOSE_TRACKED
                and int((~tracked & with_depth).sum()) > self.cfg.keyframe_min_new_points)

    def _min_point_obs(self) -> int:
        return 2

    def _lost_timeout(self, frame: Frame, feats: FrameFeatures) -> np.ndarray | None:
        """New segment: a fresh map anchored at the last good pose."""
        anchor = self._last_good_T_cw if self._last_good_T_cw is not None else np.eye(4)
        old_map = self.map
        self.map = SparseMap(old_map.next_keyframe_id)
        self.segment_id += 1
        info = self._start_map(frame, feats, anchor)
        if info is None:
            self.map = old_map
            self.segment_id -= 1
            return None
        return anchor.copy()

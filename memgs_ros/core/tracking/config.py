"""Tracker configuration and the records the tracker hands out (no algorithm here)."""
from __future__ import annotations

import enum
from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np

from memgs_ros.errors import ConfigError

MODES = ("rgbd", "mono")


class TrackingState(enum.Enum):
    """Where the tracker stands after a frame.

    NOT_INITIALIZED: no map yet (monocular before two-view initialisation, or no depth yet).
    OK: pose estimated from enough inliers against the local map.
    RECENTLY_LOST: too few inliers; the pose is the constant-velocity prediction (a few frames at most).
    LOST: no pose (``TrackResult.T_wc`` is None) until relocalisation or a new segment.
    """

    NOT_INITIALIZED = "not_initialized"
    OK = "ok"
    RECENTLY_LOST = "recently_lost"
    LOST = "lost"


@dataclass(frozen=True)
class TrackerConfig:
    """Every knob of the feature tracker; defaults suit 640x480 TUM-like RGB-D at 30 Hz.

    Pixel thresholds are at pyramid level 0 and grow with ``scale_factor ** octave``.
    """

    mode: str = "rgbd"
    # ORB extraction (ORB-SLAM defaults).
    n_features: int = 1000
    scale_factor: float = 1.2
    n_levels: int = 8
    fast_threshold: int = 20
    fast_min_threshold: int = 7
    grid_cell_px: int = 40  # detection is spread over cells of this size
    # Depth accepted at keypoints (RGB-D), metres.
    min_depth_m: float = 0.1
    max_depth_m: float = 6.0
    # Virtual stereo baseline times fx (pixels * m): turns depth into a disparity residual, as
    # ORB-SLAM does for RGB-D, so depth and reprojection errors share pixel units.
    virtual_baseline_m: float = 0.08
    # Use the current frame's depth in per-frame pose refinement (map points always use depth).
    track_with_depth: bool = True
    # Rolling shutter: seconds from the first to the last image row of the colour camera (0 = global
    # shutter, e.g. rendered images; negative: the rows are read bottom to top, as a sensor mounted
    # upside down reads them). Keypoints are moved to the centre row's time with the
    # tracker's angular velocity. The Kinect v1 of TUM RGB-D rolls over about 25 ms (config/tum_*.yaml).
    rolling_shutter_readout_s: float = 0.0
    # Rolling shutter direction: checked on fast-turning frames; the correction flips when the frames
    # read their rows the other way than the sign above says (a recording played backward, an image
    # rotated by its driver; frontend/readout.py).
    rolling_shutter_auto_direction: bool = True
    # Matching.
    search_radius_px: float = 15.0  # first projection pass around the velocity-predicted pose
    refine_radius_px: float = 4.0  # second pass around the optimised pose
    max_descriptor_distance: int = 80  # Hamming, of 256 bits
    match_ratio: float = 0.85  # best / second-best among candidates of one map point
    # Pose estimation.
    # The frame path's inlier bound at level 0, px: 2.45 is chi2(2) 95 % (5.991) and chi2(3) 95 % (7.815)
    # for a depth residual; another value scales both by (value / 2.45)^2 (``chi2_scale``)
    max_reprojection_px: float = 2.45
    min_inliers: int = 25  # fewer -> tracking failure for this frame
    ransac_iterations: int = 100
    ransac_reprojection_px: float = 4.0
    max_translation_jump_m: float = 0.25  # per-frame deviation from the velocity prediction
    max_rotation_jump_deg: float = 20.0
    # Keyframes.
    # The reference keyframe is the one sharing the most tracked points with the frame (ORB-SLAM's),
    # not the last inserted: on a revisit it is the keyframe already there.
    keyframe_tracked_ratio: float = 0.75  # insert when tracked points fall below this of the reference KF's
    keyframe_min_new_points: int = 70  # ... or (RGB-D) few close points tracked and more than this many untracked
    keyframe_max_frames: int = 20  # a keyframe at least every this many frames, where the map needs one
    keyframe_min_frames: int = 1
    keyframe_max_rotation_deg: float = 15.0  # ... or this far from the last keyframe
    keyframe_max_translation_m: float = 0.15
    # ... unless a settled keyframe of the local map (taken at least keyframe_cover_age_s before)
    # already sees from within these: a place flown again adds no keyframe for time or motion
    # (0: never covered) ...
    keyframe_cover_deg: float = 15.0
    keyframe_cover_m: float = 0.15
    # ... nor, from within these, for weak tracking (tracked ratio, close points)
    keyframe_weak_cover_deg: float = 7.5
    keyframe_weak_cover_m: float = 0.075
    keyframe_cover_age_s: float = 6.0
    # Keyframe culling (ORB-SLAM's): after each insertion, a covisible keyframe whose good points are
    # at least this fraction seen by keyframe_cull_observers other keyframes is removed (0: never).
    # Its points and loop-closure entry go with it; the mapper is told (poll_culled_keyframes).
    keyframe_cull_ratio: float = 0.9
    keyframe_cull_observers: int = 3
    # A live frame never waits for a BA: an RGB-D keyframe due while the previous local BA runs is
    # deferred, for at most this many frames; then it goes in without that result.
    keyframe_max_deferred_frames: int = 1  # RGB-D: frames a due keyframe is deferred for a running local BA
    # Local map and local bundle adjustment.
    local_map_keyframes: int = 10  # covisible keyframes whose points form the local map
    ba_window: int = 7  # keyframes optimised per local BA (oldest of them fixed)
    ba_max_iterations: int = 10
    ba_huber_px: float = 2.45
    # RGB-D: a local BA that moves its newest keyframe farther than this fraction of the keyframe's
    # median point depth is not committed (0: always committed; monocular BAs always are: a young
    # monocular map legitimately moves a lot). A keyframe inserted on a weakly tracked
    # frame shares few points with the map; a BA can then slide it centimetres off while lowering
    # its cost, and the next frames track onto its new points at that error (fr1/rpy head, +-1
    # grey level of noise on the frames, 11 draws: one run had 8 cm frames and 1.89 cm ATE; with
    # 0.012 the worst was 1.36 cm, the median unchanged). Committed moves there stay under 0.009.
    ba_max_shift_ratio: float = 0.012
    ba_enabled: bool = True
    ba_threaded: bool = True
    point_min_found_ratio: float = 0.25  # cull points found in fewer than this of frames that saw them
    # Keyframes kept in the sparse map (0 = all). Over it the most redundant one (nearest pose to
    # another, outside the local map) is removed and points no keyframe sees are dropped, so
    # memory stays flat on long flights; relocalisation then searches the kept keyframes.
    max_keyframes: int = 200
    # Loss handling.
    max_recently_lost_frames: int = 3
    reloc_min_inliers: int = 50
    reloc_max_keyframes: int = 30
    new_segment_after_lost_frames: int = 30  # RGB-D: start a new map anchored at the last good pose
    # Place recognition (the shipped ORB vocabulary; relocalisation asks it too) and loop closure
    # (RGB-D only): consistent candidates outside the local map, PnP RANSAC verification, then a
    # pose graph on the tracking back-end (an actor); corrected keyframes go out as refined poses.
    loop_closure: bool = True
    loop_min_keyframe_gap: int = 20  # loop candidates are at least this many keyframes older than the query
    loop_consistency: int = 3  # consecutive keyframes whose candidates must agree (ORB-SLAM: 3)
    loop_min_inliers: int = 40  # PnP RANSAC and refinement inliers needed to accept a loop
    loop_covisibility_edge_points: int = 50  # shared points that make a covisibility edge of the pose graph
    loop_cooldown_keyframes: int = 10  # no new loop search for this many keyframes after a correction
    # Global BA after each loop correction (on the back-end, one iteration at a time): every keyframe but
    # the first and every point seen twice, stopped after the iterations or the time budget.
    loop_global_ba: bool = True
    loop_global_ba_iterations: int = 10
    loop_global_ba_budget_s: float = 2.0
    loop_global_ba_followup_keyframes: int = 5  # one more global BA this many keyframes after (0: none)
    # Monocular initialisation.
    mono_min_init_matches: int = 100
    mono_min_parallax_deg: float = 2.0  # median ray angle of the two-view reconstruction
    mono_keyframe_tracked_ratio: float = 0.75  # ORB-SLAM uses 0.9; 0.75 drifted less on the synthetic room
    mono_min_triangulated: int = 50
    mono_homography_ratio: float = 0.45  # choose the homography when S_H / (S_H + S_E) exceeds this
    # A frame waits for the local BA in flight once it has run this long, in frames (0: never):
    # bounded staleness of the map the frame tracks on. At 30 Hz a 60 ms BA lands within 2 frames.
    mono_ba_max_frames_behind: int = 2

    # Ranges a user can reason about, checked before a run starts and by the node at start.
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "n_features": (50, 20_000), "scale_factor": (1.01, 2.0), "n_levels": (1, 16), "fast_threshold": (1, 255),
        "fast_min_threshold": (1, 255), "grid_cell_px": (8, 1024), "min_depth_m": (0.0, 100.0),
        "max_depth_m": (0.01, 1000.0), "virtual_baseline_m": (0.001, 10.0), "rolling_shutter_readout_s": (-1.0, 1.0),
        "search_radius_px": (1.0, 500.0), "refine_radius_px": (0.5, 500.0), "max_descriptor_distance": (1, 256),
        "match_ratio": (0.1, 1.0), "max_reprojection_px": (0.1, 100.0), "min_inliers": (4, 10_000),
        "ransac_iterations": (1, 100_000), "ransac_reprojection_px": (0.1, 100.0),
        "max_translation_jump_m": (0.0, 100.0), "max_rotation_jump_deg": (0.0, 180.0),
        "keyframe_tracked_ratio": (0.0, 1.0), "keyframe_min_new_points": (0, 100_000),
        "keyframe_cover_deg": (0.0, 180.0), "keyframe_cover_m": (0.0, 100.0),
        "keyframe_weak_cover_deg": (0.0, 180.0), "keyframe_weak_cover_m": (0.0, 100.0),
        "keyframe_cover_age_s": (0.0, 1e6),
        "keyframe_cull_ratio": (0.0, 1.0), "keyframe_cull_observers": (1, 100),
        "keyframe_max_frames": (1, 100_000), "keyframe_min_frames": (0, 100_000),
        "keyframe_max_rotation_deg": (0.0, 180.0), "keyframe_max_translation_m": (0.0, 100.0),
        "keyframe_max_deferred_frames": (0, 1000),
        "local_map_keyframes": (1, 1000), "ba_window": (2, 1000), "ba_max_iterations": (0, 1000),
        "ba_huber_px": (0.1, 100.0), "ba_max_shift_ratio": (0.0, 1.0), "point_min_found_ratio": (0.0, 1.0),
        "max_keyframes": (0, 10**6),
        "max_recently_lost_frames": (0, 10_000), "reloc_min_inliers": (4, 10_000), "reloc_max_keyframes": (1, 10_000),
        "new_segment_after_lost_frames": (0, 10**6), "loop_min_keyframe_gap": (1, 10**6),
        "loop_consistency": (1, 100), "loop_min_inliers": (4, 10_000), "loop_covisibility_edge_points": (1, 10_000),
        "loop_cooldown_keyframes": (0, 10**6), "loop_global_ba_iterations": (0, 1000),
        "loop_global_ba_budget_s": (0.0, 3600.0), "loop_global_ba_followup_keyframes": (0, 10**6),
        "mono_min_init_matches": (8, 100_000), "mono_min_parallax_deg": (0.0, 90.0),
        "mono_keyframe_tracked_ratio": (0.0, 1.0), "mono_min_triangulated": (3, 100_000),
        "mono_homography_ratio": (0.0, 1.0), "mono_ba_max_frames_behind": (0, 1000),
    }
    CHOICES: ClassVar[dict[str, tuple[str, ...]]] = {"mode": MODES}

    @property
    def chi2_scale(self) -> float:
        """What ``max_reprojection_px`` does to the chi-square inlier bounds of the frame path's
        pose optimisation (1.0 at its default, exactly)."""
        return (self.max_reprojection_px / 2.45) ** 2

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"TrackerConfig.mode must be one of {MODES}, got {self.mode!r}")
        positive = ("n_features", "scale_factor", "n_levels", "grid_cell_px", "search_radius_px",
                    "refine_radius_px", "max_reprojection_px", "min_inliers", "ransac_iterations",
                    "ransac_reprojection_px", "virtual_baseline_m", "keyframe_max_frames",
                    "local_map_keyframes", "ba_window", "ba_max_iterations", "ba_huber_px",
                    "reloc_min_inliers", "max_translation_jump_m", "max_rotation_jump_deg",
                    "loop_min_keyframe_gap", "loop_consistency", "loop_min_inliers",
                    "loop_covisibility_edge_points", "loop_global_ba_iterations", "loop_global_ba_budget_s")
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in positive and not (np.isfinite(v) and v > 0):
                raise ConfigError(f"TrackerConfig.{f.name} must be positive, got {v}")
        if self.scale_factor <= 1.0:
            raise ConfigError(f"TrackerConfig.scale_factor must exceed 1, got {self.scale_factor}")
        if not 0 <= self.fast_min_threshold <= self.fast_threshold:
            raise ConfigError(
                f"TrackerConfig.fast_min_threshold ({self.fast_min_threshold}) must be in "
                f"[0, fast_threshold={self.fast_threshold}]")
        if not (np.isfinite(self.rolling_shutter_readout_s) and -1 < self.rolling_shutter_readout_s < 1):
            raise ConfigError(f"TrackerConfig.rolling_shutter_readout_s must be in (-1, 1) s, "
                              f"got {self.rolling_shutter_readout_s}")
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError(
                f"TrackerConfig depth range must satisfy 0 < min_depth_m < max_depth_m, "
                f"got {self.min_depth_m}, {self.max_depth_m}")
        if not 0 < self.match_ratio <= 1 or not 0 < self.keyframe_tracked_ratio <= 1:
            raise ConfigError("TrackerConfig.match_ratio and keyframe_tracked_ratio must be in (0, 1]")
        if not 0 <= self.max_descriptor_distance <= 256:
            raise ConfigError(
                f"TrackerConfig.max_descriptor_distance must be in [0, 256], got {self.max_descriptor_distance}")
        if self.max_keyframes != 0 and self.max_keyframes < self.local_map_keyframes + 2:
            raise ConfigError(
                f"TrackerConfig.max_keyframes must be 0 (keep all) or at least local_map_keyframes + 2 "
                f"= {self.local_map_keyframes + 2}, got {self.max_keyframes}")
        if self.ba_window < 2:
            raise ConfigError(f"TrackerConfig.ba_window must be at least 2, got {self.ba_window}")


@dataclass(frozen=True, eq=False)
class KeyframeInfo:
    """A keyframe as the mapper and Patch-Grid sampler see it.

    T_wc: [4, 4] float64 pose at insertion (later refinements come from ``poll_refined_keyframes``).
    keypoints_uv: [M, 2] float32 undistorted pixel coordinates.
    keypoint_depth: [M] float32 metres along the optical axis, NaN where there is no 3D point.
    keypoint_active: [M] bool, True where the keypoint has a map point.
    """

    keyframe_id: int
    stamp_ns: int
    T_wc: np.ndarray
    keypoints_uv: np.ndarray
    keypoint_depth: np.ndarray
    keypoint_active: np.ndarray


@dataclass(frozen=True, eq=False)
class TrackResult:
    """The tracker's answer for one frame.

    T_wc: [4, 4] float64, or None when LOST / NOT_INITIALIZED (never a guessed pose there).
    keyframe: set when this frame became a keyframe.
    segment_id: increases when the tracker gave up relocalising and started a new map; poses of
      different segments share a frame only through the anchor (the last good pose).
    reference_keyframe_id: the keyframe this pose was tracked against (the one sharing the most of
      its tracked points; the new keyframe for a keyframe frame), -1 when none: when a loop correction
      moves that keyframe, the frame's corrected pose is the keyframe's new pose times the same
      relative pose (``AnchoredPath``); when culling removes it, the frame follows the keyframe the
      tracker names instead (``poll_culled_keyframes``).
    """

    stamp_ns: int
    T_wc: np.ndarray | None
    state: TrackingState
    keyframe: KeyframeInfo | None
    n_matches: int
    n_inliers: int
    time_s: float
    segment_id: int = 0
    reference_keyframe_id: int = -1
    # [6, 6] covariance of T_wc (ROS order: x, y, z, rotation about the world's x, y, z; metres^2,
    # rad^2) from the pose optimisation's information matrix at 1 px noise; None unless OK, or
    # when the tracker was told no one reads it (``Tracker.covariance_wanted``)
    pose_cov: np.ndarray | None = None

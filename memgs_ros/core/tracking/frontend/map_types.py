"""The sparse map's records: a keyframe of the tracker (``SparseKeyframe``) and the point table
(``PointStore``); ``local_map.SparseMap`` holds them."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking.features.features import FrameFeatures

__all__ = ["PointStore", "SparseKeyframe"]


@dataclass(eq=False)
class SparseKeyframe:
    """The tracker's keyframe inside its sparse map: pose, ORB keypoints and the map point of each
    (mutable: BA refines ``T_cw``; points attach to keypoints). Not the mapper's keyframe.

    feats: its ORB features; point_ids: [M] int64 map point per keypoint, -1 where none.
    """

    keyframe_id: int
    stamp_ns: int
    T_cw: np.ndarray
    feats: FrameFeatures
    point_ids: np.ndarray
    segment_id: int = 0

    @property
    def T_wc(self) -> np.ndarray:
        return invert_pose(self.T_cw)


@dataclass(eq=False)
class PointStore:
    """Growable arrays of map point attributes (index = point id)."""

    pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    desc: np.ndarray = field(default_factory=lambda: np.zeros((0, 32), np.uint8))
    octave: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_visible: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_found: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    first_kf: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_obs: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # keyframes observing
    bad: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    size: int = 0

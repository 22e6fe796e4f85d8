"""A tracker that starts from a saved map (a map bundle's ``tracker.npz``) instead of nothing.

``load_map`` puts the saved keyframes and points in the tracker's map and their bag-of-words
vectors in both place-recognition databases (the front-end's, for relocalisation, and the
back-end's, so loops can close onto the earlier session). Until a frame relocalises against
them (bag-of-words candidates + PnP + the local map, as after a tracking loss) the tracker
gives no pose: such frames are counted in ``frames_relocalizing``, and no new world is started
(no map is initialised from them). From the first relocalised frame on, tracking, keyframes,
BA and loop closure go on in the loaded world frame.

``localize_only``: track against the map without changing it (no keyframes, so no BA, no new
points, no new segment after a long loss: a lost tracker keeps trying to relocalise).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from memgs_ros.core.tracking.config import KeyframeInfo, TrackingState
from memgs_ros.core.tracking.map_io import TrackerMap, export_map, restore_map
from memgs_ros.errors import DataError

if TYPE_CHECKING:
    from memgs_ros.core.geometry.frame import Frame
    from memgs_ros.core.tracking.features.features import FrameFeatures

__all__ = ["MapSession"]


class MapSession:
    """Mixin of ``FeatureTracker``: loading and exporting its map (see the module docstring)."""

    localize_only = False
    frames_relocalizing = 0  # frames given no pose while a loaded map waited for its first relocalisation
    relocalized_after = -1  # frames it took (-1: not yet, or no map loaded)
    loaded_until_ns = 0  # the loaded map's newest keyframe stamp
    stamps_before_map = False  # a frame stamped before it came: the same recording played again?

    def load_map(self: Any, m: TrackerMap) -> None:
        """Start from ``m`` (before the first frame). DataError when it is another camera's or mode's."""
        if self.state != TrackingState.NOT_INITIALIZED or self.map.keyframes:
            raise DataError("a map can only be loaded into a tracker that has not started")
        cam = m.camera
        if (cam.width, cam.height) != (self.camera.width, self.camera.height) or not np.allclose(
                [cam.fx, cam.fy, cam.cx, cam.cy], [self.camera.fx, self.camera.fy, self.camera.cx, self.camera.cy],
                rtol=0.01):
            raise DataError(f"the map's camera ({cam.width}x{cam.height} fx {cam.fx:.1f}) is not this tracker's "
                            f"({self.camera.width}x{self.camera.height} fx {self.camera.fx:.1f})")
        if m.header.get("mode") != self.cfg.mode:
            raise DataError(f"the map was made by a {m.header.get('mode')} tracker, this one is {self.cfg.mode}")
        smap, vectors = restore_map(m)
        have = {k for k, _ in vectors}
        if self.vocabulary is not None:  # keyframes whose vector had not come back when it was saved
            vectors += [(k, self.vocabulary.transform(kf.feats.desc)) for k, kf in smap.keyframes.items()
                        if k not in have]
        self.map, self.segment_id = smap, int(m.header.get("segment_id", 0))
        for k, bow in vectors:
            self._link.keyframe_db.add(k, bow)
        self._link.keyframes_loaded(smap)
        self.backend.load_places(vectors)
        self.state = TrackingState.LOST
        self.loaded_until_ns = max((kf.stamp_ns for kf in smap.keyframes.values()), default=0)
        self.relocalized_after = -1

    def export_map(self: Any, extra: dict[str, Any] | None = None) -> TrackerMap:
        """A copy of the map as it stands (tracking thread; milliseconds), to write elsewhere."""
        return export_map(self.map, self._link.keyframe_db, self.camera, self.cfg.mode, self.segment_id, extra)

    def _relocalise_loaded(self: Any, frame: Frame, feats: FrameFeatures
                           ) -> tuple[np.ndarray | None, KeyframeInfo | None, int, int]:
        """A frame before the first pose in a loaded map: relocalised, or counted and given no pose.
        Keyframes are keyed by stamp between tracker and mapper: a frame stamped before the map's
        newest keyframe (its recording played again) is flagged (``stamps_before_map``)."""
        self.stamps_before_map = self.stamps_before_map or frame.stamp_ns <= self.loaded_until_ns
        outcome = self._relocalise(feats)
        if outcome is None:
            self.frames_relocalizing += 1
            return None, None, 0, 0
        self.relocalized_after = self.frames_relocalizing
        self._T_cw_last = outcome.T_cw
        self.motion.reset()
        best = self.map.covisible(outcome.point_ids, 1)
        self._last_kf_id = self._ref_kf_id = best[0] if best else max(self.map.keyframes)
        return self._tracked(frame, feats, feats, outcome, 0.0, True)

"""The tracker's part of a map bundle (``ros/map_bundles.py``): ``memgs/tracker/save_map_part``, and
``map_bundle`` loaded into a new tracker."""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from std_srvs.srv import Trigger

from memgs_ros.core.maps.bundle import TRACKER_FILE, resolve_bundle
from memgs_ros.core.tracking.config import TrackingState
from memgs_ros.errors import DataError, MemgsError
from memgs_ros.ros.diagnostics import TrackerStats
from memgs_ros.ros.hand_over import HandOver
from memgs_ros.ros.map_bundles import answer, in_thread, part_path

__all__ = ["TrackerMapPart", "map_check"]


def map_check(node: Any) -> dict[str, Any]:
    """What a bundle loaded into the tracker ``node`` must match (``check_bundle``'s keywords):
    its depth unit and tracker mode, and its camera once the node has one."""
    cam = node.cams.camera if getattr(node, "cams", None) is not None else None
    return {"depth_scale": node.params.depth_scale, "tracker_mode": node.cfg.mode,
            "camera": None if cam is None else cam.as_dict()}


class TrackerMapPart:
    """The tracker's part: ``memgs/tracker/save_map_part``, and loading ``map_bundle`` into a new tracker.
    ``tracker()``: the node's tracker (None before the camera is known); ``extra()``: header fields."""

    def __init__(self, node: Node, params: Any, stats: TrackerStats, tracker: Callable[[], Any],
                 extra: Callable[[], dict[str, Any]]) -> None:
        self.params, self.stats, self._tracker, self._extra = params, stats, tracker, extra
        self._log = node.get_logger()
        self.hand_over = HandOver(node)
        node.create_service(Trigger, "memgs/tracker/save_map_part", self.on_save,
                            callback_group=ReentrantCallbackGroup())

    def load_into(self, tracker: Any) -> None:
        """Start ``tracker`` from the bundle's tracker map, in ``map_mode``. A map it cannot take
        leaves it relocalising in an empty map: no pose, and no new world started."""
        p = self.params
        tracker.localize_only = p.map_mode == "localize"
        if not p.map_bundle:
            return
        from memgs_ros.core.tracking.map_io import read_tracker_map  # numba: the tracker's, once it tracks

        try:
            m = read_tracker_map(resolve_bundle(p.map_bundle) / TRACKER_FILE)
            tracker.load_map(m)
        except DataError as err:
            tracker.state = TrackingState.LOST  # no map, no pose: nothing to relocalise in
            self.stats.problem("map_refused", f"cannot start from map bundle {p.map_bundle}: {err}")
            return
        self._log.info(f"map bundle {p.map_bundle}: {m.n_keyframes} keyframes, {m.header['points']} points loaded "
                       f"({p.map_mode}); relocalising before the first pose")

    async def on_save(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        tracker = self._tracker()
        if not self.params.bundle_dir:
            return answer(res, False, "bundle_dir is not set: no map bundle to save into")
        if tracker is None or not hasattr(tracker, "export_map"):
            return answer(res, False, "no tracker map yet (no camera or no frame)")
        from memgs_ros.core.tracking.map_io import write_tracker_map

        t0 = time.perf_counter()
        m = tracker.export_map(self._extra())  # on the tracking thread: a copy, milliseconds
        self.stats.map_part_copy_ms = round((time.perf_counter() - t0) * 1e3, 2)
        path = part_path(self.params.bundle_dir, "tracker")
        try:
            await self.hand_over.result(in_thread(lambda: write_tracker_map(m, path), "tracker-map-part"))
        except (OSError, MemgsError) as err:
            return answer(res, False, f"could not write the tracker map {path}: {err}")
        self.stats.map_parts += 1
        return answer(res, True, str(path))

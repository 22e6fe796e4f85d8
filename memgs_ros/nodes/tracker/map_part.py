"""The tracker's part of a map bundle (``ros/map_bundles.py``): ``memgs/tracker/save_map_part``, and
``map_bundle`` loaded into a new tracker."""
from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import Any

from rclpy.node import Node

from memgs_ros.core.map_io.bundle import TRACKER_FILE, resolve_bundle
from memgs_ros.errors import DataError
from memgs_ros.nodes.tracker.stats import TrackerStats
from memgs_ros.ros.hand_over import HandOver
from memgs_ros.ros.map_bundles import PartService, in_thread

__all__ = ["TrackerMapPart", "map_check"]


def map_check(node: Any) -> dict[str, Any]:
    """What a bundle loaded into the tracker ``node`` must match (``check_bundle``'s keywords):
    its depth unit and tracker mode, and its camera once the node has one."""
    cam = node.cams.camera if getattr(node, "cams", None) is not None else None
    return {"depth_scale": node.params.depth_scale, "tracker_mode": node.cfg.mode,
            "camera": None if cam is None else cam.as_dict()}


class TrackerMapPart:
    """The tracker's part: ``memgs/tracker/save_map_part`` (``PartService``: the map copied on the
    tracking thread, written beside it), and loading ``map_bundle`` into a new tracker.
    ``tracker()``: the node's tracker (None before the camera is known); ``extra()``: header fields."""

    def __init__(self, node: Node, params: Any, stats: TrackerStats, tracker: Callable[[], Any],
                 extra: Callable[[], dict[str, Any]]) -> None:
        self.params, self.stats, self._tracker, self._extra = params, stats, tracker, extra
        self._log = node.get_logger()
        self.service = PartService(node, "tracker", params.bundle_dir, HandOver(node), self._write,
                                   self._saved, "the tracker map")

    def load_into(self, tracker: Any) -> None:
        """Start ``tracker`` from ``map_bundle`` in ``map_mode`` (``map_io.load_bundle_map``)."""
        from memgs_ros.core.tracking.map_io import load_bundle_map  # numba: the tracker's, once it tracks

        p = self.params
        try:
            path = resolve_bundle(p.map_bundle) / TRACKER_FILE if p.map_bundle else None
            m = load_bundle_map(tracker, path, p.map_mode)
        except DataError as err:
            self.stats.problem("map_refused", f"cannot start from map bundle {p.map_bundle}: {err}")
            return
        if m is not None:
            self._log.info(f"map bundle {p.map_bundle}: {m.n_keyframes} keyframes, {m.header['points']} points "
                           f"loaded ({p.map_mode}); relocalising before the first pose")

    def _write(self, path: Path) -> Future[Any] | str:
        tracker = self._tracker()
        if tracker is None or not hasattr(tracker, "export_map"):
            return "no tracker map yet (no camera or no frame)"
        from memgs_ros.core.tracking.map_io import write_tracker_map

        t0 = time.perf_counter()
        m = tracker.export_map(self._extra())  # on the tracking thread: a copy, milliseconds
        self.stats.map_part_copy_ms = round((time.perf_counter() - t0) * 1e3, 2)
        return in_thread(lambda: write_tracker_map(m, path), "tracker-map-part")

    def _saved(self) -> None:
        self.stats.map_parts += 1

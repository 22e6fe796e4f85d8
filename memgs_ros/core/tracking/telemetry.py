"""The tracker's figures in its telemetry record (``TrackerTelemetry``, written through the
generated ``TrackerFields``): what the node reports per tracked frame, without ROS."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

from memgs_ros.core.runtime.telemetry_fields import TrackerFields

__all__ = ["track_stats"]


def track_stats(stats: TrackerFields, tracker: Any, dt_s: float, keyframe: bool,  # noqa: ANN401 - any Tracker
                problem: Callable[[str, str], None]) -> Any | None:  # noqa: ANN401 - its SparseMapStats
    """A tracked frame's cost (``dt_s``: the front end alone) and the tracker's gauges into ``stats``;
    on a keyframe the sparse map's size too, whose stats it returns (else None). ``problem(kind,
    message)``: counts and warns once per kind (the node's ``NodeStats.problem``)."""
    stats.track_ms = round(dt_s * 1e3, 2)
    stats.keyframes_deferred = int(getattr(tracker, "keyframes_deferred", 0))
    stats.ba_waits, stats.ba_refused = int(getattr(tracker, "ba_waits", 0)), int(getattr(tracker, "ba_refused", 0))
    if getattr(tracker, "stamps_before_map", False):
        problem("map_stamps", "frames stamped before the loaded map's newest keyframe (the same recording "
                              "played again?): their keyframes may collide with the map's, keyed by stamp")
    # A loaded map (map_bundle): frames given no pose before the first relocalisation in it.
    stats.relocalizing = int(getattr(tracker, "frames_relocalizing", 0))
    stats.relocalized_after = int(getattr(tracker, "relocalized_after", 0))
    if (ro := getattr(tracker, "readout", None)) is not None:
        stats.readout_flips, stats.readout_sign = ro.flips, ro.sign  # the rows' direction as checked
    stats.track_us_total += int(dt_s * 1e6)
    smap = tracker.map_stats() if keyframe else None
    if smap is not None:
        stats.map_keyframes, stats.map_points = smap.keyframes, smap.points
        stats.map_keyframes_removed, stats.map_keyframes_culled = smap.keyframes_removed, smap.keyframes_culled
    return smap

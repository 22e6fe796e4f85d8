"""The tracker's figures in its telemetry record (``TrackerTelemetry``, written through the
generated ``TrackerFields``): what the node reports per tracked frame, without ROS."""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from memgs_ros.core.runtime.telemetry_fields import TrackerFields

__all__ = ["state_stats", "timed_track", "track_stats"]


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


def state_stats(stats: TrackerFields, name: str, segment_id: int) -> bool:
    """A frame's tracking state ``name`` (and map segment) into ``stats``: ``state.<STATE>``,
    ``tracking_state``, ``segment``, and ``resets`` when tracking came back or a new segment began
    (poses may jump). True when the frame lost tracking or regained it: worth reporting at once."""
    stats.state[name] += 1
    previous = stats.tracking_state or None  # None: the first frame (segment is set with it)
    stats.tracking_state = name
    if previous is not None and (segment_id != stats.segment or (previous == "LOST" and name == "OK")):
        stats.resets += 1
    stats.segment = segment_id
    return previous is not None and (name == "LOST") != (previous == "LOST")


def timed_track(stats: TrackerFields, tracker: Any, frame: Any, inline_ba: bool,  # noqa: ANN401 - any Tracker
                problem: Callable[[str, str], None]) -> tuple[Any, Any | None]:  # noqa: ANN401
    """``tracker.track(frame)`` with its cost in ``stats``: the front end alone (with ``inline_ba``,
    as in acknowledged replays, the local BA run inside it is back-end work, counted beside it as
    ``ba_us_total``) and the tracker's gauges (``track_stats``). (result, the sparse map's stats
    on a keyframe, else None)."""
    ba_before, t0 = tracker.ba_time_s, time.perf_counter()
    result = tracker.track(frame)
    dt = time.perf_counter() - t0
    if inline_ba:
        ba_dt = tracker.ba_time_s - ba_before
        dt -= ba_dt
        stats.ba_us_total += int(ba_dt * 1e6)
    return result, track_stats(stats, tracker, dt, result.keyframe is not None, problem)

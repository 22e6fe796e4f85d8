"""The tracker's stats (``memgs/tracker/stats``): ``NodeStats`` written through ``TrackerFields``."""
from __future__ import annotations

from memgs_ros.core.runtime.telemetry_fields import TrackerFields
from memgs_ros.ros.diagnostics import NodeStats

__all__ = ["TrackerStats"]


class TrackerStats(NodeStats, TrackerFields):
    stats_name = "tracker"

"""The merger's stats (``memgs/merger/stats``): ``NodeStats`` written through ``MergerFields``."""
from __future__ import annotations

from typing import Any

from memgs_ros.core.runtime.telemetry_fields import MergerFields
from memgs_ros.ros.diagnostics import NodeStats

__all__ = ["MergerStats"]


class MergerStats(NodeStats, MergerFields):
    stats_name = "merger"

    def replica(self, replica: Any, resyncing: bool, buffered: int, render_cache_bytes: int) -> None:  # noqa: ANN401
        """The replica's rows, deltas buffered in a resync, the last view's render inputs (no training state)."""
        self.seq, self.epoch, self.gaussians, self.resyncing = replica.seq, replica.epoch, len(replica), int(resyncing)
        self.unknown_removals, self.map_bytes = replica.unknown_removals, replica.records.nbytes if len(replica) else 0
        self.buffered_deltas, self.render_cache_bytes = buffered, render_cache_bytes

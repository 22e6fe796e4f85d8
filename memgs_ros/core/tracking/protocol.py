"""What the tracker node needs from a tracker: one explicit interface.

Every tracker (the RGB-D and the monocular feature tracker) subclasses
:class:`Tracker`, so a missing method is an error at construction (abstract) rather than an
``AttributeError`` in the middle of a run, and the node never probes with ``getattr``.
"""
from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    import numpy as np

    from memgs_ros.core.geometry.frame import Frame
    from memgs_ros.core.tracking.config import TrackResult


@dataclass(frozen=True)
class SparseMapStats:
    """A snapshot of a backend's sparse map, for diagnostics and bookkeeping.

    keyframe_ids: the keyframes the map still holds (bounded maps remove old ones; only
    these can still be refined by BA). points: good map points. keyframes_removed: in total.
    """

    keyframe_ids: frozenset[int]
    points: int
    keyframes_removed: int
    keyframes_culled: int = 0  # of those, culled as redundant (the rest: over max_keyframes)

    @property
    def keyframes(self) -> int:
        return len(self.keyframe_ids)


@runtime_checkable
class Tracker(Protocol):
    """A tracking backend.

    ba_time_s: seconds spent in local bundle adjustment so far, inline or threaded; 0.0 for a
    backend that does its own BA out of sight. The node subtracts inline BA from front-end time.
    covariance_wanted: whether tracked frames carry ``pose_cov`` (default True).
    """

    ba_time_s: float
    # False: tracked frames' TrackResult.pose_cov stays None (the node sets it from its odometry
    # subscribers: no one fusing the odometry, no covariance to compute, ~0.25 ms a frame).
    covariance_wanted: bool = True

    @abstractmethod
    def track(self, frame: Frame) -> TrackResult:
        """Estimate the pose of ``frame``."""

    @abstractmethod
    def poll_refined_keyframes(self) -> list[tuple[int, np.ndarray]]:
        """(keyframe_id, refined T_wc [4, 4]) since the last poll, oldest first."""

    def poll_culled_keyframes(self) -> list[tuple[int, int, np.ndarray]]:
        """(culled keyframe id, heir keyframe id, last T_wc [4, 4]) of the keyframes culling removed
        since the last poll; a backend that culls none has none."""
        return []

    def poll_loop_corrected_keyframes(self) -> list[tuple[int, np.ndarray]]:
        """(keyframe_id, corrected T_wc [4, 4]) of keyframes a loop closure moved since the last
        poll; a backend without loop closure has none."""
        return []

    def poll_loop_corrections(self) -> list[dict[int, np.ndarray]]:
        """Loop corrections committed since the last poll ({keyframe_id: D [4, 4]}, world frame);
        a backend without loop closure has none."""
        return []

    def end_flight(self) -> TrackResult | None:
        """At the end of a flight (the source's end): the last tracked frame as a keyframe when no
        keyframe sees its view yet, else None; a backend without keyframes of its own has none."""
        return None

    @abstractmethod
    def map_stats(self) -> SparseMapStats | None:
        """The sparse map's stats, or None for a backend that exposes no map."""

    @abstractmethod
    def close(self) -> None:
        """Release threads and native resources (idempotent)."""

    def __enter__(self) -> Tracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["SparseMapStats", "Tracker"]

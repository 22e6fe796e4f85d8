"""What a mapping session hands out (``session.MappingSession``): immutable records its callers
read on any thread, a problem the worker met, a render, a batch of deltas sent, the finish, and
the session's status."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.mapper_service.keyframe_timing import KeyframeTimingSummary
from memgs_ros.core.runtime.stat_fields import StatValues
from memgs_ros.core.runtime.telemetry_fields import MapperFields

__all__ = ["DeltaBatch", "FinishResult", "RenderedView", "SessionEvent", "SessionStatus"]


@dataclass(frozen=True)
class SessionEvent:
    """A problem the worker met: ``kind`` is the counter name (e.g. ``bad_keyframe``)."""

    kind: str
    message: str


@dataclass(frozen=True, eq=False)
class RenderedView:
    """A render of the map: rgb [h, w, 3] uint8, depth [h, w] float32 metres, the camera used."""

    rgb: np.ndarray
    depth: np.ndarray
    camera: PinholeCamera


@dataclass(frozen=True)
class DeltaBatch:
    """How many delta messages were sent (each handed to ``publish``), the sequence number after
    them, the outbox's epoch and the rows over tolerance still held back by the row limit. The rows
    themselves are not kept: a caller holding the future would hold megabytes after a final flush."""

    messages: int
    seq: int
    epoch: int
    pending_rows: int


@dataclass(frozen=True)
class FinishResult:
    epoch: int
    gaussians: int
    final_iterations: int
    seconds: float


@dataclass(frozen=True)
class SessionStatus:
    """What the session looks like after its latest command or step (immutable; replaced whole)."""

    iteration: int = 0
    gaussians: int = 0
    keyframes: int = 0  # inserted since start (resumed ones included)
    keyframes_trained: int = 0
    keyframes_dropped: int = 0  # by max_keyframes
    budget_gaussians: int = 0
    model_bytes: int = 0
    model_bytes_peak: int = 0
    keyframe_bytes: int = 0  # the stored training keyframes' tensors
    accounted_bytes: int = 0  # model + keyframes + step buffers (GaussianMapper.memory_account)
    accounted_bytes_peak: int = 0
    gaussians_peak: int = 0
    loss: float | None = None
    cuda_max_allocated: int | None = None
    insert_queue: int = 0
    delta_seq: int = 0
    delta_pending_rows: int = 0
    finished: bool = False
    alive: bool = True  # the worker and the outbox run commands (False once closed or dead)
    render_camera: PinholeCamera | None = None
    counters: Mapping[str, int] = field(default_factory=dict)
    keyframe_timing: KeyframeTimingSummary = field(default_factory=KeyframeTimingSummary)
    cuda_peak_by_work: Mapping[str, int] = field(default_factory=dict)  # PeakAttribution.by_work (CUDA)
    iterations_final: int = 0  # run by ``finish`` (the rest ran while keyframes arrived)

    def gauges(self) -> dict[str, int | float]:
        """The values a node reports as gauges (the counters are reported as counters); the map's
        figures once training has begun, so a time series of them starts at the first step."""
        g = SessionCounts()
        g.insert_queue, g.seq, g.delta_pending_rows, g.alive = (self.insert_queue, self.delta_seq,
                                                                self.delta_pending_rows, int(self.alive))
        if self.iteration > 0:
            g.iteration, g.gaussians, g.gaussians_peak = self.iteration, self.gaussians, self.gaussians_peak
            g.model_bytes, g.model_bytes_peak = self.model_bytes, self.model_bytes_peak
            g.keyframes_trained, g.keyframes_dropped = self.keyframes_trained, self.keyframes_dropped
            g.budget_gaussians, g.keyframe_bytes = self.budget_gaussians, self.keyframe_bytes
            g.accounted_bytes, g.accounted_bytes_peak = self.accounted_bytes, self.accounted_bytes_peak
        if self.loss is not None:
            g.loss = self.loss
        if self.cuda_max_allocated is not None:
            g.cuda_max_allocated = self.cuda_max_allocated
        for work, peak in self.cuda_peak_by_work.items():
            g.cuda_peak_mb[work] = round(peak / 2**20, 1)
        t = self.keyframe_timing
        g.keyframes_used, g.keyframes_waiting, g.iterations_final = t.used, t.waiting, self.iterations_final
        if t.intake_ms_median is not None:
            g.keyframe_intake_ms_median = t.intake_ms_median
        if t.intake_ms_p95 is not None:
            g.keyframe_intake_ms_p95 = t.intake_ms_p95
        if t.latency_ms_median is not None:
            g.keyframe_latency_ms_median = t.latency_ms_median
        if t.latency_ms_p95 is not None:
            g.keyframe_latency_ms_p95 = t.latency_ms_p95
        return g.values


class SessionCounts(MapperFields, StatValues):
    """The mapping session's figures by the mapper record's names (``MapperTelemetry``), which the
    node's stats take whole (``NodeStats.assign``)."""

    def with_map(self, merge_passes: int, seeds_covered: int) -> dict[str, Any]:
        """These counters and the map's own totals, for a status."""
        out = SessionCounts.of(self.values)
        out.merge_passes, out.seeds_covered = merge_passes, seeds_covered
        return out.values

    @staticmethod
    def with_outbox(counters: Mapping[str, Any], messages: int, nbytes: int, snapshots: int) -> dict[str, Any]:
        """``counters`` and the delta outbox's totals."""
        out = SessionCounts.of(counters)
        out.delta_messages, out.delta_bytes, out.snapshots = messages, nbytes, snapshots
        return out.values

"""What a mapping session hands out (``session.MappingSession``): immutable records its callers
read on any thread, a problem the worker met, a render, a batch of deltas sent, the finish, and
the session's status."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.mapping.keyframe_timing import KeyframeTimingSummary

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
        out: dict[str, int | float] = {"insert_queue": self.insert_queue, "seq": self.delta_seq,
                                       "delta_pending_rows": self.delta_pending_rows, "alive": int(self.alive)}
        if self.iteration > 0:
            out.update(iteration=self.iteration, gaussians=self.gaussians, model_bytes=self.model_bytes,
                       model_bytes_peak=self.model_bytes_peak, gaussians_peak=self.gaussians_peak,
                       keyframes_trained=self.keyframes_trained, keyframes_dropped=self.keyframes_dropped,
                       budget_gaussians=self.budget_gaussians, keyframe_bytes=self.keyframe_bytes,
                       accounted_bytes=self.accounted_bytes, accounted_bytes_peak=self.accounted_bytes_peak)
        if self.loss is not None:
            out["loss"] = self.loss
        if self.cuda_max_allocated is not None:
            out["cuda_max_allocated"] = self.cuda_max_allocated
        for work, peak in self.cuda_peak_by_work.items():
            out[f"cuda_peak_mb.{work}"] = round(peak / 2**20, 1)
        t = self.keyframe_timing
        out.update(keyframes_used=t.used, keyframes_waiting=t.waiting, iterations_final=self.iterations_final)
        for name in ("intake_ms_median", "intake_ms_p95", "latency_ms_median", "latency_ms_p95"):
            value = getattr(t, name)
            if value is not None:
                out[f"keyframe_{name}"] = value
        return out

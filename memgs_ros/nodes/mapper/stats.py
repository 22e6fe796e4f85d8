"""The mapper's stats (``memgs/mapper/stats``): the node's counters and gauges plus what its
mapping session reports (status, problems), the training rate, the kernels' warm-up and the
working memory above the start-up baseline."""
from __future__ import annotations

import time
from concurrent.futures import Future
from typing import Any, TypeVar

from rclpy.node import Node

from memgs_ros.core.mapper_service.mapper_start import warm_kernels
from memgs_ros.core.mapper_service.reporting import IterationRate, report_failure, reportable_error
from memgs_ros.core.mapper_service.session import MappingSession
from memgs_ros.core.mapping.config import MappingConfig
from memgs_ros.core.runtime.telemetry_fields import MapperFields
from memgs_ros.ros.diagnostics import NodeStats, RollingMedian, peak_rss_mb, rss_mb
from memgs_ros.ros.stamp_sync import KeyframeIntake

__all__ = ["MapperStats"]

T = TypeVar("T")


class MapperStats(NodeStats, MapperFields):
    """``NodeStats`` of the mapper: gauges ``raster_backend``, ``checkpoint_period_s`` (0: this
    mapper never checkpoints; fault injection waits for a checkpoint to resume from) and
    ``kernels_warm``; ``frame_ack_ms_median`` over ``ack_ms``."""

    def __init__(self, node: Node, raster_backend: str, checkpoint_period_s: float) -> None:
        # Free heap pages go back every 2 s (each trim ~5 ms): training leaves ~30-50 MB of
        # freed step buffers a step, and at the default 30 s they piled up into the peak RSS.
        super().__init__(node, "mapper", trim_period_s=2.0)
        self.raster_backend, self.checkpoint_period_s, self.kernels_warm = raster_backend, checkpoint_period_s, 0
        self.ack_ms = RollingMedian()  # an acknowledged frame's time here: the tracker's word to the acknowledgement
        self.compute(MapperStats.frame_ack_ms_median, self.ack_ms)
        self._rate = IterationRate(time.monotonic())
        self._rss_baseline_mb: float | None = None  # set by the warm-up, on the session's worker

    def watch(self, future: Future[T], command: str) -> Future[T]:
        """A session command nobody waits on: its error is counted (``problem.command_failed``)."""
        future.add_done_callback(report_failure(self, command))
        return future

    def warm_up(self, session: MappingSession, device: str, cfg: MappingConfig) -> None:
        """Queue the kernels' loading (on a fresh install: compiling) as the session's first command,
        then the memory baseline (imports, node, session and kernels; the working memory is above
        it); ``kernels_warm`` says when they are in. A failed warm-up is counted and the run goes on
        (a training step will meet the same error and report it) rather than wait."""
        t0 = time.perf_counter()

        def warm(_mapper: object) -> None:  # on the session's worker
            warm_kernels(device, cfg)
            self._rss_baseline_mb = rss_mb()
            self.post_set(MapperStats.rss_baseline_mb, round(self._rss_baseline_mb, 1))
            self.post_set(MapperStats.warm_up_s, round(time.perf_counter() - t0, 2))
            self.post_set(MapperStats.kernels_warm, 1)

        def failed(future: Future[Any]) -> None:
            err = reportable_error(future)
            if err is not None:
                self.post_problem("warm_up", f"could not load the mapping kernels: {type(err).__name__}: {err}")
                self.post_set(MapperStats.kernels_warm, 1)

        session.call(warm).add_done_callback(failed)

    def sync(self, session: MappingSession, intake: KeyframeIntake) -> None:
        """Session problems and status, and lost keyframes, into the stats; also applies what other
        threads posted (the node's default callback group, 10 times a second)."""
        self.apply_posted()
        self.keyframes_missed += intake.missed(time.monotonic())
        for ev in session.poll_events():
            self.problem(ev.kind, ev.message)
        st = session.status
        self.assign(st.counters)  # assigned, not added: totals
        self.assign(st.gauges())
        rate = self._rate.update(time.monotonic(), st.iteration)  # over the last sync period
        if rate is not None:
            self.iterations_per_s = rate
        # Peak resident memory above the start-up baseline (VmHWM, read 10 times a second).
        if self._rss_baseline_mb is not None:
            self.working_peak_mb = round(max(peak_rss_mb() - self._rss_baseline_mb, 0.0), 1)

"""What each keyframe cost the mapper to take in, and how long it waited to be trained on.

Per keyframe the mapping session records its intake CPU time (decoding the messages, preparing
the training view, uploading it, inserting it into the map and seeding its Gaussians) and, at the
first training step that draws it, the latency from the tracker's decision (the wall-clock time
the tracker published it) to that step. A keyframe the mapper never trains on stays counted in
``waiting``: a live map that falls behind shows there.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np

__all__ = ["KeyframeTimingSummary", "KeyframeTimings"]


def _percentiles(values: deque[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    a = np.fromiter(values, dtype=np.float64)
    return round(float(np.median(a)), 2), round(float(np.percentile(a, 95)), 2)


@dataclass(frozen=True)
class KeyframeTimingSummary:
    """Medians and 95th percentiles over the last ``window`` keyframes (None before any)."""

    intake_ms_median: float | None = None
    intake_ms_p95: float | None = None
    latency_ms_median: float | None = None
    latency_ms_p95: float | None = None
    used: int = 0  # keyframes drawn by at least one training step
    waiting: int = 0  # inserted keyframes no step has drawn yet


class KeyframeTimings:
    """Intake CPU and decision-to-training latency per keyframe (one owner: the session's worker)."""

    def __init__(self, window: int = 1024) -> None:
        self._intake_ms: deque[float] = deque(maxlen=window)
        self._latency_ms: deque[float] = deque(maxlen=window)
        self._waiting: dict[int, int] = {}  # kf_id -> the tracker's decision (wall clock, ns; 0 unknown)
        self._used = 0

    def inserted(self, kf_id: int, decided_ns: int, intake_ms: float) -> None:
        self._intake_ms.append(float(intake_ms))
        self._waiting[int(kf_id)] = int(decided_ns)

    def trained(self, kf_id: int, now_ns: int | None = None) -> None:
        """A training step drew ``kf_id``: its first draw ends its wait."""
        decided = self._waiting.pop(int(kf_id), None)
        if decided is None:
            return
        self._used += 1
        if decided > 0:
            now = time.time_ns() if now_ns is None else now_ns
            self._latency_ms.append(max(now - decided, 0) / 1e6)

    def summary(self) -> KeyframeTimingSummary:
        intake = _percentiles(self._intake_ms)
        latency = _percentiles(self._latency_ms)
        return KeyframeTimingSummary(*intake, *latency, used=self._used, waiting=len(self._waiting))

"""A run's stats timeline (``stats_timeline.jsonl``: every node's 1 Hz stats, one JSON row each)
read back for the evaluation: the mapper's map size and memory over the run, its training rate,
and each node's peak resident memory. No ROS; rows that lack a value are skipped, not guessed."""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["MapSample", "finite_number", "map_samples", "mapper_gauge_max", "node_peak_rss_mb", "training_rate"]

_TIMELINE_NODE_NAMES = {"player": "bag_player"}


@dataclass(frozen=True)
class MapSample:
    """One mapper stats message: seconds since the run started, map size and memory then."""

    t_s: float
    iteration: int
    gaussians: int
    model_bytes: int
    cuda_max_allocated: int | None = None


def training_rate(samples: Sequence[MapSample]) -> float | None:
    """Mapping iterations per second while training ran: from the first sample with a positive
    iteration count to the first sample at the final count (None with fewer than 2 such samples)."""
    active = [m for m in samples if m.iteration > 0]
    if len(active) < 2:
        return None
    final = max(m.iteration for m in active)
    end = next(m for m in active if m.iteration == final)
    start = active[0]
    if end.t_s <= start.t_s:
        return None
    return (end.iteration - start.iteration) / (end.t_s - start.t_s)


def finite_number(value: Any) -> float | None:  # noqa: ANN401 - a stats value of any JSON type
    """``value`` as a finite float; None for a missing, non-numeric or non-finite one."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def map_samples(timeline: Sequence[Mapping[str, Any]]) -> tuple[MapSample, ...]:
    """The mapper's stats over the run (rows of ``stats_timeline.jsonl`` from node ``mapper``
    that carry map gauges; before training starts the mapper has none)."""
    out: list[MapSample] = []
    for row in timeline:
        if row.get("node") != "mapper" or "gaussians" not in row:
            continue

        def num(key: str, row: Mapping[str, Any] = row) -> int:
            v = finite_number(row.get(key, 0))
            return 0 if v is None else int(v)

        cuda = finite_number(row["cuda_max_allocated"]) if "cuda_max_allocated" in row else None
        out.append(MapSample(t_s=float(row["t_s"]), iteration=num("iteration"), gaussians=num("gaussians"),
                             model_bytes=num("model_bytes"), cuda_max_allocated=None if cuda is None else int(cuda)))
    return tuple(out)


def mapper_gauge_max(timeline: Sequence[Mapping[str, Any]], key: str) -> float | None:
    """The largest value of a mapper stats gauge over the run (None when it never reported it)."""
    vals = [v for row in timeline if row.get("node") == "mapper" and (v := finite_number(row.get(key))) is not None]
    return max(vals) if vals else None


def node_peak_rss_mb(timeline: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """Peak RSS (MB) per node: the largest ``peak_rss_mb`` (VmHWM) each node reported."""
    peaks: dict[str, float] = {}
    for row in timeline:
        v = finite_number(row.get("peak_rss_mb"))
        if v is None:
            continue
        name = _TIMELINE_NODE_NAMES.get(str(row["node"]), str(row["node"]))
        peaks[name] = max(peaks.get(name, 0.0), round(v, 1))
    return peaks

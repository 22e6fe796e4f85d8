"""Every node's statistics, as frozen dataclasses: what ``memgs/<node>/stats`` may carry.

A field is one key of the stats message; a ``Mapping`` field is a family of keys sharing a prefix
(``skipped`` holds ``skipped.busy``, ``skipped.stale`` ...). The node's ``NodeStats`` refuses a key
its record does not name, and :func:`parse_stats` refuses one too, so a counter renamed on one side
only fails the first test that runs it, instead of reading 0 in the run summary. No rclpy here:
the runner and the benchmarks read the records without it.
"""
from __future__ import annotations

import dataclasses
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

from memgs_ros.errors import MessageError


class StatsError(MessageError):
    """A stats key that the node's telemetry record does not name, or a value of the wrong type."""


def _family() -> Any:  # noqa: ANN401 - a dataclass field default
    return field(default_factory=dict)


@dataclass(frozen=True)
class NodeTelemetry:
    """What every node reports (``ros/diagnostics.NodeStats`` fills these in)."""

    peak_rss_mb: float = 0.0
    rss_mb: float = 0.0
    cpu_s: float = 0.0  # the process's CPU time so far (composed: of every node in it)
    nice: int = 0
    kernels_warm: int = 0  # 1 once the node's compiled kernels are loaded (``memgs run`` waits for it)
    problem: Mapping[str, int] = _family()  # problem.<kind>: counted, logged once per kind


@dataclass(frozen=True)
class TrackerTelemetry(NodeTelemetry):
    frames_in: int = 0
    poses_out: int = 0
    keyframes: int = 0
    track_us_total: int = 0
    ba_us_total: int = 0
    frame_cpu_us_total: int = 0
    frame_cpu_ms: float = 0.0
    frame_cpu_ms_median: float = 0.0  # message in to pose out, CPU
    frame_ms_median: float = 0.0  # wall: a lockstep frame's share
    camera_info_differs: int = 0
    refined_keyframe_poses: int = 0  # keyframe poses re-published after local BA
    loop_corrected_keyframe_poses: int = 0  # ... after a loop closure
    segment: int = 0
    track_ms: float = 0.0  # the last frame's track() time
    ba_waits: int = 0  # frames that waited for the back-end's BA
    keyframes_deferred: int = 0
    map_points: int = 0  # the local map's size
    map_keyframes: int = 0
    map_keyframes_removed: int = 0
    warm_up_s: float = 0.0
    skipped: Mapping[str, int] = _family()  # skipped.<warming|stale|busy|...>
    state: Mapping[str, int] = _family()  # state.<OK|LOST|...>: frames per tracking state


@dataclass(frozen=True)
class SamplerTelemetry(NodeTelemetry):
    keyframes: int = 0
    seeds_keypoint: int = 0
    seeds_patch_grid: int = 0
    dropped_bundles: int = 0
    pending_bundles: int = 0


@dataclass(frozen=True)
class MapperTelemetry(NodeTelemetry):
    # the node's own
    raster_backend: str = ""
    checkpoint_period_s: float = 0.0
    checkpoints: int = 0
    checkpoint_gaussians: int = 0
    checkpoint_ms: float = 0.0
    resumed: int = 0
    rss_baseline_mb: float = 0.0
    warm_up_s: float = 0.0
    working_peak_mb: float = 0.0
    iterations_per_s: float = 0.0
    lockstep_ack_ms_median: float = 0.0
    keyframes_announced: int = 0
    keyframes_missed: int = 0
    duplicate_keyframe_parts: int = 0
    dropped_keyframe_bundles: int = 0
    delta_waits: int = 0
    delta_messages: int = 0
    delta_bytes: int = 0
    snapshots: int = 0
    # the mapping session's counters
    keyframes: int = 0
    duplicate_keyframes: int = 0
    seeded_gaussians: int = 0
    insert_ms_total: int = 0
    keyframe_pose_updates: int = 0
    refined_poses_of_dropped_keyframes: int = 0
    keyframes_corrected: int = 0
    gaussians_corrected: int = 0
    renders: int = 0
    train_commands: int = 0
    train_ms_total: int = 0
    merged_removed: int = 0
    merged_added: int = 0
    budget_merged: int = 0
    budget_pruned: int = 0
    # the mapping session's gauges (SessionStatus.gauges)
    insert_queue: int = 0
    seq: int = 0
    delta_pending_rows: int = 0
    alive: int = 0
    iteration: int = 0
    iterations_final: int = 0
    gaussians: int = 0
    gaussians_peak: int = 0
    model_bytes: int = 0
    model_bytes_peak: int = 0
    keyframes_trained: int = 0
    keyframes_dropped: int = 0
    keyframes_used: int = 0
    keyframes_waiting: int = 0
    budget_gaussians: int = 0
    keyframe_bytes: int = 0
    accounted_bytes: int = 0
    accounted_bytes_peak: int = 0
    loss: float | None = None  # None: no training step yet
    cuda_max_allocated: int | None = None  # None: not on CUDA
    # None until a keyframe has been trained (intake: decoded and prepared; latency: from the
    # tracker's decision to its first training step)
    keyframe_intake_ms_median: float | None = None
    keyframe_intake_ms_p95: float | None = None
    keyframe_latency_ms_median: float | None = None
    keyframe_latency_ms_p95: float | None = None
    cuda_peak_mb: Mapping[str, float] = _family()  # cuda_peak_mb.<work>: the CUDA peak each work set


@dataclass(frozen=True)
class MergerTelemetry(NodeTelemetry):
    deltas: int = 0
    delta_bytes: int = 0
    renders: int = 0
    saves: int = 0
    snapshot_requests: int = 0
    snapshots: int = 0
    buffered_deltas: int = 0
    epoch: int = 0
    gaussians: int = 0
    map_bytes: int = 0
    render_cache_bytes: int = 0
    resyncing: int = 0
    seq: int = 0
    unknown_removals: int = 0
    fault_dropped_deltas: int = 0
    resync: Mapping[str, int] = _family()  # resync.<status>


@dataclass(frozen=True)
class PlayerTelemetry(NodeTelemetry):
    frames_published: int = 0
    frames_total: int = 0
    ack_timeouts: int = 0
    ack_wait_ms_median: float = 0.0
    late_ms: float = 0.0
    skipped: Mapping[str, int] = _family()  # skipped.<kind>: frames the source could not give


@dataclass(frozen=True)
class RecorderTelemetry(NodeTelemetry):
    messages: int = 0
    bytes: int = 0
    topics: int = 0


@dataclass(frozen=True)
class ViewTelemetry(NodeTelemetry):
    map_seq: int = -1  # the last map logged (-1: none yet)
    map_epoch: int = -1
    map_gaussians: int = 0
    map_requests: int = 0
    log_us_total: int = 0
    psnr_db: float = 0.0
    logged: Mapping[str, int] = _family()  # logged.<what>
    log_us: Mapping[str, int] = _family()  # log_us.<what>


T = TypeVar("T", bound=NodeTelemetry)


_FIELDS: dict[type, tuple[dict[str, type], frozenset[str]]] = {}


def _fields(record: type[NodeTelemetry]) -> tuple[dict[str, type], frozenset[str]]:
    """The record's scalar fields (name -> int/float/str) and its key families."""
    if record in _FIELDS:
        return _FIELDS[record]
    hints = typing.get_type_hints(record)
    scalars: dict[str, type] = {}
    families: set[str] = set()
    for f in dataclasses.fields(record):
        hint = hints[f.name]
        if typing.get_origin(hint) is Mapping:  # a key family: Mapping[str, int | float]
            families.add(f.name)
        else:  # int, float, str, or one of them | None (reported only once it means something)
            scalars[f.name] = next(a for a in typing.get_args(hint) or (hint,) if a is not type(None))
    _FIELDS[record] = (scalars, frozenset(families))
    return _FIELDS[record]


def check_key(record: type[NodeTelemetry], key: str) -> None:
    """Raise StatsError unless ``record`` names ``key`` (a field, or ``<family>.<anything>``)."""
    scalars, families = _fields(record)
    if key in scalars:
        return
    family, dot, rest = key.partition(".")
    if not (dot and rest and family in families):
        raise StatsError(f"{record.__name__} has no stats key {key!r}: name it there (core/runtime/telemetry.py)")


def parse_stats(record: type[T], values: Mapping[str, str]) -> T:
    """The record of one stats message's key/values (``ros/diagnostics.stats_values``); keys the
    message lacks keep the record's defaults (a node reports some only once they mean something)."""
    scalars, families = _fields(record)
    kwargs: dict[str, Any] = {name: {} for name in families}
    for key, text in values.items():
        check_key(record, key)
        if key in scalars:
            kwargs[key] = _convert(record, key, scalars[key], text)
        else:
            family, _, member = key.partition(".")
            kind = typing.get_args(typing.get_type_hints(record)[family])[1]
            kwargs[family][member] = _convert(record, key, kind, text)
    return record(**kwargs)


def _convert(record: type, key: str, kind: type, text: str) -> int | float | str:
    try:
        if kind is int:
            return int(float(text))  # a counter published as "3.0" by an older node still reads
        if kind is float:
            return float(text)
        return str(text)
    except ValueError:
        raise StatsError(f"{record.__name__}.{key}: {text!r} is not a {kind.__name__}") from None


#: The record of each node name as it appears in ``memgs/<name>/stats``.
TELEMETRY: dict[str, type[NodeTelemetry]] = {
    "tracker": TrackerTelemetry, "keyframe_sampler": SamplerTelemetry, "mapper": MapperTelemetry,
    "merger": MergerTelemetry, "player": PlayerTelemetry, "recorder": RecorderTelemetry,
    "rerun_bridge": ViewTelemetry,
}

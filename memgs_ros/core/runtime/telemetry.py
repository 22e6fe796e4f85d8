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

    peak_rss_mb: float = 0.0  # the process's peak resident memory (VmHWM), MB
    rss_mb: float = 0.0  # its resident memory now
    cpu_s: float = 0.0  # the process's CPU time so far (composed: of every node in it)
    nice: int = 0  # scheduling priority
    kernels_warm: int = 0  # 1 once the node's compiled kernels are loaded (``memgs run`` waits for it)
    problem: Mapping[str, int] = _family()  # problem.<kind>: counted, logged once per kind


@dataclass(frozen=True)
class TrackerTelemetry(NodeTelemetry):
    frames_in: int = 0  # colour frames taken
    map_parts: int = 0  # bundle parts written (memgs/tracker/save_map_part)
    map_part_copy_ms: float = 0.0  # the last part's copy on the tracking thread (the write runs beside it)
    poses_out: int = 0  # poses published on memgs/pose (coasted ones too)
    odometry_out: int = 0  # tracked poses (state OK) on memgs/odom and memgs/pose_with_covariance
    odometry_withheld: int = 0  # poses whose odometry and TF waited for the camera's mount on tf_static
    tf_no_odom: int = 0  # tracked frames with an odom_frame but no odom -> base_link near their stamp: no TF
    tf_out: int = 0  # map -> base_link (or map -> odom) transforms broadcast on /tf, one per tracked frame
    keyframes: int = 0  # keyframes sent to the sampler and mapper
    track_us_total: int = 0  # time in track(), microseconds
    ba_us_total: int = 0  # inline local BA time (threaded BA: 0)
    frame_cpu_us_total: int = 0  # CPU from message in to pose out, over all frames
    frame_cpu_ms: float = 0.0  # the last frame's
    frame_cpu_ms_median: float = 0.0  # its rolling median
    frame_ms_median: float = 0.0  # wall: an acknowledged frame's share
    camera_info_differs: int = 0  # camera_info messages unlike the first (kept)
    refined_keyframe_poses: int = 0  # keyframe poses re-published after local BA
    loop_corrected_keyframe_poses: int = 0  # ... after a loop closure
    segment: int = 0  # the map segment tracked on (a new one after a long loss)
    tracking_state: str = ""  # the last frame's: NOT_INITIALIZED, OK, RECENTLY_LOST or LOST
    resets: int = 0  # relocalisations and new segments: the pose may jump there
    track_ms: float = 0.0  # the last frame's track() time
    ba_waits: int = 0  # frames that waited for the back-end's BA
    keyframes_deferred: int = 0  # due keyframes put off while a BA ran
    ba_refused: int = 0  # local BAs not committed: they slid their new keyframe (tracker.ba_max_shift_ratio)
    relocalizing: int = 0  # frames with no pose before the first relocalisation in a loaded map (map_bundle)
    relocalized_after: int = 0  # frames a loaded map took to relocalise in (-1: not yet)
    readout_flips: int = 0  # times the rolling shutter's row order flipped (tracking/frontend/readout.py)
    readout_sign: int = 1  # -1: the frames read their rows bottom to top
    map_points: int = 0  # the sparse map's size
    map_keyframes: int = 0  # keyframes it holds
    map_keyframes_removed: int = 0  # removed in all: culled, and over tracker.max_keyframes
    map_keyframes_culled: int = 0  # culled as redundant (tracker.keyframe_cull_ratio)
    culled_keyframes: int = 0  # announced on memgs/keyframe/culled
    warm_up_s: float = 0.0  # the kernels' load (or compile) time
    skipped: Mapping[str, int] = _family()  # skipped.<warming|stale|busy|...>
    state: Mapping[str, int] = _family()  # state.<OK|LOST|...>: frames per tracking state


@dataclass(frozen=True)
class SamplerTelemetry(NodeTelemetry):
    keyframes: int = 0  # keyframes sampled
    seeds_keypoint: int = 0  # seeds at the tracker's keypoints
    seeds_patch_grid: int = 0  # seeds the Patch-Grid added in sparse cells
    dropped_bundles: int = 0  # incomplete keyframe bundles given up
    pending_bundles: int = 0  # bundles waiting for a part
    skipped: Mapping[str, int] = _family()  # skipped.inactive: keyframe parts that came while paused (lifecycle)


@dataclass(frozen=True)
class MapperTelemetry(NodeTelemetry):
    # the node's own
    raster_backend: str = ""  # the rasterizer in use
    checkpoint_period_s: float = 0.0  # 0: this mapper never checkpoints
    checkpoints: int = 0  # written
    checkpoint_gaussians: int = 0  # in the last one
    checkpoint_ms: float = 0.0  # its write time
    map_parts: int = 0  # bundle parts written (memgs/mapper/save_map_part)
    resumed: int = 0  # 1 when it started from a checkpoint
    rss_baseline_mb: float = 0.0  # after imports, session and kernels
    warm_up_s: float = 0.0  # the kernels' load (or compile) time
    working_peak_mb: float = 0.0  # peak RSS above the baseline
    iterations_per_s: float = 0.0  # over the last stats period
    frame_ack_ms_median: float = 0.0  # tracker's word to the acknowledgement
    keyframes_announced: int = 0  # decisions heard from the tracker
    keyframes_missed: int = 0  # announced but never received whole
    duplicate_keyframe_parts: int = 0  # a part that came twice
    dropped_keyframe_bundles: int = 0  # incomplete bundles given up
    delta_waits: int = 0  # periodic deltas skipped while a receiver lagged
    delta_messages: int = 0  # map deltas sent
    delta_bytes: int = 0  # their size
    snapshots: int = 0  # full maps sent
    # the mapping session's counters
    keyframes: int = 0  # inserted
    duplicate_keyframes: int = 0  # inserted twice (the second ignored)
    seeded_gaussians: int = 0  # added from the sampler's seeds
    seeds_covered: int = 0  # seeds not added: the map already explained them (mapping.seed_coverage)
    keyframes_retired: int = 0  # culled by the tracker: out of training
    gaussians_handed_on: int = 0  # Gaussians of retired keyframes that now follow a kept one
    merge_passes: int = 0  # scheduled voxel-merge passes run
    insert_ms_total: int = 0  # time inserting keyframes
    keyframe_pose_updates: int = 0  # poses refined by the tracker's BA
    refined_poses_of_dropped_keyframes: int = 0  # refinements of keyframes no longer stored
    keyframes_corrected: int = 0  # moved by loop closures
    gaussians_corrected: int = 0  # Gaussians moved with them
    renders: int = 0  # views rendered on request
    train_commands: int = 0  # per-frame train commands run
    train_ms_total: int = 0  # their time
    merged_removed: int = 0  # Gaussians the voxel merge removed
    merged_added: int = 0  # ... and added in their place
    budget_merged: int = 0  # merged to keep within a memory budget
    budget_pruned: int = 0  # pruned for the same reason
    # the mapping session's gauges (SessionStatus.gauges)
    insert_queue: int = 0  # keyframes waiting for insertion
    seq: int = 0  # the last delta's sequence number
    delta_pending_rows: int = 0  # changed rows not yet sent
    alive: int = 0  # 1 while the session's worker and outbox run
    iteration: int = 0  # training steps so far
    iterations_final: int = 0  # those run by the finish
    gaussians: int = 0  # in the map now
    gaussians_peak: int = 0  # the most at any time
    model_bytes: int = 0  # parameters, gradients and Adam moments
    model_bytes_peak: int = 0  # their peak
    keyframes_trained: int = 0  # stored for training
    keyframes_dropped: int = 0  # left the store (mapping.max_keyframes)
    keyframes_used: int = 0  # trained at least once
    keyframes_waiting: int = 0  # stored, not yet trained
    budget_gaussians: int = 0  # the budget's bound (0: none)
    keyframe_bytes: int = 0  # stored keyframes' tensors
    accounted_bytes: int = 0  # model, keyframes and step buffers
    accounted_bytes_peak: int = 0  # their peak
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
    deltas: int = 0  # map deltas received
    delta_bytes: int = 0  # their size
    renders: int = 0  # views rendered on request
    saves: int = 0  # PLY files written
    bundles: int = 0  # map bundles saved (memgs/save_map with bundle_dir)
    bundle_mb: float = 0.0  # the last one's size on disk
    snapshot_requests: int = 0  # full maps asked of the mapper
    snapshots: int = 0  # full maps applied
    buffered_deltas: int = 0  # held while resynchronising
    epoch: int = 0  # the mapper's epoch followed
    gaussians: int = 0  # in the replica
    map_bytes: int = 0  # the replica's size
    render_cache_bytes: int = 0  # the renderer's tensors
    resyncing: int = 0  # 1 while waiting for a full map
    seq: int = 0  # the last delta applied
    unknown_removals: int = 0  # removals of ids the replica never held
    resync: Mapping[str, int] = _family()  # resync.<status>: why the replica resynchronised


@dataclass(frozen=True)
class PlayerTelemetry(NodeTelemetry):
    frames_published: int = 0  # frames sent
    frames_total: int = 0  # in the source (0: looping)
    ack_timeouts: int = 0  # acknowledged frames whose acknowledgement never came
    ack_wait_ms_median: float = 0.0  # an acknowledged frame's round trip
    late_ms: float = 0.0  # behind the real-time schedule
    skipped: Mapping[str, int] = _family()  # skipped.<kind>: frames the source could not give


@dataclass(frozen=True)
class RecorderTelemetry(NodeTelemetry):
    messages: int = 0  # written to the .mcap
    bytes: int = 0  # their payload
    topics: int = 0  # being recorded


@dataclass(frozen=True)
class ViewTelemetry(NodeTelemetry):
    map_seq: int = -1  # the last map logged (-1: none yet)
    map_epoch: int = -1  # its epoch
    map_gaussians: int = 0  # its size
    map_requests: int = 0  # full maps asked of the merger
    log_us_total: int = 0  # time in Rerun's log calls
    psnr_db: float = 0.0  # the last render against its frame
    logged: Mapping[str, int] = _family()  # logged.<what>: entities logged
    log_us: Mapping[str, int] = _family()  # log_us.<what>: their time


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

"""Generated from core/runtime/telemetry.py by `python -m memgs_ros.core.runtime.stat_fields
--write`: do not edit (test_telemetry fails while it is stale). See stat_fields.py."""
from __future__ import annotations

from memgs_ros.core.runtime.stat_fields import Family, Stat, StatsWriter


class NodeFields(StatsWriter):
    """NodeTelemetry, written by attribute."""

    peak_rss_mb = Stat[float](0.0)
    rss_mb = Stat[float](0.0)
    cpu_s = Stat[float](0.0)
    nice = Stat[int](0)
    kernels_warm = Stat[int](0)
    problem_counts = Family[int]("problem", 0)


class TrackerFields(NodeFields):
    """TrackerTelemetry, written by attribute."""

    frames_in = Stat[int](0)
    map_parts = Stat[int](0)
    map_part_copy_ms = Stat[float](0.0)
    poses_out = Stat[int](0)
    odometry_out = Stat[int](0)
    odometry_withheld = Stat[int](0)
    tf_no_odom = Stat[int](0)
    tf_out = Stat[int](0)
    keyframes = Stat[int](0)
    track_us_total = Stat[int](0)
    ba_us_total = Stat[int](0)
    frame_cpu_us_total = Stat[int](0)
    frame_cpu_ms = Stat[float](0.0)
    frame_cpu_ms_median = Stat[float](0.0)
    frame_ms_median = Stat[float](0.0)
    camera_info_differs = Stat[int](0)
    refined_keyframe_poses = Stat[int](0)
    loop_corrected_keyframe_poses = Stat[int](0)
    segment = Stat[int](0)
    tracking_state = Stat[str]("")
    resets = Stat[int](0)
    track_ms = Stat[float](0.0)
    ba_waits = Stat[int](0)
    keyframes_deferred = Stat[int](0)
    ba_refused = Stat[int](0)
    relocalizing = Stat[int](0)
    relocalized_after = Stat[int](0)
    readout_flips = Stat[int](0)
    readout_sign = Stat[int](1)
    map_points = Stat[int](0)
    map_keyframes = Stat[int](0)
    map_keyframes_removed = Stat[int](0)
    map_keyframes_culled = Stat[int](0)
    culled_keyframes = Stat[int](0)
    warm_up_s = Stat[float](0.0)
    skipped = Family[int]("skipped", 0)
    state = Family[int]("state", 0)


class SamplerFields(NodeFields):
    """SamplerTelemetry, written by attribute."""

    keyframes = Stat[int](0)
    seeds_keypoint = Stat[int](0)
    seeds_patch_grid = Stat[int](0)
    dropped_bundles = Stat[int](0)
    pending_bundles = Stat[int](0)
    skipped = Family[int]("skipped", 0)


class MapperFields(NodeFields):
    """MapperTelemetry, written by attribute."""

    raster_backend = Stat[str]("")
    checkpoint_period_s = Stat[float](0.0)
    checkpoints = Stat[int](0)
    checkpoint_gaussians = Stat[int](0)
    checkpoint_ms = Stat[float](0.0)
    map_parts = Stat[int](0)
    resumed = Stat[int](0)
    rss_baseline_mb = Stat[float](0.0)
    warm_up_s = Stat[float](0.0)
    working_peak_mb = Stat[float](0.0)
    iterations_per_s = Stat[float](0.0)
    lockstep_ack_ms_median = Stat[float](0.0)
    keyframes_announced = Stat[int](0)
    keyframes_missed = Stat[int](0)
    duplicate_keyframe_parts = Stat[int](0)
    dropped_keyframe_bundles = Stat[int](0)
    delta_waits = Stat[int](0)
    delta_messages = Stat[int](0)
    delta_bytes = Stat[int](0)
    snapshots = Stat[int](0)
    keyframes = Stat[int](0)
    duplicate_keyframes = Stat[int](0)
    seeded_gaussians = Stat[int](0)
    seeds_covered = Stat[int](0)
    keyframes_retired = Stat[int](0)
    gaussians_handed_on = Stat[int](0)
    merge_passes = Stat[int](0)
    insert_ms_total = Stat[int](0)
    keyframe_pose_updates = Stat[int](0)
    refined_poses_of_dropped_keyframes = Stat[int](0)
    keyframes_corrected = Stat[int](0)
    gaussians_corrected = Stat[int](0)
    renders = Stat[int](0)
    train_commands = Stat[int](0)
    train_ms_total = Stat[int](0)
    merged_removed = Stat[int](0)
    merged_added = Stat[int](0)
    budget_merged = Stat[int](0)
    budget_pruned = Stat[int](0)
    insert_queue = Stat[int](0)
    seq = Stat[int](0)
    delta_pending_rows = Stat[int](0)
    alive = Stat[int](0)
    iteration = Stat[int](0)
    iterations_final = Stat[int](0)
    gaussians = Stat[int](0)
    gaussians_peak = Stat[int](0)
    model_bytes = Stat[int](0)
    model_bytes_peak = Stat[int](0)
    keyframes_trained = Stat[int](0)
    keyframes_dropped = Stat[int](0)
    keyframes_used = Stat[int](0)
    keyframes_waiting = Stat[int](0)
    budget_gaussians = Stat[int](0)
    keyframe_bytes = Stat[int](0)
    accounted_bytes = Stat[int](0)
    accounted_bytes_peak = Stat[int](0)
    loss = Stat[float | None](None)
    cuda_max_allocated = Stat[int | None](None)
    keyframe_intake_ms_median = Stat[float | None](None)
    keyframe_intake_ms_p95 = Stat[float | None](None)
    keyframe_latency_ms_median = Stat[float | None](None)
    keyframe_latency_ms_p95 = Stat[float | None](None)
    cuda_peak_mb = Family[float]("cuda_peak_mb", 0.0)


class MergerFields(NodeFields):
    """MergerTelemetry, written by attribute."""

    deltas = Stat[int](0)
    delta_bytes = Stat[int](0)
    renders = Stat[int](0)
    saves = Stat[int](0)
    bundles = Stat[int](0)
    bundle_mb = Stat[float](0.0)
    snapshot_requests = Stat[int](0)
    snapshots = Stat[int](0)
    buffered_deltas = Stat[int](0)
    epoch = Stat[int](0)
    gaussians = Stat[int](0)
    map_bytes = Stat[int](0)
    render_cache_bytes = Stat[int](0)
    resyncing = Stat[int](0)
    seq = Stat[int](0)
    unknown_removals = Stat[int](0)
    fault_dropped_deltas = Stat[int](0)
    resync = Family[int]("resync", 0)


class PlayerFields(NodeFields):
    """PlayerTelemetry, written by attribute."""

    frames_published = Stat[int](0)
    frames_total = Stat[int](0)
    ack_timeouts = Stat[int](0)
    ack_wait_ms_median = Stat[float](0.0)
    late_ms = Stat[float](0.0)
    skipped = Family[int]("skipped", 0)


class RecorderFields(NodeFields):
    """RecorderTelemetry, written by attribute."""

    messages = Stat[int](0)
    bytes = Stat[int](0)
    topics = Stat[int](0)


class ViewFields(NodeFields):
    """ViewTelemetry, written by attribute."""

    map_seq = Stat[int](-1)
    map_epoch = Stat[int](-1)
    map_gaussians = Stat[int](0)
    map_requests = Stat[int](0)
    log_us_total = Stat[int](0)
    psnr_db = Stat[float](0.0)
    logged = Family[int]("logged", 0)
    log_us = Family[int]("log_us", 0)

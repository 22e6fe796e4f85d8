"""Generated from core/runtime/telemetry.py by `python -m memgs_ros.core.runtime.stat_fields
--write`: do not edit (test_telemetry fails while it is stale). See stat_fields.py."""
from __future__ import annotations

from memgs_ros.core.runtime.stat_fields import Family, Stat, StatsWriter


class NodeFields(StatsWriter):
    """NodeTelemetry, written by attribute."""

    peak_rss_mb = Stat[float](0.0)  # the process's peak resident memory (VmHWM), MB
    rss_mb = Stat[float](0.0)  # its resident memory now
    cpu_s = Stat[float](0.0)  # the process's CPU time so far (composed: of every node in it)
    nice = Stat[int](0)  # scheduling priority
    kernels_warm = Stat[int](0)  # 1 once the node's compiled kernels are loaded (``memgs run`` waits for it)
    problem_counts = Family[int]("problem", 0)  # problem.<kind>: counted, logged once per kind


class TrackerFields(NodeFields):
    """TrackerTelemetry, written by attribute."""

    frames_in = Stat[int](0)  # colour frames taken
    map_parts = Stat[int](0)  # bundle parts written (memgs/tracker/save_map_part)
    map_part_copy_ms = Stat[float](0.0)  # the last part's copy on the tracking thread (the write runs beside it)
    poses_out = Stat[int](0)  # poses published on memgs/pose (coasted ones too)
    odometry_out = Stat[int](0)  # tracked poses (state OK) on memgs/odom and memgs/pose_with_covariance
    odometry_withheld = Stat[int](0)  # poses whose odometry and TF waited for the camera's mount on tf_static
    tf_no_odom = Stat[int](0)  # tracked frames with an odom_frame but no odom -> base_link near their stamp: no TF
    tf_out = Stat[int](0)  # map -> base_link (or map -> odom) transforms broadcast on /tf, one per tracked frame
    keyframes = Stat[int](0)  # keyframes sent to the sampler and mapper
    track_us_total = Stat[int](0)  # time in track(), microseconds
    ba_us_total = Stat[int](0)  # inline local BA time (threaded BA: 0)
    frame_cpu_us_total = Stat[int](0)  # CPU from message in to pose out, over all frames
    frame_cpu_ms = Stat[float](0.0)  # the last frame's
    frame_cpu_ms_median = Stat[float](0.0)  # its rolling median
    frame_ms_median = Stat[float](0.0)  # wall: an acknowledged frame's share
    camera_info_differs = Stat[int](0)  # camera_info messages unlike the first (kept)
    refined_keyframe_poses = Stat[int](0)  # keyframe poses re-published after local BA
    loop_corrected_keyframe_poses = Stat[int](0)  # ... after a loop closure
    segment = Stat[int](0)  # the map segment tracked on (a new one after a long loss)
    tracking_state = Stat[str]("")  # the last frame's: NOT_INITIALIZED, OK, RECENTLY_LOST or LOST
    resets = Stat[int](0)  # relocalisations and new segments: the pose may jump there
    track_ms = Stat[float](0.0)  # the last frame's track() time
    ba_waits = Stat[int](0)  # frames that waited for the back-end's BA
    keyframes_deferred = Stat[int](0)  # due keyframes put off while a BA ran
    ba_refused = Stat[int](0)  # local BAs not committed: they slid their new keyframe (tracker.ba_max_shift_ratio)
    relocalizing = Stat[int](0)  # frames with no pose before the first relocalisation in a loaded map (map_bundle)
    relocalized_after = Stat[int](0)  # frames a loaded map took to relocalise in (-1: not yet)
    readout_flips = Stat[int](0)  # times the rolling shutter's row order flipped (tracking/frontend/readout.py)
    readout_sign = Stat[int](1)  # -1: the frames read their rows bottom to top
    map_points = Stat[int](0)  # the sparse map's size
    map_keyframes = Stat[int](0)  # keyframes it holds
    map_keyframes_removed = Stat[int](0)  # removed in all: culled, and over tracker.max_keyframes
    map_keyframes_culled = Stat[int](0)  # culled as redundant (tracker.keyframe_cull_ratio)
    culled_keyframes = Stat[int](0)  # announced on memgs/keyframe/culled
    warm_up_s = Stat[float](0.0)  # the kernels' load (or compile) time
    skipped = Family[int]("skipped", 0)  # skipped.<warming|stale|busy|...>
    state = Family[int]("state", 0)  # state.<OK|LOST|...>: frames per tracking state


class SamplerFields(NodeFields):
    """SamplerTelemetry, written by attribute."""

    keyframes = Stat[int](0)  # keyframes sampled
    seeds_keypoint = Stat[int](0)  # seeds at the tracker's keypoints
    seeds_patch_grid = Stat[int](0)  # seeds the Patch-Grid added in sparse cells
    dropped_bundles = Stat[int](0)  # incomplete keyframe bundles given up
    pending_bundles = Stat[int](0)  # bundles waiting for a part
    skipped = Family[int]("skipped", 0)  # skipped.inactive: keyframe parts that came while paused (lifecycle)


class MapperFields(NodeFields):
    """MapperTelemetry, written by attribute."""

    raster_backend = Stat[str]("")  # the rasterizer in use
    checkpoint_period_s = Stat[float](0.0)  # 0: this mapper never checkpoints
    checkpoints = Stat[int](0)  # written
    checkpoint_gaussians = Stat[int](0)  # in the last one
    checkpoint_ms = Stat[float](0.0)  # its write time
    map_parts = Stat[int](0)  # bundle parts written (memgs/mapper/save_map_part)
    resumed = Stat[int](0)  # 1 when it started from a checkpoint
    rss_baseline_mb = Stat[float](0.0)  # after imports, session and kernels
    warm_up_s = Stat[float](0.0)  # the kernels' load (or compile) time
    working_peak_mb = Stat[float](0.0)  # peak RSS above the baseline
    iterations_per_s = Stat[float](0.0)  # over the last stats period
    frame_ack_ms_median = Stat[float](0.0)  # tracker's word to the acknowledgement
    keyframes_announced = Stat[int](0)  # decisions heard from the tracker
    keyframes_missed = Stat[int](0)  # announced but never received whole
    duplicate_keyframe_parts = Stat[int](0)  # a part that came twice
    dropped_keyframe_bundles = Stat[int](0)  # incomplete bundles given up
    delta_waits = Stat[int](0)  # periodic deltas skipped while a receiver lagged
    delta_messages = Stat[int](0)  # map deltas sent
    delta_bytes = Stat[int](0)  # their size
    snapshots = Stat[int](0)  # full maps sent
    keyframes = Stat[int](0)  # inserted
    duplicate_keyframes = Stat[int](0)  # inserted twice (the second ignored)
    seeded_gaussians = Stat[int](0)  # added from the sampler's seeds
    seeds_covered = Stat[int](0)  # seeds not added: the map already explained them (mapping.seed_coverage)
    keyframes_retired = Stat[int](0)  # culled by the tracker: out of training
    gaussians_handed_on = Stat[int](0)  # Gaussians of retired keyframes that now follow a kept one
    merge_passes = Stat[int](0)  # scheduled voxel-merge passes run
    insert_ms_total = Stat[int](0)  # time inserting keyframes
    keyframe_pose_updates = Stat[int](0)  # poses refined by the tracker's BA
    refined_poses_of_dropped_keyframes = Stat[int](0)  # refinements of keyframes no longer stored
    keyframes_corrected = Stat[int](0)  # moved by loop closures
    gaussians_corrected = Stat[int](0)  # Gaussians moved with them
    renders = Stat[int](0)  # views rendered on request
    train_commands = Stat[int](0)  # per-frame train commands run
    train_ms_total = Stat[int](0)  # their time
    merged_removed = Stat[int](0)  # Gaussians the voxel merge removed
    merged_added = Stat[int](0)  # ... and added in their place
    budget_merged = Stat[int](0)  # merged to keep within a memory budget
    budget_pruned = Stat[int](0)  # pruned for the same reason
    insert_queue = Stat[int](0)  # keyframes waiting for insertion
    seq = Stat[int](0)  # the last delta's sequence number
    delta_pending_rows = Stat[int](0)  # changed rows not yet sent
    alive = Stat[int](0)  # 1 while the session's worker and outbox run
    iteration = Stat[int](0)  # training steps so far
    iterations_final = Stat[int](0)  # those run by the finish
    gaussians = Stat[int](0)  # in the map now
    gaussians_peak = Stat[int](0)  # the most at any time
    model_bytes = Stat[int](0)  # parameters, gradients and Adam moments
    model_bytes_peak = Stat[int](0)  # their peak
    keyframes_trained = Stat[int](0)  # stored for training
    keyframes_dropped = Stat[int](0)  # left the store (mapping.max_keyframes)
    keyframes_used = Stat[int](0)  # trained at least once
    keyframes_waiting = Stat[int](0)  # stored, not yet trained
    budget_gaussians = Stat[int](0)  # the budget's bound (0: none)
    keyframe_bytes = Stat[int](0)  # stored keyframes' tensors
    accounted_bytes = Stat[int](0)  # model, keyframes and step buffers
    accounted_bytes_peak = Stat[int](0)  # their peak
    loss = Stat[float | None](None)  # None: no training step yet
    cuda_max_allocated = Stat[int | None](None)  # None: not on CUDA
    keyframe_intake_ms_median = Stat[float | None](None)
    keyframe_intake_ms_p95 = Stat[float | None](None)
    keyframe_latency_ms_median = Stat[float | None](None)
    keyframe_latency_ms_p95 = Stat[float | None](None)
    cuda_peak_mb = Family[float]("cuda_peak_mb", 0.0)  # cuda_peak_mb.<work>: the CUDA peak each work set


class MergerFields(NodeFields):
    """MergerTelemetry, written by attribute."""

    deltas = Stat[int](0)  # map deltas received
    delta_bytes = Stat[int](0)  # their size
    renders = Stat[int](0)  # views rendered on request
    saves = Stat[int](0)  # PLY files written
    bundles = Stat[int](0)  # map bundles saved (memgs/save_map with bundle_dir)
    bundle_mb = Stat[float](0.0)  # the last one's size on disk
    snapshot_requests = Stat[int](0)  # full maps asked of the mapper
    snapshots = Stat[int](0)  # full maps applied
    buffered_deltas = Stat[int](0)  # held while resynchronising
    epoch = Stat[int](0)  # the mapper's epoch followed
    gaussians = Stat[int](0)  # in the replica
    map_bytes = Stat[int](0)  # the replica's size
    render_cache_bytes = Stat[int](0)  # the renderer's tensors
    resyncing = Stat[int](0)  # 1 while waiting for a full map
    seq = Stat[int](0)  # the last delta applied
    unknown_removals = Stat[int](0)  # removals of ids the replica never held
    resync = Family[int]("resync", 0)  # resync.<status>: why the replica resynchronised


class PlayerFields(NodeFields):
    """PlayerTelemetry, written by attribute."""

    frames_published = Stat[int](0)  # frames sent
    frames_total = Stat[int](0)  # in the source (0: looping)
    ack_timeouts = Stat[int](0)  # acknowledged frames whose acknowledgement never came
    ack_wait_ms_median = Stat[float](0.0)  # an acknowledged frame's round trip
    late_ms = Stat[float](0.0)  # behind the real-time schedule
    skipped = Family[int]("skipped", 0)  # skipped.<kind>: frames the source could not give


class RecorderFields(NodeFields):
    """RecorderTelemetry, written by attribute."""

    messages = Stat[int](0)  # written to the .mcap
    bytes = Stat[int](0)  # their payload
    topics = Stat[int](0)  # being recorded


class ViewFields(NodeFields):
    """ViewTelemetry, written by attribute."""

    map_seq = Stat[int](-1)  # the last map logged (-1: none yet)
    map_epoch = Stat[int](-1)  # its epoch
    map_gaussians = Stat[int](0)  # its size
    map_requests = Stat[int](0)  # full maps asked of the merger
    log_us_total = Stat[int](0)  # time in Rerun's log calls
    psnr_db = Stat[float](0.0)  # the last render against its frame
    logged = Family[int]("logged", 0)  # logged.<what>: entities logged
    log_us = Family[int]("log_us", 0)  # log_us.<what>: their time

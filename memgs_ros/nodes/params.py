"""Every node's parameters, as frozen dataclasses, and which config groups each node declares.

The nodes declare these through rclpy (:func:`memgs_ros.ros.config_params.declare_config`); the
runner, ``memgs eval`` and the parameter reference read them here, with no rclpy: a config is
checked (names, types, ranges, choices) before any process starts, also where the ROS extra is
not installed. ``RANGES``/``CHOICES`` on a class bound its fields; a node's ``CONFIGS`` is
``NODE_CONFIGS[name]``: (prefix, config class) pairs, ``""`` for the node's own.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from memgs_ros.core.geometry.camera import CAMERA_PREFIX, CameraCalibration
from memgs_ros.core.geometry.frames import FrameConvention, mount_transform
from memgs_ros.core.mapping.config import MappingConfig
from memgs_ros.core.merge.config import MergeConfig
from memgs_ros.core.runtime.replay import Pacing
from memgs_ros.core.sampling import PatchGridConfig
from memgs_ros.core.tracking import TrackerConfig
from memgs_ros.errors import ConfigError


@dataclass(frozen=True)
class BagPlayerParams:
    """The player's own parameters (no prefix; the ``camera.*`` calibration is its own group).

    wait_for_readers: comma-separated node names whose color and camera_info readers must be matched
        before the first frame (memgs run names the tracker); at most start_delay_s
    """

    source: str = ""  # frame source: TUM folder, .bag, ROS 2 bag folder/.mcap, or 'synthetic:...' spec
    # a bag's topics, 'color=/a,depth=/b,camera_info=/c' (any of them); empty: TUM's names, else found by type
    bag_topics: str = ""
    rate: float = 1.0  # real-time factor (2.0 plays twice as fast); live pacing only
    loop: bool = False  # start over at the end (stamps keep increasing)
    # live: the recorded rate; lockstep: the next frame only after the mapper acknowledged this one
    pacing: str = "live"
    ack_topic: str = "memgs/frame_ack"  # std_msgs/Header acks (stamp of the finished frame), acknowledged pacing
    ack_timeout_s: float = 10.0  # acknowledged pacing: warn and go on when no ack arrives within this time
    start_delay_s: float = 5.0  # wait at most this long for a color subscriber before the first frame
    wait_for_readers: str = ""
    max_frames: int = 0  # stop after this many frames, over all loops (0 = no limit)
    # play the source this many times, every other pass backward, on one clock, ground truth with it
    # (a long flight over the same room; memgs run --repeat)
    repeat: int = 1
    # ... every pass forward, the camera jumping back to the start between them (a rolling-shutter
    # recording played backward reads its rows bottom to top)
    repeat_forward: bool = False
    # depth image encoding: 32FC1 metres, or 16UC1 as a camera driver writes it: a TUM folder's PNG
    # units as stored (5000 a metre), other depth in REP-118's millimetres
    depth_encoding: str = "32FC1"
    frame_id: str = "camera_color_optical_frame"  # frame id of the images and camera info
    world_frame_id: str = "world"  # frame id of the ground-truth poses
    # stop at the first bad frame (unreadable or mis-sized image, stamp going backwards, a camera that
    # changes mid-run) instead of skipping and counting it (skipped.<kind> in the stats)
    strict: bool = False
    # decode every frame into memory before the first goes out, at most this many MB (0 = decode each
    # frame as it goes out): a live replay then costs the CPU a camera driver does, not a PNG decoder's
    preload_mb: int = 0

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "rate": (0.01, 1000.0), "ack_timeout_s": (0.05, 3600.0), "start_delay_s": (0.0, 600.0),
        "max_frames": (0, 2**31 - 1), "preload_mb": (0, 1_000_000),
        "repeat": (1, 1000),
    }
    CHOICES: ClassVar[dict[str, tuple[str, ...]]] = {"depth_encoding": ("32FC1", "16UC1"), "pacing": Pacing.choices()}

    @property
    def replay(self) -> Pacing:
        return Pacing(self.pacing)


@dataclass(frozen=True)
class TrackerParams:
    """The tracker node's own parameters (no prefix; the algorithm's are ``tracker.*``).

    depth_topic: depth image input registered to colour (16UC1 or 32FC1); unused in mono mode
    camera_info_topic: camera_info of the colour camera (plumb_bob or rational_polynomial)
    input_reliability: camera subscriptions: best_effort (sensor-data QoS, live cameras: drop rather than
        queue) or reliable (lockstep replays must not lose a frame)
    path_rate_hz: memgs/path publications per second (the whole path each time; poses go out per frame on
        memgs/pose and memgs/odom)
    time_jump_back_s: a frame stamped more than this before the previous one is a time reset (bag loop):
        tracking goes on from it; a smaller step back is a late frame and is dropped
    camera_info_override: use the camera.* calibration instead of camera_info (whose intrinsics and
        distortion are then ignored; TUM's bags carry placeholder ones)
    max_frame_age_s: a colour frame that waited longer than this since it was published, beyond the least
        wait seen, is stale (the tracker fell behind) and is dropped so that tracking catches up with the
        camera (counted as skipped.stale); 0 = never drop (memgs run's lockstep replays)
    """
    # configure and activate at start (ros2 run, launch); false: wait for lifecycle transitions
    # (<node>/change_state, lifecycle_msgs/srv/ChangeState), as memgs run and a lifecycle manager drive them
    autostart: bool = True

    color_topic: str = "camera/camera/color/image_raw"  # colour image input
    depth_topic: str = "camera/camera/aligned_depth_to_color/image_raw"
    camera_info_topic: str = "camera/camera/color/camera_info"
    # raw: sensor_msgs/Image; compressed: CompressedImage on <color_topic>/compressed (JPEG, PNG) and
    # <depth_topic>/compressedDepth (image_transport's PNG), as a camera streams over a radio link
    image_transport: str = "raw"
    depth_scale: float = 1000.0  # the camera's 16UC1 units a metre (RealSense 1000, TUM 5000): no other node reads them
    sync: str = "approximate"  # colour/depth pairing
    max_sync_dt_s: float = 0.02  # largest colour/depth stamp difference paired (approximate)
    unpaired_warn_s: float = 5.0  # colour arriving this long with no depth to pair it with: warn, naming why
    # the SLAM world: the first camera's optical frame (x right, y down, z forward); memgs/pose, the path,
    # keyframes and maps are in it, TF relates it to map_frame by a static transform
    world_frame: str = "map_optical"
    map_frame: str = "map"  # REP-105 map: z up, the body's first pose (odometry and TF are in it)
    base_frame: str = "base_link"  # the body (REP-103: x forward, y left, z up); the odometry's child frame
    # non-empty (e.g. odom): broadcast map -> odom_frame from the odom_frame -> base_frame another source
    # publishes on /tf (a flight controller, wheels), instead of map -> base_frame
    odom_frame: str = ""
    odom_tolerance_s: float = 0.05  # the odom_frame -> base_frame transform used lies this close to the frame
    publish_tf: bool = True  # /tf map -> base_frame (or odom_frame) per tracked frame, /tf_static map -> world_frame
    # /tf_static base_frame -> the images' optical frame from camera_mount_*; false where the robot
    # description or the camera driver already publishes the camera in TF (the mount is then read there)
    publish_camera_tf: bool = True
    # with publish_camera_tf false: how long to wait for base_frame -> the camera on tf_static (read as the
    # mount) before the camera_mount_* parameters stand in; the body's poses wait with it
    camera_mount_wait_s: float = 2.0
    # the camera's mount in base_frame: metres and radians of its own REP-103 frame (x along the lens), as a
    # URDF joint; all zero: looking forward from the body's origin
    camera_mount_x: float = 0.0
    camera_mount_y: float = 0.0
    camera_mount_z: float = 0.0
    camera_mount_roll: float = 0.0
    camera_mount_pitch: float = 0.0
    camera_mount_yaw: float = 0.0
    camera_frame: str = "camera_color_optical_frame"  # the images' frame when their header names none
    input_reliability: str = "best_effort"
    path_max_len: int = 10000  # poses kept in memgs/path (0 = all)
    path_rate_hz: float = 1.0
    time_jump_back_s: float = 1.0
    max_stamp_ahead_s: float = 3600.0  # drop frames stamped more than this ahead of the node's clock (0 = no check)
    camera_info_override: bool = False
    max_frame_age_s: float = 0.1
    map_bundle: str = ""  # a saved map bundle to start from (core/map_io/bundle.py): no pose until relocalised in it
    map_mode: str = "mapping"  # with map_bundle: mapping (continue the map) or localize (track, change nothing)
    bundle_dir: str = ""  # where bundles are saved (memgs/save_map); this node stages its part in <bundle_dir>/.parts

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "depth_scale": (1e-3, 1e6), "max_sync_dt_s": (0.0, 1.0), "unpaired_warn_s": (0.1, 3600.0),
        "path_max_len": (0, 10**7),
        "path_rate_hz": (0.01, 100.0), "time_jump_back_s": (0.0, 1e6), "max_stamp_ahead_s": (0.0, 1e9),
        "max_frame_age_s": (0.0, 60.0), "odom_tolerance_s": (0.0, 10.0), "camera_mount_wait_s": (0.0, 600.0),
        "camera_mount_x": (-100.0, 100.0), "camera_mount_y": (-100.0, 100.0), "camera_mount_z": (-100.0, 100.0),
        "camera_mount_roll": (-7.0, 7.0), "camera_mount_pitch": (-7.0, 7.0), "camera_mount_yaw": (-7.0, 7.0),
    }
    CHOICES: ClassVar[dict[str, tuple[str, ...]]] = {
        "sync": ("approximate", "exact"), "input_reliability": ("best_effort", "reliable"),
        "image_transport": ("raw", "compressed"), "map_mode": ("mapping", "localize"),
    }

    def __post_init__(self) -> None:
        names = {"world_frame": self.world_frame, "map_frame": self.map_frame, "base_frame": self.base_frame}
        if self.odom_frame:
            names["odom_frame"] = self.odom_frame
        if not all(names.values()) or len(set(names.values())) != len(names):
            raise ConfigError(f"tracker frames must be non-empty and distinct: {names}")

    def frame_convention(self) -> FrameConvention:
        """The SLAM world's relation to map and base_frame, from the camera's mount."""
        return FrameConvention(mount_transform((self.camera_mount_x, self.camera_mount_y, self.camera_mount_z,
                                                self.camera_mount_roll, self.camera_mount_pitch,
                                                self.camera_mount_yaw)))


@dataclass(frozen=True)
class KeyframeSamplerParams:
    """The keyframe sampler's own parameters (no prefix)."""
    # configure and activate at start (ros2 run, launch); false: wait for lifecycle transitions
    # (<node>/change_state, lifecycle_msgs/srv/ChangeState), as memgs run and a lifecycle manager drive them
    autostart: bool = True

    mode: str = "rgbd"  # camera mode (mono: depth from the nearest keypoint)
    world_frame: str = "map_optical"  # frame id (the SLAM world; TF: map -> map_optical) of the seed cloud
    niceness: int = 5  # CPU niceness of the whole process (0..19): below the tracker, above the mapper

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"niceness": (0, 19)}
    CHOICES: ClassVar[dict[str, tuple[str, ...]]] = {"mode": ("rgbd", "mono")}


@dataclass(frozen=True)
class MapperParams:
    """The mapper's own parameters (no prefix); the map's are ``mapping.*`` and ``merge.*``.

    final_budget_s: end the final iterations once they have run this long (0 = all of them): the time
        to a map handed over, e.g. a ground station over a radio link, against the last polish
    final_total_iterations: the final iterations go on while the map has trained fewer than this many in all
        (0 = final_iterations only): a live run on a slow machine, which trained little while the camera moved,
        still gets a lockstep replay's training (final_budget_s still bounds them)
    final_densify: densify during the final iterations too (false: they only refine the map, which then
        keeps its size)
    delta_budget_kbytes_per_s: link budget for map deltas; the largest changes go first, the rest wait
        (the final flush ignores it)
    delta_tolerance: send a Gaussian again only when a parameter moved more than this (m, or
        pre-activation units); the final flush is exact
    checkpoint_period_s: write a checkpoint this often while the map changes (0 = only at finish/shutdown)
    insert_queue: free-running: complete keyframes waiting for insertion; when full the oldest is dropped
        and counted (problem.keyframe_overload)
    ack_window: acknowledged pacing: a frame is acknowledged once at most this many frames' training (its own
        included) is unfinished, so the tracker works on the next frame while the mapper trains (1); 0 waits
        for the frame's own training. The map is the same either way (core/runtime/replay.py)
    """
    # configure and activate at start (ros2 run, launch); false: wait for lifecycle transitions
    # (<node>/change_state, lifecycle_msgs/srv/ChangeState), as memgs run and a lifecycle manager drive them
    autostart: bool = True

    mode: str = "rgbd"  # camera mode: rgbd, or mono (keyframes carry no depth)
    device: str = "auto"  # torch device for the map: auto (CUDA when present), cpu, cuda, cuda:N
    # live: train freely beside the frames; lockstep: train iterations_per_frame for each frame, then acknowledge it
    pacing: str = "live"
    iterations_per_frame: int = 10  # training iterations per frame in an acknowledged replay
    ack_window: int = 1
    final_iterations: int = 0  # extra training iterations run by the finish service before the final flush
    final_densify: bool = True
    final_budget_s: float = 0.0
    final_total_iterations: int = 0
    delta_rate_hz: float = 1.0  # map deltas per second
    delta_budget_kbytes_per_s: float = 500.0
    delta_tolerance: float = 1e-3
    snapshot_period_s: float = 0.0  # publish a full snapshot this often (0 = only on request)
    render_rate_hz: float = 1.0  # live view renders per second (0 = off)
    world_frame: str = "map_optical"  # frame id (the SLAM world; TF: map -> map_optical) of published maps and poses
    ack_topic: str = "memgs/frame_ack"  # the acknowledgement topic (to the player), acknowledged pacing
    checkpoint_path: str = ""  # file for map + keyframe checkpoints (.npz); empty = no checkpoints
    checkpoint_period_s: float = 30.0
    resume: bool = True  # start from the checkpoint at checkpoint_path when one exists
    insert_queue: int = 4
    niceness: int = 10  # CPU niceness of the whole process (0..19): the tracker (0) goes first on shared cores
    map_bundle: str = ""  # a saved map bundle to continue (this mapper's own checkpoint, after a crash, comes first)
    map_mode: str = "mapping"  # with map_bundle: mapping (train it on) or localize (render it, never train)
    bundle_dir: str = ""  # where bundles are saved (memgs/save_map); this node stages its part in <bundle_dir>/.parts

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "niceness": (0, 19), "iterations_per_frame": (0, 10000),
        "ack_window": (0, 100),
        "final_iterations": (0, 10**7), "final_budget_s": (0.0, 1e6), "final_total_iterations": (0, 10**8),
        "delta_rate_hz": (0.01, 100.0), "delta_budget_kbytes_per_s": (1.0, 1e7), "delta_tolerance": (0.0, 10.0),
        "snapshot_period_s": (0.0, 1e6), "render_rate_hz": (0.0, 60.0), "checkpoint_period_s": (0.0, 1e6),
        "insert_queue": (1, 1000),
    }
    CHOICES: ClassVar[dict[str, tuple[str, ...]]] = {"mode": ("rgbd", "mono"), "map_mode": ("mapping", "localize"),
                                                     "pacing": Pacing.choices()}

    def __post_init__(self) -> None:  # CHOICES refuses a bad parameter; this, a bad direct construction
        if self.mode not in self.CHOICES["mode"]:
            raise ConfigError(f"mode must be rgbd or mono, got {self.mode!r}")

    @property
    def replay(self) -> Pacing:
        return Pacing(self.pacing)


@dataclass(frozen=True)
class MergerParams:
    """The merger's own parameters (no prefix)."""
    # configure and activate at start (ros2 run, launch); false: wait for lifecycle transitions
    # (<node>/change_state, lifecycle_msgs/srv/ChangeState), as memgs run and a lifecycle manager drive them
    autostart: bool = True

    map_path: str = "memgs_map.ply"  # where the map PLY is saved (atomically)
    # the tracker's and mapper's bundle_dir must name the same folder (they stage their parts there)
    bundle_dir: str = ""  # non-empty: memgs/save_map also saves a map bundle here (a new folder, a latest link)
    map_source: str = ""  # what the map was made from, written into the bundle's manifest
    save_period_s: float = 60.0  # also save the PLY this often when it changed (0 = only on request and shutdown)
    # publish the full map on memgs/map/gaussians and memgs/map/points this often (0 = only on request)
    publish_period_s: float = 30.0
    resync_interval_s: float = 1.0  # least time between snapshot requests (doubles, up to 8x, while unanswered)
    max_buffered_deltas: int = 200  # deltas kept while resynchronising
    delta_topic: str = "memgs/map/delta"  # the mapper's deltas as they reach here (a bridge may rename them)
    world_frame: str = "map_optical"  # frame id (the SLAM world; TF: map -> map_optical) of the published map
    render_width: int = 320  # render width (px) for view requests
    render_height: int = 240  # render height (px) for view requests
    render_fx: float = 258.65  # render focal length x (px)
    render_fy: float = 258.23  # render focal length y (px)
    render_cx: float = 159.32  # render principal point x (px)
    render_cy: float = 127.66  # render principal point y (px)
    niceness: int = 10  # CPU niceness of the whole process (0..19) where it shares the robot's cores

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "niceness": (0, 19), "save_period_s": (0.0, 1e6), "publish_period_s": (0.0, 1e6),
        "resync_interval_s": (0.0, 3600.0),
        "max_buffered_deltas": (1, 100000),
        "render_width": (1, 8192), "render_height": (1, 8192), "render_fx": (1e-3, 1e6), "render_fy": (1e-3, 1e6),
        "render_cx": (-1e6, 1e6), "render_cy": (-1e6, 1e6),
    }


# Every output of the graph, relative to the node's namespace (types as the nodes publish them).
DEFAULT_TOPICS: tuple[str, ...] = (
    # tracker
    "memgs/pose",                            # geometry_msgs/PoseStamped, every frame tracked
    "memgs/odom",                            # nav_msgs/Odometry (tracked frames, with covariance)
    "memgs/pose_with_covariance",            # geometry_msgs/PoseWithCovarianceStamped (tracked frames)
    "memgs/path",                            # nav_msgs/Path (loop-corrected trajectory)
    "memgs/tracking_state",                  # std_msgs/String
    "memgs/keyframe/pose",                   # geometry_msgs/PoseStamped, at keyframe insertion
    "memgs/keyframe/refined_poses",          # nav_msgs/Path (local BA)
    "memgs/keyframe/loop_corrected_poses",   # nav_msgs/Path (loop closure)
    "tf", "tf_static",                       # tf2_msgs/TFMessage: map -> base_link; map -> map_optical, the mount
    # mapper
    "memgs/map/delta",                       # sensor_msgs/PointCloud2
    "memgs/mapper/snapshot",                 # sensor_msgs/PointCloud2 (latched, rgb)
    "memgs/render/color",                    # sensor_msgs/Image
    "memgs/render/depth",                    # sensor_msgs/Image
    "memgs/render/camera_info",              # sensor_msgs/CameraInfo
    # merger
    "memgs/map/gaussians",                   # sensor_msgs/PointCloud2 (latched, rgb)
    "memgs/map/points",                      # sensor_msgs/PointCloud2 (latched: x, y, z, rgb, opacity)
    "memgs/merger/render/color",             # sensor_msgs/Image
    "memgs/merger/render/depth",             # sensor_msgs/Image
    "memgs/merger/render/camera_info",       # sensor_msgs/CameraInfo
    # every node: diagnostic_msgs/DiagnosticArray
    "memgs/tracker/stats", "memgs/keyframe_sampler/stats", "memgs/mapper/stats", "memgs/merger/stats",
    "memgs/player/stats",
)


@dataclass(frozen=True)
class RecorderParams:
    """The recorder's own parameters (no prefix).

    topics: topics to record, relative to the node's namespace or absolute (default: every memgs output)
    """

    path: str = ""  # the .mcap file to write (required); replaced atomically when the node stops
    topics: tuple[str, ...] = DEFAULT_TOPICS
    discovery_period_s: float = 0.2  # look for publishers of topics not yet recorded this often

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"discovery_period_s": (0.01, 60.0)}


DEFAULT_STATS_KEYS = ("gaussians,iteration,loss,keyframes,poses_out,track_ms,rss_mb,model_bytes,map_bytes,"
                      "delta_bytes")


@dataclass(frozen=True)
class RerunBridgeParams:
    """The bridge's own parameters (no prefix).

    log_sh: send the map's degree 1..3 SH coefficients too (+90 B a Gaussian each time; the viewer then
        shows view-dependent colour)
    log_frames: subscribe to color_topic and log the frame beside each render (off on a thin link: the
        renders alone are small)
    """

    spawn: bool = False  # spawn a local Rerun viewer (or use one listening on port 9876)
    connect_url: str = ""  # stream to the Rerun viewer at this URL (rerun+http://HOST:9876/proxy); empty = none
    save_path: str = ""  # also record to this .rrd file; empty = none
    application_id: str = "memgs_ros"  # Rerun application id (the viewer groups recordings by it)
    recording_name: str = ""  # Rerun recording name (empty: the node's namespace)
    map_period_s: float = 5.0  # log the map this often when it changed (s); 0 = only full maps the merger publishes
    log_sh: bool = False
    jpeg_quality: int = 85  # JPEG quality of logged images (0 = raw pixels)
    log_frames: bool = True
    color_topic: str = "color/image_raw"  # the source colour images
    stats_keys: str = DEFAULT_STATS_KEYS  # comma-separated stats keys to plot ('*' = all)
    frustum_size_m: float = 0.08  # depth of the drawn keyframe frusta (m)

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "map_period_s": (0.0, 3600.0), "jpeg_quality": (0, 100), "frustum_size_m": (1e-4, 100.0),
    }


# node (the registry's name) -> its parameter groups: (prefix, frozen config class)
NODE_CONFIGS: dict[str, tuple[tuple[str, type], ...]] = {
    "bag_player": (("", BagPlayerParams), (CAMERA_PREFIX, CameraCalibration)),
    "tracker": (("", TrackerParams), ("tracker", TrackerConfig), (CAMERA_PREFIX, CameraCalibration)),
    "keyframe_sampler": (("", KeyframeSamplerParams), ("patch_grid", PatchGridConfig)),
    "mapper": (("", MapperParams), ("mapping", MappingConfig), ("merge", MergeConfig)),
    "merger": (("", MergerParams),),
    "recorder": (("", RecorderParams),),
    "rerun_bridge": (("", RerunBridgeParams),),
}

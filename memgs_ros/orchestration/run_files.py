"""What a run is given and what it leaves behind: options, the parameter file, the summary, and
the names of the files in a run's output folder.

Writers (:mod:`memgs_ros.orchestration.pipeline`) and readers (:mod:`memgs_ros.evaluation.runs`)
share these names. Importing this module loads no node, rclpy or torch, so the CLI can check
its inputs quickly before anything starts.
"""
from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Generic, NamedTuple, TypeVar

import yaml

from memgs_ros.core.geometry.camera import CameraCalibration, PinholeCamera
from memgs_ros.core.runtime.replay import Pacing
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.nodes.registry import GRAPH, NODES
from memgs_ros.viz import RerunTarget

__all__ = [
    "BUNDLES_DIR", "CHECKPOINT_FILE", "GRAPH_NODE_NAMES", "KEYFRAMES_FILE", "LOGS_DIR", "MAP_FILE", "NODE_NAMES",
    "PARAMS_FILE", "STATS_TIMELINE_FILE",
    "SUMMARY_FILE", "TRAJECTORY_FILE", "ConfigEdit", "ConfiguredCamera", "RunOptions", "RunSummary", "build_params",
    "check_parameters", "check_record_path", "config_path", "configured_camera", "node_params", "read_params",
    "read_stats_timeline", "read_summary",
]

# The nodes a parameter override may name; the pipeline starts one module per name (recorder
# only with RunOptions.record, rerun_bridge only with RunOptions.rerun). Start order: the graph,
# then the player. Both from memgs_ros/nodes/registry.py.
NODE_NAMES = tuple(NODES)
GRAPH_NODE_NAMES = GRAPH

# Files in a run's output folder.
PARAMS_FILE = "params.yaml"  # the effective per-node parameters
MAP_FILE = "map.ply"
CHECKPOINT_FILE = "mapper_checkpoint.npz"  # the mapper's checkpoint (resumed by a mapper restarted mid-run)
BUNDLES_DIR = "maps"  # map bundles the run saves (core/map_io/bundle.py), and their "latest" link
TRAJECTORY_FILE = "trajectory.txt"  # every tracked pose, TUM format
KEYFRAMES_FILE = "keyframes.txt"  # keyframe poses at insertion, TUM format
STATS_TIMELINE_FILE = "stats_timeline.jsonl"  # every node stats message: {"t_s", "node", key: value}
SUMMARY_FILE = "summary.json"  # RunSummary.as_dict()
LOGS_DIR = "logs"


C = TypeVar("C")


@dataclass(frozen=True)
class ConfigEdit(Generic[C]):
    """A typed change to one node's config group, e.g. ``ConfigEdit("mapper", "mapping",
    MappingConfig, lambda c: replace(c, merge_enabled=False))`` (mypy checks the field names):
    ``change`` maps the group's config as the run's config file and settings give it to the one
    to run with. It becomes parameters only in the run's parameter file (:func:`build_params`)."""

    node: str
    prefix: str  # the group's parameter prefix, "" for the node's own parameters
    config: type[C]
    change: Callable[[C], C]

    def parameters(self, node_params: Mapping[str, Any]) -> dict[str, Any]:
        """The parameters that turn the group's config in ``node_params`` into the changed one."""
        from memgs_ros.nodes.params import NODE_CONFIGS
        from memgs_ros.ros.config_params import changed_parameters, config_from_values

        if (self.prefix, self.config) not in NODE_CONFIGS.get(self.node, ()):
            raise ConfigError(f"{self.node} has no config group {self.prefix!r} of {self.config.__name__}")
        before = config_from_values(self.config, self.prefix, node_params)
        return changed_parameters(self.prefix, before, self.change(before))


@dataclass(frozen=True)
class RunOptions:
    source: str
    config: str = "synthetic"
    out_dir: Path = Path("memgs_out")
    composed: bool = False  # the nodes as components of the runner's process, on one executor
    pacing: Pacing = Pacing.LOCKSTEP  # memgs run acknowledges every frame unless --realtime
    rate: float = 1.0
    namespace: str = ""
    domain_id: int | None = None
    max_frames: int = 0
    repeat: int = 1  # the source played this many times, forward and back (io/repeat.py)
    repeat_forward: bool = False  # ... every pass forward
    bag_topics: str = ""  # a bag's topics (BagTopics.parse: memgs run --topics); empty: TUM's or found by type
    edits: tuple[ConfigEdit[Any], ...] = ()  # typed changes, applied in order before the overrides
    overrides: Mapping[str, Any] = field(default_factory=dict)  # "node.param" -> value (a user's --set)
    # Start these nodes this many seconds after the player starts (a ground-station merger
    # joining mid-run; separate processes only).
    start_delays_s: Mapping[str, float] = field(default_factory=dict)
    # Fault injection (separate processes only): SIGKILL these nodes this many seconds after
    # the player starts and once each has state to lose (the mapper a checkpoint holding Gaussians,
    # the merger a delta), and start them again at once (the mapper resumes from its checkpoint).
    kill_after_s: Mapping[str, float] = field(default_factory=dict)
    timeout_s: float = 1800.0
    # Stop at the first bad frame instead of skipping and counting it (the player's strict).
    strict: bool = False
    # Record every output topic into this .mcap file (a recorder node; see check_record_path).
    record: Path | None = None
    # Stream the run to Rerun (viewer and/or .rrd file) through a rerun_bridge node; None = no view.
    rerun: RerunTarget | None = None
    # A saved map bundle to start from (core/map_io/bundle.py), and what to do with it: mapping (continue
    # it; the run saves a new bundle) or localize (track in it, change nothing, save no bundle).
    map_bundle: Path | None = None
    map_mode: str = "mapping"


@dataclass(frozen=True)
class RunSummary:
    source: str  # what was played
    frames: int  # taken by the tracker
    poses: int  # in trajectory.txt
    keyframes: int  # the tracker's
    gaussians: int  # in the saved map
    tracking_fps: float  # frames over the time in track()
    wall_s: float  # start of the nodes to the saved map
    ply_path: str  # the merger's map
    trajectory_path: str  # trajectory.txt
    delta_messages: int
    delta_bytes: int
    delta_bytes_per_s: float
    lost_frames: int
    merger_seq: int
    namespace: str
    domain_id: int
    mapping_iterations: int
    model_bytes_peak: int  # the map's parameters + gradients + Adam state, peak over the run
    gaussians_peak: int
    peak_rss_mb: dict[str, float]  # per node process (in one process: the same figure for all)
    merger_resyncs: int  # gaps, late starts or mismatches the merger repaired from a snapshot
    restarts: dict[str, int]  # nodes killed and restarted by fault injection
    replica_identical: bool  # merger's map == mapper's map (same ids, parameters within 1e-6)
    replica_max_abs_diff: float
    render_size: tuple[int, int]  # (width, height) of the last live render, (0, 0) if none
    render_std: float  # spread of its pixel values in [0, 255]: ~0 means a blank view
    source_complete: bool = True  # False: the source failed part-way; the map holds what was played
    cpu_s: dict[str, float] = field(default_factory=dict)  # per node process, from its last stats (s)
    skipped_frames: dict[str, int] = field(default_factory=dict)  # bad frames the player skipped, by kind
    frames_played: int = 0  # frames the player published (``frames`` is what reached the tracker)
    # frames played but not tracked, by reason: warming (came before the tracker's kernels were in),
    # stale (dropped by the tracker, which had fallen behind), busy (published, never delivered: the
    # reader's queue overflowed or transport lost it), unpaired (colour that found no depth to pair)
    tracker_skipped: dict[str, int] = field(default_factory=dict)
    tracker_frame_cpu_ms: float = 0.0  # the tracker's CPU per frame, message in to pose out (median)
    mapping_iterations_final: int = 0  # of mapping_iterations, run by the finish (the rest while frames came)
    keyframes_mapped: int = 0  # keyframes the mapper inserted into its map
    keyframes_trained: int = 0  # of those, drawn by at least one training step
    # per keyframe, median and p95: the mapper's intake CPU (decode, prepare, upload, insert), and
    # the wall time from the tracker's decision to the first training step that drew it
    keyframe_intake_ms: dict[str, float] = field(default_factory=dict)
    keyframe_latency_ms: dict[str, float] = field(default_factory=dict)
    # the managed nodes' configure requests to all active, as the runner drove them (None: composed,
    # or an earlier run's summary)
    bring_up_s: float | None = None
    cuda_peak_mb: float | None = None  # the mapper's torch.cuda.max_memory_allocated (None on the CPU)
    # per kind of mapper work (forward, backward, merge, keyframe upload...), the highest CUDA peak
    # it raised the device to: the largest names the work that set the peak
    cuda_peak_by_work_mb: dict[str, float] = field(default_factory=dict)
    # what the graph held at its peaks: every node process's peak RSS (one process when composed)
    # plus the CUDA peak; on a Jetson both come out of one memory
    graph_memory_mb: float = 0.0
    # an acknowledged replay: where a frame's time goes (ms): ``frame`` the player's wait from publishing it to
    # its acknowledgement (median), ``tracker`` the tracker's time on it (median), ``mapper`` from
    # the tracker's word on it to the mapper's acknowledgement (median), ``training`` the mapper's
    # training per frame (mean); what ``frame`` holds beyond them is messages and handshakes
    frame_ms: dict[str, float] = field(default_factory=dict)
    repeat: int = 1  # the source was played this many times, forward and back (``open_source(repeat=)``)
    repeat_forward: bool = False  # ... every pass forward
    bag_topics: str = ""  # the bag topics the run was given (``BagTopics.parse``)
    bundle_path: str = ""  # the map bundle saved at the end ("" when none: localize, or no map)
    map_bundle: str = ""  # the bundle the run started from ("" when none)
    relocalizing: int = 0  # frames given no pose before the first relocalisation in map_bundle

    @property
    def mapping_iterations_replay(self) -> int:
        """Training steps run while the source played (live: while the camera moved)."""
        return self.mapping_iterations - self.mapping_iterations_final

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "mapping_iterations_replay": self.mapping_iterations_replay}


def config_path(name_or_path: str) -> Path:
    """A config name (``tum_fr1``) or path to the YAML file; searches the source tree and ``share/``."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml", ".xml") and p.exists():
        return p
    if len(p.parts) > 1:  # a path, not a name: say so rather than search the config folders
        raise ConfigError(f"config file {p} does not exist")
    name = p.name if p.suffix in (".yaml", ".yml", ".xml") else f"{name_or_path}.yaml"
    roots = [Path(__file__).resolve().parents[2] / "config"]
    roots += [Path(prefix) / "share" / "memgs_ros" / "config"
              for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if prefix]
    roots.append(Path(sys.prefix) / "share" / "memgs_ros" / "config")
    for root in roots:
        if (root / name).exists():
            return root / name
    raise ConfigError(f"no config '{name_or_path}' (looked for {name} in {', '.join(map(str, roots))})")


def build_params(options: RunOptions, map_path: Path) -> dict[str, Any]:
    """The run's parameter file: the config, then the run's own settings, then the overrides."""
    path = config_path(options.config)
    base = _load_config(path)
    params: dict[str, dict[str, Any]] = {}
    for key, section in base.items():
        node = str(key).rsplit("/", 1)[-1]
        section = {} if section is None else section
        node_params = (section.get("ros__parameters") or {}) if isinstance(section, dict) else None
        if not isinstance(node_params, dict):
            raise ConfigError(f"config {path}: '{key}' must be a mapping with a 'ros__parameters' mapping, "
                              f"got {section!r:.80}")
        params[node] = dict(node_params)
    params.setdefault("bag_player", {}).update(
        source=str(options.source), pacing=options.pacing.value, rate=float(options.rate),
        max_frames=int(options.max_frames), repeat=int(options.repeat), repeat_forward=bool(options.repeat_forward),
        bag_topics=str(options.bag_topics), ack_topic="memgs/frame_ack",
        world_frame_id="map",
        strict=bool(options.strict))
    params.setdefault("mapper", {})["pacing"] = options.pacing.value
    if params["bag_player"].get("depth_encoding", "32FC1") == "16UC1":
        from memgs_ros.io.sources import player_depth_units  # loads the bag readers: only here

        # The player writes 16-bit depth in its source's units (a TUM folder's as stored): the
        # tracker, the one node that reads a camera's units, reads them with the same scale.
        params.setdefault("tracker", {})["depth_scale"] = player_depth_units(options.source)
    if float(options.start_delays_s.get("tracker", 0.0)) <= 0:
        # The first frame waits for the tracker's readers, not just any reader (a Rerun bridge
        # reads the frames too); the runner has already seen the tracker come up.
        params["bag_player"].setdefault("wait_for_readers", "tracker")
        params["bag_player"].setdefault("start_delay_s", 30.0)
    if options.pacing.acknowledged:
        # Background BA would refine poses at timing-dependent moments: run it in step instead.
        params.setdefault("tracker", {}).setdefault("tracker.ba_threaded", False)
        params["tracker"].setdefault("input_reliability", "reliable")  # a frame waited for must not be lost
        params["tracker"].setdefault("max_frame_age_s", 0.0)  # and never drops one as stale
    else:
        # The player is a reliable publisher on this host: a reliable reader gets each frame it
        # reads whole (best effort lost half the 2 MB frames in transport, counted as busy), and
        # its keep-last queue still lets a busy tracker skip frames; stale ones are dropped.
        params.setdefault("tracker", {}).setdefault("input_reliability", "reliable")
    params.setdefault("merger", {})["map_path"] = str(map_path)
    _bundle_params(params, options, map_path.parent / BUNDLES_DIR)
    if options.record is not None:
        params.setdefault("recorder", {})["path"] = str(Path(options.record).resolve())
    if options.rerun is not None:
        params.setdefault("rerun_bridge", {}).update(
            options.rerun.node_params(),
            recording_name=f"{Path(str(options.source)).name} ({Path(options.out_dir).name})")
    params.setdefault("mapper", {}).setdefault("checkpoint_path", str(map_path.with_name(CHECKPOINT_FILE)))
    for edit in options.edits:
        params.setdefault(edit.node, {}).update(edit.parameters(params.get(edit.node, {})))
    for key, value in options.overrides.items():
        node, _, name = key.partition(".")
        if node not in NODE_NAMES or not name:
            raise ConfigError(f"override '{key}' must be <node>.<parameter> with node one of {sorted(NODE_NAMES)}")
        params.setdefault(node, {})[name] = value
    try:
        configured_camera(params)  # a half-given calibration fails here, naming the config
    except ConfigError as err:
        raise ConfigError(f"config {path}: {err}") from err
    # The config's calibration (tracker section) is also the camera of a TUM folder that names
    # none, which only the player can attach to the frames it publishes.
    for name, value in params.get("tracker", {}).items():
        if name.startswith(CALIBRATION_PREFIX):
            params.setdefault("bag_player", {}).setdefault(name, value)
    return {f"/**/{node}": {"ros__parameters": p} for node, p in params.items()}


def edited_parameters(config: str, edits: Sequence[ConfigEdit[Any]]) -> dict[str, Any]:
    """{"node.param": value} that ``edits`` change in ``config``'s parameters, in order (what a
    run's record says it changed)."""
    params = node_params(build_params(RunOptions(source="", config=config), Path(MAP_FILE)))
    out: dict[str, Any] = {}
    for edit in edits:
        changed = edit.parameters(params.get(edit.node, {}))
        params.setdefault(edit.node, {}).update(changed)
        out.update({f"{edit.node}.{name}": value for name, value in changed.items()})
    return out


def _bundle_params(params: dict[str, dict[str, Any]], options: RunOptions, bundle_dir: Path) -> None:
    """Map bundles: the one to start from (tracker and mapper), and where the run saves its own
    (tracker, mapper and merger; none in localize mode, which changes nothing)."""
    for node in ("tracker", "mapper"):
        params.setdefault(node, {})["map_mode"] = options.map_mode
        if options.map_bundle is not None:
            params[node]["map_bundle"] = str(Path(options.map_bundle).expanduser().resolve())
    if options.map_mode != "localize":
        for node in ("tracker", "mapper", "merger"):
            params.setdefault(node, {}).setdefault("bundle_dir", str(bundle_dir.resolve()))
    params.setdefault("merger", {}).setdefault("map_source", str(options.source))


def check_record_path(path: str | os.PathLike[str]) -> Path:
    """The absolute path of a ``--record`` file, checked before anything starts: it must end in
    ``.mcap``, must not be a folder, and its folder must be creatable and writable (it is made
    here). An existing file is replaced when the recording is complete."""
    p = Path(path).expanduser()
    if p.suffix != ".mcap":
        raise ConfigError(f"--record {p}: the recording is a ROS 2 mcap file; give a name ending in .mcap")
    if p.is_dir():
        raise DataError(f"--record {p}: is an existing folder; give a file name ending in .mcap")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise DataError(f"--record {p}: cannot create its folder {p.parent}: {err.strerror or err}") from err
    if not os.access(p.parent, os.W_OK | os.X_OK):
        raise DataError(f"--record {p}: cannot write into {p.parent}: permission denied")
    return p.resolve()


CALIBRATION_PREFIX = "camera."  # tracker parameters camera.width ... camera.k6 (CameraCalibration)


class ConfiguredCamera(NamedTuple):
    """The calibration a run's parameters carry (tracker ``camera.*``)."""

    camera: PinholeCamera | None  # None: the config gives no calibration
    override: bool  # tracker.camera_info_override: the nodes use ``camera`` instead of camera_info


def check_parameters(params: Mapping[str, Mapping[str, Any]]) -> None:
    """ConfigError with one line per problem in {node: {param: value}}, before any node starts:
    a name the node does not declare (rclpy would ignore it and the node would run on the
    default), a value of the wrong type, out of its range or not one of its choices, or a group
    its config refuses as a whole: what the node itself would refuse at start, in its words.
    Reads the parameter tables (memgs_ros.nodes.params), not the nodes: no rclpy needed."""
    from memgs_ros.nodes.params import NODE_CONFIGS
    from memgs_ros.ros.config_params import check_values, parameter_names, unknown_parameters

    lines: list[str] = []
    for node, values in params.items():
        if node not in NODE_NAMES:
            raise ConfigError(f"parameters for '{node}': no such node (nodes: {', '.join(NODE_NAMES)})")
        lines += unknown_parameters(node, values, parameter_names(NODE_CONFIGS[node]), set_form=True)
        for prefix, config_cls in NODE_CONFIGS[node]:
            lines += check_values(config_cls, prefix, values, node=node)
    if not lines:
        lines += _mapper_device_problem(params)
    if lines:
        raise ConfigError("; ".join(lines))


def _mapper_device_problem(params: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """The mapper's device and rasterizer against this machine's torch and packages (a CUDA
    device without a CUDA torch, gsplat without gsplat): one line naming what to install."""
    if "mapper" not in params:
        return []
    from memgs_ros.nodes.params import NODE_CONFIGS

    own = dict(NODE_CONFIGS["mapper"])
    device = str(params["mapper"].get("device", own[""].device))
    backend = str(params["mapper"].get("mapping.raster_backend", own["mapping"].raster_backend))
    if device in ("auto", "cpu") and backend in ("auto", "torch", "numba"):
        return []  # runs anywhere the package installs: no torch import for the common case
    from memgs_ros.core.raster.backend_choice import device_problem

    problem = device_problem(device, backend)
    return [problem] if problem else []


def configured_camera(params: Mapping[str, Mapping[str, Any]]) -> ConfiguredCamera:
    """The calibration in per-node parameters ({node: {param: value}}, as :func:`read_params` or
    :func:`node_params` give them). ConfigError when it is given only in part or not numbers."""
    tracker = params.get("tracker", {})
    override = tracker.get("camera_info_override", False)
    if not isinstance(override, bool):
        raise ConfigError(f"tracker.camera_info_override must be true or false, got {override!r}")
    camera = CameraCalibration.from_params(tracker, CALIBRATION_PREFIX).camera()
    if override and camera is None:
        raise ConfigError("tracker.camera_info_override is true but the tracker has no camera.* calibration")
    return ConfiguredCamera(camera, override)


def node_params(params_file: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """{node: {param: value}} of a parameter file's mapping (:func:`build_params`' result)."""
    return {str(key).rsplit("/", 1)[-1]: dict((v or {}).get("ros__parameters", {}) or {})
            for key, v in params_file.items()}


def _load_config(path: Path) -> dict[Any, Any]:
    """The YAML mapping in ``path``; ConfigError (one line, naming the file) when it is not one."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"could not read config {path}: {err}") from err
    try:
        base = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ConfigError(f"config {path} is not valid YAML{where}: {problem}") from err
    if base is None:
        return {}
    if not isinstance(base, dict):
        raise ConfigError(f"config {path} must be a mapping of node names to parameters, "
                          f"got a {type(base).__name__}")
    return base


def read_summary(out_dir: str | os.PathLike[str]) -> RunSummary:
    """The RunSummary a finished run wrote to ``out_dir/summary.json``."""
    path = Path(out_dir) / SUMMARY_FILE
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
        if isinstance(raw, dict) and raw.get("outcome") in ("failed", "interrupted"):
            raise DataError(f"the run in {Path(out_dir)} did not finish ({raw['outcome']}: {raw.get('error', '?')})")
        known = {f.name for f in fields(RunSummary)}
        data = {k: v for k, v in raw.items() if k in known}
        data["render_size"] = tuple(data.get("render_size", (0, 0)))
        return RunSummary(**data)
    except (OSError, ValueError, TypeError, AttributeError) as err:
        raise DataError(f"could not read the run summary {path}: {err}") from err


def read_params(out_dir: str | os.PathLike[str]) -> dict[str, dict[str, Any]]:
    """The effective per-node parameters a run used (``params.yaml``), by node name."""
    path = Path(out_dir) / PARAMS_FILE
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
        return node_params(raw)
    except (OSError, yaml.YAMLError, AttributeError, TypeError, ValueError) as err:
        raise DataError(f"could not read the run's parameters {path}: {err}") from err


def read_stats_timeline(out_dir: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Every stats message the run recorded, in arrival order: {"t_s": float, "node": str,
    key: value (strings, as the nodes publish them)}. [] when the run recorded none."""
    path = Path(out_dir) / STATS_TIMELINE_FILE
    if not path.is_file():
        return []
    rows: list[dict[str, Any]] = []
    try:
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if line.strip():
                row = json.loads(line)
                if not isinstance(row, dict) or "node" not in row or "t_s" not in row:
                    raise ValueError(f"line {n} is not a stats row")
                rows.append(row)
    except (OSError, ValueError) as err:
        raise DataError(f"could not read the stats timeline {path}: {err}") from err
    return rows

"""Run the whole graph on a recorded source: player -> tracker -> sampler -> mapper -> merger.

``run_pipeline(options)`` starts the five nodes either as separate processes over real DDS
(the default, as on a robot) or in this process on one multi-threaded executor, watches them
through an observer node, and at the end of the source finishes the mapper (final flush),
waits for the merger to hold the mapper's last delta, saves the map and returns a summary.
It is what ``memgs run`` / ``memgs demo`` and the end-to-end tests call.
"""
from __future__ import annotations

import json
import logging
import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from memgs_ros.errors import ConfigError, MemgsError

logger = logging.getLogger(__name__)

GRAPH_NODES = ("merger", "mapper", "keyframe_sampler", "tracker")
NODE_CLASSES = {
    "tracker": ("memgs_ros.nodes.tracker", "TrackerNode"),
    "keyframe_sampler": ("memgs_ros.nodes.keyframe_sampler", "KeyframeSamplerNode"),
    "mapper": ("memgs_ros.nodes.mapper", "MapperNode"),
    "merger": ("memgs_ros.nodes.merger", "MergerNode"),
    "bag_player": ("memgs_ros.nodes.bag_player", "BagPlayer"),
}


class PipelineError(MemgsError):
    """A node died, timed out or the run could not finish."""


@dataclass(frozen=True)
class RunOptions:
    source: str
    config: str = "synthetic"
    out_dir: Path = Path("memgs_out")
    single_process: bool = False
    lockstep: bool = True
    rate: float = 1.0
    namespace: str = ""
    domain_id: int | None = None
    max_frames: int = 0
    overrides: Mapping[str, Any] = field(default_factory=dict)  # "node.param" -> value
    # Start these nodes this many seconds after the player starts (a ground-station merger
    # joining mid-run; separate processes only).
    start_delays_s: Mapping[str, float] = field(default_factory=dict)
    # Fault injection (separate processes only): SIGKILL these nodes this many seconds after
    # the player starts, and start them again at once (the mapper resumes from its checkpoint).
    kill_after_s: Mapping[str, float] = field(default_factory=dict)
    timeout_s: float = 1800.0


@dataclass(frozen=True)
class RunSummary:
    source: str
    frames: int
    poses: int
    keyframes: int
    gaussians: int
    tracking_fps: float
    wall_s: float
    ply_path: str
    trajectory_path: str
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

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


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
        source=str(options.source), lockstep=options.lockstep, rate=float(options.rate),
        max_frames=int(options.max_frames), ack_topic="memgs/frame_ack", world_frame_id="map")
    params.setdefault("mapper", {})["lockstep"] = options.lockstep
    if options.lockstep:
        # Background BA would refine poses at timing-dependent moments: run it in step instead.
        params.setdefault("tracker", {}).setdefault("tracker.ba_threaded", False)
        params["tracker"].setdefault("input_reliability", "reliable")  # lockstep must not lose a frame
    params.setdefault("merger", {})["map_path"] = str(map_path)
    params.setdefault("mapper", {}).setdefault("checkpoint_path", str(map_path.with_name("mapper_checkpoint.npz")))
    for key, value in options.overrides.items():
        node, _, name = key.partition(".")
        if node not in NODE_CLASSES or not name:
            raise ConfigError(f"override '{key}' must be <node>.<parameter> with node one of {sorted(NODE_CLASSES)}")
        params.setdefault(node, {})[name] = value
    return {f"/**/{node}": {"ros__parameters": p} for node, p in params.items()}


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


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


class _Observer:
    """An rclpy node that watches the graph and drives its end (created after rclpy.init)."""

    def __init__(self, context: Any) -> None:
        from geometry_msgs.msg import PoseStamped
        from rclpy.node import Node
        from std_msgs.msg import Bool
        from std_srvs.srv import Trigger
        from diagnostic_msgs.msg import DiagnosticArray

        from memgs_ros.ros import qos
        from memgs_ros.ros.codecs import pose_to_matrix, stamp_to_ns
        from memgs_ros.ros.diagnostics import stats_values

        self.node = Node("memgs_run_observer", context=context)
        self.done = threading.Event()
        self.source_ok = True  # False when the player reported a source that failed part-way
        self.stats: dict[str, dict[str, str]] = {}
        self.trajectory: list[tuple[int, np.ndarray]] = []
        self.keyframes: list[tuple[int, np.ndarray]] = []
        self.timeline: list[dict[str, Any]] = []  # every stats message: {"t_s", "node", values...}
        self._t0 = time.monotonic()
        self._lock = threading.Lock()

        def on_pose(msg: PoseStamped) -> None:
            with self._lock:
                self.trajectory.append((stamp_to_ns(msg.header.stamp), pose_to_matrix(msg.pose)))

        def stats_cb(name: str):  # noqa: ANN202
            def cb(msg: DiagnosticArray) -> None:
                values = stats_values(msg)
                self.stats[name] = values
                with self._lock:
                    self.timeline.append({"t_s": round(time.monotonic() - self._t0, 2), "node": name, **values})
            return cb

        def on_done(msg: Bool) -> None:
            self.source_ok = bool(msg.data)
            self.done.set()

        self.node.create_subscription(Bool, "memgs/player/done", on_done, qos.latched())
        def on_keyframe(msg: PoseStamped) -> None:
            with self._lock:
                self.keyframes.append((stamp_to_ns(msg.header.stamp), pose_to_matrix(msg.pose)))

        self.node.create_subscription(PoseStamped, "memgs/pose", on_pose, qos.reliable(1000))
        self.node.create_subscription(PoseStamped, "memgs/keyframe/pose", on_keyframe, qos.reliable(1000))
        for name in ("tracker", "keyframe_sampler", "mapper", "merger", "player"):
            self.node.create_subscription(DiagnosticArray, f"memgs/{name}/stats", stats_cb(name), qos.reliable(5))
        from sensor_msgs.msg import Image, PointCloud2

        self.maps: dict[str, Any] = {}
        self.render: Any = None
        self.node.create_subscription(PointCloud2, "memgs/mapper/snapshot",
                                      lambda m: self.maps.__setitem__("mapper", m), qos.latched())
        self.node.create_subscription(PointCloud2, "memgs/map/gaussians",
                                      lambda m: self.maps.__setitem__("merger", m), qos.latched())
        self.node.create_subscription(Image, "memgs/render/color", lambda m: setattr(self, "render", m),
                                      qos.reliable(2))
        self.finish_client = self.node.create_client(Trigger, "memgs/mapper/finish")
        self.snapshot_client = self.node.create_client(Trigger, "memgs/mapper/publish_snapshot")
        self.publish_map_client = self.node.create_client(Trigger, "memgs/merger/publish_map")
        self.save_client = self.node.create_client(Trigger, "memgs/save_map")
        self._trigger = Trigger

    def call(self, client: Any, timeout_s: float) -> str:
        """Call a Trigger service and return its message; PipelineError if it fails."""
        if not client.wait_for_service(timeout_sec=min(timeout_s, 30.0)):
            raise PipelineError(f"service {client.srv_name} is not available")
        future = client.call_async(self._trigger.Request())
        end = time.monotonic() + timeout_s
        while not future.done():
            if time.monotonic() > end:
                raise PipelineError(f"service {client.srv_name} did not answer within {timeout_s:.0f} s")
            time.sleep(0.05)
        res = future.result()
        if not res.success:
            raise PipelineError(f"service {client.srv_name} failed: {res.message}")
        return res.message

    def stat(self, node: str, key: str, default: float = 0.0) -> float:
        try:
            return float(self.stats.get(node, {}).get(key, default))
        except ValueError:
            return default


def _parse_kv(message: str) -> dict[str, str]:
    return dict(part.split("=", 1) for part in message.split() if "=" in part)


class _Processes:
    """The graph's nodes as child processes, logs in ``log_dir``; stopped with SIGINT."""

    def __init__(self, params_file: Path, namespace: str, env: dict[str, str], log_dir: Path) -> None:
        self.procs: dict[str, subprocess.Popen] = {}
        self.log_dir = log_dir
        self.player_reported = False  # the player announced its end (done or failed): its exit code is known
        self._params_file, self._ns, self._env = params_file, namespace, env

    def start(self, name: str) -> None:
        module = NODE_CLASSES[name][0]
        cmd = [sys.executable, "-m", module, "--ros-args", "--params-file", str(self._params_file)]
        if self._ns:
            cmd += ["-r", f"__ns:={self._ns}"]
        log = open(self.log_dir / f"{name}.log", "wb")  # noqa: SIM115 - owned by the child
        self.procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=self._env)

    def kill_and_restart(self, name: str) -> None:
        """SIGKILL a node (no chance to save anything) and start it again."""
        p = self.procs[name]
        p.kill()
        p.wait()
        os.replace(self.log_dir / f"{name}.log", self.log_dir / f"{name}.killed-{int(time.time())}.log")
        self.start(name)

    def check(self) -> None:
        for name, p in list(self.procs.items()):
            code = p.poll()
            if code is not None and not (name == "bag_player" and (code == 0 or self.player_reported)):
                tail = (self.log_dir / f"{name}.log").read_text(errors="replace").strip().splitlines()[-15:]
                raise PipelineError(f"node {name} exited with code {code}:\n  " + "\n  ".join(tail))

    def stop(self, timeout_s: float = 20.0) -> None:
        for p in list(self.procs.values()):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        end = time.monotonic() + timeout_s
        for name, p in list(self.procs.items()):
            try:
                p.wait(timeout=max(0.1, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                logger.warning("node %s did not stop on SIGINT; killing it", name)
                p.kill()
                p.wait()


def _open_context(domain_id: int | None, ros_args: list[str], probe_s: float = 1.0,
                  tries: int = 12) -> tuple[Any, int]:
    """An rclpy context on ``domain_id``, or on a random domain where no other node is seen.

    Two graphs on one domain hear each other (another run's camera_info reached a tracker):
    a run that picks its own domain first listens for ``probe_s`` that nobody is there.
    """
    import rclpy

    candidates = [domain_id] if domain_id is not None else random.sample(range(1, 233), tries)
    for domain in candidates:
        context = rclpy.Context()
        rclpy.init(args=ros_args, context=context, domain_id=domain)
        if domain_id is not None:
            return context, domain
        probe = rclpy.create_node("memgs_run_domain_probe", context=context)
        time.sleep(probe_s)
        busy = [n for n in probe.get_node_names() if n != "memgs_run_domain_probe"]
        probe.destroy_node()
        if not busy:
            return context, domain
        rclpy.try_shutdown(context=context)
    raise PipelineError(f"no free ROS domain found in {tries} tries; pass one with --domain-id")


def run_pipeline(options: RunOptions, progress: bool = True) -> RunSummary:
    """Replay ``options.source`` through the graph and return what it produced."""
    import rclpy
    from rclpy.executors import MultiThreadedExecutor

    out = Path(options.out_dir).resolve()
    (out / "logs").mkdir(parents=True, exist_ok=True)
    map_path = out / "map.ply"
    params_file = out / "params.yaml"
    _write_atomic(params_file, yaml.safe_dump(build_params(options, map_path), sort_keys=False))

    # A 50 ms heartbeat repairs lost fragments of big messages fast (see config/fastdds.xml);
    # a profile the user chose is kept.
    os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(config_path("fastdds.xml")))
    ns = options.namespace
    ros_args = ["--ros-args", "--params-file", str(params_file)] + (["-r", f"__ns:={ns}"] if ns else [])
    context, domain = _open_context(options.domain_id, ros_args)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    executor = MultiThreadedExecutor(num_threads=8, context=context)
    procs: _Processes | None = None
    in_process: list[Any] = []
    t0 = time.monotonic()
    try:
        observer = _Observer(context)
        executor.add_node(observer.node)
        if options.single_process:
            import importlib

            for name in (*GRAPH_NODES, "bag_player"):
                module, cls = NODE_CLASSES[name]
                node = getattr(importlib.import_module(module), cls)(context=context)
                in_process.append(node)
                executor.add_node(node)
        spin = threading.Thread(target=executor.spin, daemon=True)
        spin.start()
        if not options.single_process:
            env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1")
            # Threaded BLAS/OpenMP pools fight over a few shared cores (a 1 ms product took
            # 460 ms under load): one thread per node unless the user asked otherwise.
            for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
                env.setdefault(var, "1")
            procs = _Processes(params_file, ns, env, out / "logs")
            delayed = {n: float(d) for n, d in options.start_delays_s.items() if float(d) > 0}
            for name in GRAPH_NODES:
                if name not in delayed:
                    procs.start(name)
            _wait_for_graph(observer, procs, [n for n in GRAPH_NODES if n not in delayed], t0 + options.timeout_s)
            procs.start("bag_player")
            for name, delay in delayed.items():  # counted from the start of the replay, as kills are
                timer = threading.Timer(delay, procs.start, args=(name,))
                timer.daemon = True
                timer.start()
        elif options.kill_after_s:
            raise ConfigError("fault injection (kill_after_s) needs separate processes")
        summary = _drive(observer, options, procs, out, t0, progress)
        return summary
    finally:
        if procs is not None:
            procs.stop()
        for node in in_process:
            hook = getattr(node, "on_shutdown", None)
            if hook is not None:
                hook()
        executor.shutdown()
        for node in in_process:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


# A topic each node publishes: once the observer sees it, DDS discovery reached that node.
_READY_TOPICS = {"tracker": "memgs/pose", "keyframe_sampler": "memgs/keyframe/seeds",
                 "mapper": "memgs/frame_ack", "merger": "memgs/map/gaussians"}


def _wait_for_graph(obs: _Observer, procs: _Processes, nodes: list[str], deadline: float) -> None:
    """Block until every node in ``nodes`` is discovered, so the first frame reaches all of them."""
    missing = list(nodes)
    while missing:
        procs.check()
        if time.monotonic() > deadline:
            raise PipelineError(f"nodes did not come up: {', '.join(missing)}")
        missing = [n for n in missing if obs.node.count_publishers(_READY_TOPICS[n]) == 0]
        time.sleep(0.1)
    time.sleep(0.5)  # endpoint matching between the nodes themselves settles just after discovery


def _drive(obs: _Observer, options: RunOptions, procs: _Processes | None, out: Path, t0: float,
           progress: bool) -> RunSummary:
    """Wait for the end of the source, finish the mapper, sync the merger, save, summarise."""
    end = t0 + options.timeout_s
    last_log = 0.0
    play_start = time.monotonic()
    kills = dict(options.kill_after_s)
    restarts: dict[str, int] = {}
    if procs is not None:
        unknown = set(kills) - set(GRAPH_NODES)
        if unknown:
            raise ConfigError(f"cannot kill {sorted(unknown)}: nodes are {list(GRAPH_NODES)}")
    while not obs.done.is_set():
        if procs is not None:
            for name, after in list(kills.items()):
                if time.monotonic() - play_start >= after:
                    logger.warning("fault injection: killing %s (SIGKILL) and restarting it", name)
                    procs.kill_and_restart(name)
                    restarts[name] = restarts.get(name, 0) + 1
                    del kills[name]
            procs.check()
        if time.monotonic() > end:
            raise PipelineError(f"the source did not finish within {options.timeout_s:.0f} s")
        if progress and time.monotonic() - last_log > 5.0:
            last_log = time.monotonic()
            logger.info("frames tracked %d, keyframes %d, Gaussians %d, mapping iteration %d",
                        obs.stat("tracker", "poses_out"), obs.stat("tracker", "keyframes"),
                        obs.stat("mapper", "gaussians"), obs.stat("mapper", "iteration"))
        time.sleep(0.1)
    if procs is not None:
        procs.player_reported = True
    if not obs.source_ok:
        # What was played is still mapped and saved; the caller reports the failure.
        logger.error("the source failed part-way (see the bag_player log): finishing and saving the map "
                     "of the frames played")
    if not options.lockstep:
        time.sleep(2.0)  # let the last frames drain through the graph
    logger.info("source finished after %.1f s; finishing the mapper", time.monotonic() - t0)
    final = _parse_kv(obs.call(obs.finish_client, max(60.0, end - time.monotonic())))
    final_seq, gaussians = int(final.get("seq", 0)), int(final.get("gaussians", 0))
    epoch = int(final.get("epoch", 0))
    while (obs.stat("merger", "seq", -1) < final_seq or obs.stat("merger", "resyncing") > 0
           or obs.stat("merger", "epoch", -1) != epoch):
        if procs is not None:
            procs.check()
        if time.monotonic() > end:
            raise PipelineError(f"the merger did not reach delta {final_seq} in time")
        time.sleep(0.1)
    identical, max_diff = _compare_maps(obs, final_seq, epoch, end)
    time.sleep(1.5)  # one more round of the 1 Hz stats, so the summary sees the final counts
    saved = obs.call(obs.save_client, 120.0) if gaussians or final_seq else ""
    ply = saved.split()[0] if saved else ""
    wall = time.monotonic() - t0
    with obs._lock:
        traj = sorted(obs.trajectory, key=lambda p: p[0])
        kfs = sorted(obs.keyframes, key=lambda p: p[0])
    traj_path = out / "trajectory.txt"
    _write_atomic(traj_path, _tum_trajectory(traj))
    _write_atomic(out / "keyframes.txt", _tum_trajectory(kfs))  # poses at insertion
    with obs._lock:
        _write_atomic(out / "stats_timeline.jsonl", "".join(json.dumps(row) + "\n" for row in obs.timeline))
    frames = int(obs.stat("tracker", "frames_in"))
    track_s = obs.stat("tracker", "track_us_total") * 1e-6
    delta_bytes = int(obs.stat("merger", "delta_bytes"))
    return RunSummary(
        source=str(options.source), frames=frames, poses=len(traj),
        keyframes=int(obs.stat("tracker", "keyframes")), gaussians=gaussians,
        tracking_fps=(frames / track_s) if track_s > 0 else 0.0, wall_s=wall, ply_path=ply,
        trajectory_path=str(traj_path), delta_messages=int(obs.stat("merger", "deltas")),
        delta_bytes=delta_bytes, delta_bytes_per_s=delta_bytes / wall if wall > 0 else 0.0,
        lost_frames=int(obs.stat("tracker", "state.LOST")), merger_seq=int(obs.stat("merger", "seq")),
        namespace=options.namespace, domain_id=int(os.environ["ROS_DOMAIN_ID"]),
        mapping_iterations=int(obs.stat("mapper", "iteration")),
        model_bytes_peak=int(obs.stat("mapper", "model_bytes_peak")),
        gaussians_peak=int(obs.stat("mapper", "gaussians_peak")),
        peak_rss_mb={n: obs.stat(n, "peak_rss_mb") for n in GRAPH_NODES},
        merger_resyncs=sum(int(v) for k, v in obs.stats.get("merger", {}).items() if k.startswith("resync.")),
        restarts=restarts,
        replica_identical=identical, replica_max_abs_diff=max_diff, **_render_info(obs.render),
        source_complete=obs.source_ok)


def _compare_maps(obs: _Observer, final_seq: int, epoch: int, end: float) -> tuple[bool, float]:
    """Ask mapper and merger for their whole maps at ``final_seq`` of ``epoch`` and compare them."""
    from memgs_ros.core.map_delta import decode
    from memgs_ros.ros.codecs import pointcloud2_to_structured

    obs.maps.clear()
    obs.call(obs.snapshot_client, 120.0)
    obs.call(obs.publish_map_client, 120.0)
    decoded: dict[str, Any] = {}
    while len(decoded) < 2:
        for name, msg in list(obs.maps.items()):
            m = decode(pointcloud2_to_structured(msg))
            if m.seq >= final_seq and m.epoch == epoch:
                decoded[name] = m
        if time.monotonic() > end:
            raise PipelineError("mapper and merger maps did not arrive for the final comparison")
        time.sleep(0.05)
    a = decoded["mapper"].upserts.select(np.argsort(decoded["mapper"].upserts.ids))
    b = decoded["merger"].upserts.select(np.argsort(decoded["merger"].upserts.ids))
    if len(a) != len(b) or not np.array_equal(a.ids, b.ids):
        return False, float("inf")
    diff = max((float(np.abs(getattr(a, f) - getattr(b, f)).max(initial=0.0))
                for f in ("xyz", "f_dc", "f_rest", "opacity", "scale", "rot")), default=0.0)
    return diff <= 1e-6, diff


def _render_info(msg: Any) -> dict[str, Any]:
    if msg is None:
        return {"render_size": (0, 0), "render_std": 0.0}
    from memgs_ros.ros.codecs import image_to_numpy

    img = image_to_numpy(msg)
    return {"render_size": (int(msg.width), int(msg.height)), "render_std": float(img.std())}


def _tum_trajectory(traj: list[tuple[int, np.ndarray]]) -> str:
    from memgs_ros.core.geometry import pose_to_tq

    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world, memgs_ros tracker)"]
    for stamp, T in traj:
        t, q = pose_to_tq(T)
        sec, nsec = divmod(int(stamp), 1_000_000_000)  # exact ns: the stamps key frames downstream
        lines.append(f"{sec}.{nsec:09d} " + " ".join(f"{v:.9f}" for v in (*t, *q)))
    return "\n".join(lines) + "\n"

"""Benchmark: the drone and the ground station on two hosts, joined by a telemetry-radio link.

The onboard graph (bag_player, tracker, keyframe_sampler, mapper) runs in one Linux network
namespace, the merger and a ground station in another; a veth pair joins them, shaped at both
ends by ``tc ... tbf rate R`` (a telemetry radio). The ground station is a node beside the merger
that does what ``memgs run``'s observer does, from the ground: it watches every node's stats,
views the mapper's live render (``memgs/render/color``), finishes the mapper at the end of the
source, waits for the merger to hold the final map and compares the two maps
(``graph_watch.compare_maps``). DDS discovery is Fast DDS's own multicast, which crosses the veth.

Measured: map-delta bytes (the merger's ``delta_bytes``) against the link rate, mean and peak
(1 s); every byte on the wire from air to ground (the ground veth's counters); the time from the
last frame until the merger holds the mapper's final map (the merger's 1 Hz stats: +-1 s);
whether the two maps are identical, and their largest difference.

Needs root, iproute2 (``ip``, ``tc``) and a kernel with network namespaces, veth and tbf. The
namespaces and every process in them are removed at the end, also on error or Ctrl-C.

    python test/system/harness/bench_two_hosts.py --rate 5 --frames 100
    python test/system/harness/bench_two_hosts.py --source synthetic:w=320,h=240,n=60,seed=0 --drop-every 5 \
        --json two_hosts.json
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import itertools
import json
import os
import random
import re
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import Image, PointCloud2
from std_msgs.msg import Bool
from std_srvs.srv import Trigger

from memgs_ros.cli.run import check_inputs, guess_config
from memgs_ros.core.map_io.answers import MapAnswer
from memgs_ros.core.runtime.cpu import MALLOC_ARENAS, PARENT_PID_ENV, die_with_parent
from memgs_ros.errors import MemgsError, PipelineError
from memgs_ros.nodes.bag_player.node import LINGER_S
from memgs_ros.nodes.registry import GRAPH, NODES
from memgs_ros.orchestration.graph_watch import compare_maps, wait_for_graph
from memgs_ros.orchestration.processes import (
    NodeProcesses,
    open_context,
    spin_in_background,
    stop_spinning,
)
from memgs_ros.orchestration.run_files import LOGS_DIR, MAP_FILE, PARAMS_FILE, RunOptions, build_params, config_path
from memgs_ros.orchestration.signals import exit_status, stop_on_signals
from memgs_ros.ros import qos
from memgs_ros.ros.diagnostics import stats_values
from memgs_ros.testing.delta_relay import LOSSY_MERGER, DeltaRelay

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks"))  # benchmarks/ (not a package): _common
from _common import TUM_ENV, tum_path, write_results  # noqa: E402

ONBOARD = ("bag_player", "tracker", "keyframe_sampler", "mapper")  # the drone; the merger is on the ground
ADDRESSES = ("10.77.0.1", "10.77.0.2")  # air, ground: the namespaces are private, any subnet will do
# tbf: 4 KB of burst (a few packets at once, as a radio modem sends) and at most 400 ms queued
# before the link drops, as a modem's buffer would.
TBF_BURST, TBF_LATENCY = "32kbit", "400ms"
FASTDDS_NS = "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"
GROUND_TRANSPORT = "memgs_ground_udp"


# ---------------------------------------------------------------------------------------- the link

def _cmd(*args: str) -> str:
    """Run a command; its stdout, or RuntimeError with its stderr."""
    p = subprocess.run(args, capture_output=True, text=True, timeout=30)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(args)}: {p.stderr.strip() or f'exit {p.returncode}'}")
    return p.stdout


def netns_unavailable_reason() -> str | None:
    """Why two shaped namespaces cannot be made here (None: they can): tried, then removed."""
    if not sys.platform.startswith("linux"):
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "creating network namespaces needs root"
    missing = [t for t in ("ip", "tc") if shutil.which(t) is None]
    if missing:
        return f"iproute2 is not installed (no {', '.join(missing)})"
    try:
        with Link(1.0):
            pass
    except (RuntimeError, OSError, subprocess.SubprocessError) as err:
        return f"cannot create a shaped veth between two network namespaces: {err}"
    return None


class Link:
    """Two network namespaces, air and ground, joined by a veth pair whose two ends are each
    shaped by tbf at ``rate_mbit`` (both directions: acknowledgements and service calls also
    cross the radio). On exit every process still in either namespace is killed, by pid (all
    were started by this run), and both namespaces are deleted, which deletes the veth."""

    def __init__(self, rate_mbit: float) -> None:
        tag = secrets.token_hex(3)  # names of this run only: another run on the host uses its own
        self.air, self.ground = f"mgair{tag}", f"mggnd{tag}"
        self.dev = {self.air: f"mgva{tag}", self.ground: f"mgvg{tag}"}  # <= 15 characters
        self.rate_mbit = rate_mbit
        self.leftover: list[int] = []  # processes teardown had to kill (none when the run stopped its nodes)

    def __enter__(self) -> Link:
        try:
            for ns in (self.air, self.ground):
                _cmd("ip", "netns", "add", ns)
            _cmd("ip", "link", "add", self.dev[self.air], "type", "veth", "peer", "name", self.dev[self.ground])
            for ns, address in zip((self.air, self.ground), ADDRESSES):
                dev = self.dev[ns]
                _cmd("ip", "link", "set", dev, "netns", ns)
                _cmd("ip", "-n", ns, "addr", "add", f"{address}/24", "dev", dev)
                _cmd("ip", "-n", ns, "link", "set", "lo", "up")
                _cmd("ip", "-n", ns, "link", "set", dev, "up")
                _cmd("tc", "-n", ns, "qdisc", "add", "dev", dev, "root", "tbf", "rate", f"{self.rate_mbit:g}mbit",
                     "burst", TBF_BURST, "latency", TBF_LATENCY)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def pids(self, ns: str) -> list[int]:
        p = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True, timeout=30)
        return [int(x) for x in p.stdout.split()] if p.returncode == 0 else []

    def qdisc(self, ns: str) -> dict[str, int]:
        """The tbf's counters at one end: bytes and packets sent, drops, overlimits."""
        rows = json.loads(_cmd("tc", "-n", ns, "-s", "-j", "qdisc", "show", "dev", self.dev[ns]))
        tbf = next(r for r in rows if r.get("kind") == "tbf")
        return {k: int(tbf.get(k, 0)) for k in ("bytes", "packets", "drops", "overlimits")}

    def close(self) -> None:
        for ns in (self.air, self.ground):
            pids = self.pids(ns)
            self.leftover += pids
            for pid in pids:
                with contextlib.suppress(ProcessLookupError):  # it ended meanwhile
                    os.kill(pid, signal.SIGKILL)
        end = time.monotonic() + 10.0
        while any(self.pids(ns) for ns in (self.air, self.ground)) and time.monotonic() < end:
            time.sleep(0.1)
        for ns in (self.air, self.ground):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)


class WireMeter:
    """Bytes through the ground end of the veth (``/proc/<pid>/net/dev`` of a process in the ground
    namespace), 10 times a second: rx = air to ground, tx = ground to air. Reading a file costs
    far less than running ``tc`` ten times a second on two shared cores."""

    def __init__(self, pid: int, dev: str) -> None:
        self.samples: list[tuple[float, int, int]] = []  # (monotonic s, rx bytes, tx bytes)
        self._path, self._dev = Path(f"/proc/{pid}/net/dev"), dev
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> WireMeter:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            try:
                text = self._path.read_text()
            except OSError:  # the process ended
                return
            for line in text.splitlines():
                name, _, values = line.partition(":")
                if name.strip() == self._dev:
                    v = values.split()
                    self.samples.append((time.monotonic(), int(v[0]), int(v[8])))


def write_profiles(out: Path, namespace: str = "", pace_kbytes_per_s: float = 0.0) -> dict[str, str]:
    """Fast DDS profiles of the two sides, from the profile a run uses (the user's
    FASTRTPS_DEFAULT_PROFILES_FILE, else config/fastdds.xml). The ground station's has UDPv4 as its
    only transport. Why: the namespaces share /dev/shm, and a ground participant offering shared
    memory could be reached past the shaped link, which a real ground station, with only the radio
    between, never is. The drone's is that profile as it is, or with ``pace_kbytes_per_s`` > 0
    config/fastdds_radio.xml paced at that rate (kB/s), and ``paced`` is set: the mapper then
    needs asynchronous writers."""
    base = Path(os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE") or config_path("fastdds.xml"))
    ET.register_namespace("", FASTDDS_NS)
    tree = ET.parse(base)
    root = tree.getroot()

    def q(tag: str) -> str:
        return f"{{{FASTDDS_NS}}}{tag}"

    def child(parent: ET.Element, tag: str, **attrib: str) -> ET.Element:
        found = parent.find(q(tag))
        return found if found is not None else ET.SubElement(parent, q(tag), attrib)

    if root.tag != q("profiles"):
        raise PipelineError(f"{base}: expected a Fast DDS <profiles> document, found <{root.tag}>")
    descriptor = ET.SubElement(child(root, "transport_descriptors"), q("transport_descriptor"))
    ET.SubElement(descriptor, q("transport_id")).text = GROUND_TRANSPORT
    ET.SubElement(descriptor, q("type")).text = "UDPv4"
    participant = next((p for p in root.findall(q("participant")) if p.get("is_default_profile") == "true"), None)
    if participant is None:
        participant = ET.SubElement(root, q("participant"),
                                    {"profile_name": "memgs_ground", "is_default_profile": "true"})
    rtps = child(participant, "rtps")
    for tag in ("userTransports", "useBuiltinTransports"):
        for old in rtps.findall(q(tag)):
            rtps.remove(old)
    ET.SubElement(ET.SubElement(rtps, q("userTransports")), q("transport_id")).text = GROUND_TRANSPORT
    ET.SubElement(rtps, q("useBuiltinTransports")).text = "false"
    ground = out / "fastdds_ground.xml"
    ET.indent(tree)
    tree.write(ground, xml_declaration=True, encoding="UTF-8")
    if pace_kbytes_per_s <= 0:
        return {"air": str(base.resolve()), "ground": str(ground.resolve())}
    # The drone's: the package's radio profile, its flow controller set to the pace and its
    # per-topic writer profiles moved under the run's namespace (they are named by topic).
    tree = ET.parse(config_path("fastdds_radio.xml"))
    root = tree.getroot()
    for fc in root.iter(q("flow_controller_descriptor")):
        period_ms = int(fc.findtext(q("period_ms")) or 100)
        child(fc, "max_bytes_per_period").text = str(int(pace_kbytes_per_s * period_ms))
    for w in root.findall(q("data_writer")):
        if w.get("profile_name", "").startswith("/"):
            w.set("profile_name", namespace + w.get("profile_name", ""))
    air = out / "fastdds_air.xml"
    ET.indent(tree)
    tree.write(air, xml_declaration=True, encoding="UTF-8")
    return {"air": str(air.resolve()), "ground": str(ground.resolve()), "paced": "1"}


# ------------------------------------------------------------------- the ground station (in its namespace)

class TwoHostProcesses(NodeProcesses):
    """The runner's node processes (its check and stop), with the onboard nodes started in the
    drone's namespace through ``ip netns exec``, which execs the node (same pid: the runner's
    signals and the node's PR_SET_PDEATHSIG still work), and each side on its own DDS profile."""

    def __init__(self, params_file: Path, namespace: str, env: dict[str, str], log_dir: Path, air_netns: str,
                 profiles: Mapping[str, str]) -> None:
        super().__init__(params_file, namespace, env, log_dir)
        self._cmd_tail = ["--ros-args", "--params-file", str(params_file), "-r", f"__ns:={namespace}"]
        self._node_env = dict(env, **{PARENT_PID_ENV: str(os.getpid())})
        self._air, self._profiles = air_netns, dict(profiles)

    def start(self, name: str) -> None:
        side = "air" if name in ONBOARD else "ground"
        cmd = [sys.executable, "-m", NODES[name][0], *self._cmd_tail]
        if side == "air":
            cmd = ["ip", "netns", "exec", self._air, *cmd]
        profile = self._profiles[side]
        env = dict(self._node_env, FASTRTPS_DEFAULT_PROFILES_FILE=profile, FASTDDS_DEFAULT_PROFILES_FILE=profile)
        if name == "mapper" and self._profiles.get("paced"):
            # A flow controller needs an asynchronous writer; rmw_fastrtps makes every writer
            # synchronous unless told otherwise (its default since Iron).
            env["RMW_FASTRTPS_PUBLICATION_MODE"] = "ASYNCHRONOUS"
        with open(self.log_dir / f"{name}.log", "wb") as log:  # the child keeps its own descriptor
            self.procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                                start_new_session=True)


class GroundStation:
    """The ground station's node beside the merger: the drone's pose, every node's stats, the
    player's end, the mapper's live render (a user viewing it from the ground), and the services
    that end a run. The mapper's snapshots are subscribed to only for the final comparison: subscribed from the
    start, the snapshot that ends the run would cross the link twice (to the merger and here)."""

    def __init__(self, context: Any, render_view: bool) -> None:
        self.node = Node("memgs_ground_station", context=context)
        self.done_at: float | None = None
        self.done_ok = True
        self.first_pose_at: float | None = None  # the first frame tracked, as seen from the ground
        self.poses = 0
        self.stats: dict[str, dict[str, str]] = {}
        self.merger_rows: list[tuple[float, dict[str, str]]] = []  # (arrival, values) of every merger stats
        self.maps: dict[str, PointCloud2] = {}  # "mapper", "merger": the last whole map of each (compare_maps)
        self.render_views = 0
        self.render_bytes = 0
        self._snapshots: Any = None
        self.node.create_subscription(Bool, "memgs/player/done", self._on_done, qos.latched())
        self.node.create_subscription(PoseStamped, "memgs/pose", self._on_pose, qos.reliable(10))
        for name in (*GRAPH, "player"):
            self.node.create_subscription(DiagnosticArray, f"memgs/{name}/stats",
                                          lambda m, n=name: self._on_stats(n, m), qos.reliable(5))
        self.node.create_subscription(PointCloud2, "memgs/map/gaussians",
                                      lambda m: self.maps.__setitem__("merger", m), qos.latched())
        if render_view:
            self.node.create_subscription(Image, "memgs/render/color", self._on_render, qos.reliable(2))
        self.finish_client = self.node.create_client(Trigger, "memgs/mapper/finish")
        self.snapshot_client = self.node.create_client(Trigger, "memgs/mapper/publish_snapshot")
        self.publish_map_client = self.node.create_client(Trigger, "memgs/merger/publish_map")

    def _on_done(self, msg: Bool) -> None:
        self.done_ok = bool(msg.data)
        self.done_at = time.monotonic()

    def _on_pose(self, _msg: PoseStamped) -> None:
        self.poses += 1
        if self.first_pose_at is None:
            self.first_pose_at = time.monotonic()

    def _on_stats(self, name: str, msg: DiagnosticArray) -> None:
        values = stats_values(msg)
        self.stats[name] = values
        if name == "merger":
            self.merger_rows.append((time.monotonic(), values))

    def _on_render(self, msg: Image) -> None:
        self.render_views += 1
        self.render_bytes += len(msg.data)

    def watch_mapper_snapshots(self) -> None:
        self._snapshots = self.node.create_subscription(
            PointCloud2, "memgs/mapper/snapshot", lambda m: self.maps.__setitem__("mapper", m), qos.latched())

    def call(self, client: Any, timeout_s: float) -> str:
        """Call a Trigger service, return its message; PipelineError if it fails or times out."""
        if not client.wait_for_service(timeout_sec=min(timeout_s, 30.0)):
            raise PipelineError(f"service {client.srv_name} is not available")
        future = client.call_async(Trigger.Request())
        end = time.monotonic() + timeout_s
        while not future.done():
            if time.monotonic() > end:
                raise PipelineError(f"service {client.srv_name} did not answer within {timeout_s:.0f} s")
            time.sleep(0.02)
        res = future.result()
        if not res.success:
            raise PipelineError(f"service {client.srv_name} failed: {res.message}")
        return res.message

    def converged_at(self, seq: int, epoch: int) -> float | None:
        """When the merger's stats first showed it holding ``seq`` of ``epoch``, not resynchronising."""
        for t, v in list(self.merger_rows):
            if (int(float(v.get("seq", -1))) >= seq and int(float(v.get("epoch", -1))) == epoch
                    and float(v.get("resyncing", 1)) == 0):
                return t
        return None


def node_env(domain_id: int) -> dict[str, str]:
    """The nodes' environment, as ``memgs run`` gives it (one BLAS thread, two malloc arenas), on
    the run's domain, with discovery beyond localhost: a LOCALHOST range inherited from the shell
    would keep the two hosts from ever seeing each other."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED="1", ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET")
    for var in ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS"):
        env.pop(var, None)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(var, "1")
    env.setdefault("MALLOC_ARENA_MAX", str(MALLOC_ARENAS))
    return env


def ground_station(spec: Mapping[str, Any]) -> dict[str, Any]:
    """Run the graph from the ground namespace (this process is in it): start the merger here and
    the onboard nodes in the air namespace, replay the source, finish the mapper, wait for the
    merger, compare the maps. Times are time.monotonic() (one clock for the whole host)."""
    out, ns = Path(spec["out_dir"]), spec["namespace"]
    env = node_env(spec["domain_id"])
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    for var in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE"):
        os.environ[var] = spec["profiles"]["ground"]
    context, _ = open_context(spec["domain_id"], ["--ros-args", "-r", f"__ns:={ns}"])
    executor = SingleThreadedExecutor(context=context)
    procs: TwoHostProcesses | None = None
    spin: threading.Thread | None = None
    end = time.monotonic() + spec["timeout_s"]
    try:
        gs = GroundStation(context, spec["render_view"])
        # Loss on the link: the deltas reach the merger through a relay here that drops every n-th.
        relay = DeltaRelay(gs.node, int(spec.get("drop_every", 0))) if spec.get("drop_every") else None
        executor.add_node(gs.node)
        spin = spin_in_background(executor)
        procs = TwoHostProcesses(Path(spec["params_file"]), ns, env, out / LOGS_DIR, spec["air_netns"],
                                 spec["profiles"])
        for name in GRAPH:  # sinks first, as the runner starts them
            procs.start(name)
        try:
            wait_for_graph(gs, procs, GRAPH, end)
        except PipelineError as err:
            raise PipelineError(f"{err} (seen from the ground namespace: DDS discovery over the veth)") from err
        procs.start("bag_player")
        t_play = time.monotonic()
        player = procs.procs["bag_player"]
        exits: list[float] = []  # when the player process ended, seen here at once

        def watch_player() -> None:
            while player.poll() is None:
                time.sleep(0.02)
            exits.append(time.monotonic())

        threading.Thread(target=watch_player, daemon=True).start()
        while gs.done_at is None and not exits:
            procs.check()  # a node that died ends the run with its log; the player's exit 0 is its end
            if time.monotonic() > end:
                raise PipelineError(f"the source did not finish within {spec['timeout_s']:.0f} s")
            time.sleep(0.02)
        if gs.done_at is None:
            procs.check()  # the player ended without its done message: only exit 0 is the source's end
        procs.player_reported = True
        t_finish = time.monotonic()
        final = MapAnswer.parse(gs.call(gs.finish_client, max(60.0, end - time.monotonic())))
        t_finished = time.monotonic()
        final_seq, epoch = final.seq, final.epoch or 0
        while (t_conv := gs.converged_at(final_seq, epoch)) is None:
            procs.check()
            if time.monotonic() > end:
                raise PipelineError(f"the merger did not reach delta {final_seq} in time")
            time.sleep(0.05)
        # The last frame: the done message crosses the link (behind queued deltas when it is busy);
        # the player's exit, LINGER_S after it sent done, is seen here at once. The earlier of the two.
        t_last = min([t for t in (gs.done_at,) if t is not None] + [t - LINGER_S for t in exits[:1]])
        gs.watch_mapper_snapshots()
        identical, max_diff = compare_maps(gs, final_seq, epoch, end)
        t_compared = time.monotonic()
        return {
            "t_first": gs.first_pose_at or t_play, "t_last": t_last, "t_finish": t_finish, "t_finished": t_finished,
            "t_conv": t_conv, "t_compared": t_compared, "poses": gs.poses, "final_seq": final_seq,
            "gaussians": final.gaussians,
            "identical": identical, "max_abs_diff": max_diff, "source_ok": gs.done_ok, "stats": gs.stats,
            "merger_series": [(t, float(v.get("delta_bytes", 0)), int(float(v.get("deltas", 0))))
                              for t, v in gs.merger_rows],
            "render_views": gs.render_views, "render_bytes": gs.render_bytes,
            "dropped_deltas": relay.dropped if relay is not None else 0,
        }
    finally:
        if procs is not None:
            procs.stop()  # SIGINT: the merger saves its PLY, the mapper its checkpoint
        stop_spinning(executor, spin)
        rclpy.try_shutdown(context=context)


def _ground_station_main(spec_path: Path) -> int:
    spec = json.loads(spec_path.read_text())
    if not die_with_parent(int(spec["parent_pid"])):  # the benchmark is gone already
        return 1
    result_path = Path(spec["result_path"])
    try:
        with stop_on_signals():  # SIGTERM from the benchmark: stop the nodes in order (finally)
            result: dict[str, Any] = ground_station(spec)
    except (PipelineError, KeyboardInterrupt) as err:
        result = {"error": f"{type(err).__name__}: {err}"}
    write_results(result_path, result)
    return 0 if "error" not in result else 1


# ------------------------------------------------------------------------------------ the benchmark

@dataclass(frozen=True)
class TwoHostsOptions:
    source: str = field(default_factory=lambda: str(tum_path(check=False)))  # $MEMGS_TUM or the fr1/rpy head
    frames: int = 100  # the player's max_frames (0 = the whole source)
    rate_mbit: float = 5.0  # the link, each way
    config: str = ""  # "" = from the source's name, as memgs run guesses it
    overrides: Mapping[str, Any] = field(default_factory=dict)  # "node.param" -> value
    drop_every: int = 0  # a relay before the merger drops every n-th delta (loss on the link; 0 = none)
    render_view: bool = True  # a ground subscriber to the mapper's live render
    # The mapper's writers that cross the link (deltas, snapshots, render) paced by config/fastdds_radio.xml's
    # flow controller at this rate: None = 90 % of the link, as that profile; 0 = unpaced (config/fastdds.xml).
    pace_kbytes_per_s: float | None = None
    out_dir: Path | None = None  # None = a new temporary folder (kept: logs, params, map)
    domain_id: int | None = None  # None = a random one
    timeout_s: float = 1800.0


@dataclass(frozen=True)
class TwoHostsResult:
    link_mbit: float
    source: str
    frames: int  # frames the tracker took in
    source_complete: bool  # False: the player reported a source that failed part-way
    poses_on_ground: int  # its poses that reached the ground station
    keyframes: int
    gaussians: int
    delta_messages: int
    delta_bytes: int  # payload of every delta the merger received (its delta_bytes)
    # Delta rates as the merger took them in: a message counts when it is complete, so over 1 s
    # one big message (the exact flush) or a burst released by a repaired fragment reads as
    # several times the link; the peak is therefore over 10 s, beside the largest single delta.
    delta_replay_bytes_per_s: float  # mean from the first frame to the last
    delta_mean_bytes_per_s: float  # mean from the first frame until the merger holds the final map
    delta_peak_bytes_per_s: float  # over 10 s windows
    delta_largest_bytes: int  # the largest delta (between two merger stats with one delta in)
    wire_bytes: int  # everything air -> ground on the veth: deltas, snapshots, renders, stats, DDS
    wire_replay_bytes_per_s: float  # mean from the first frame to the last
    wire_mean_bytes_per_s: float  # mean from the first frame until the merger holds the final map
    wire_peak_bytes_per_s: float  # over 1 s
    saturated_s: float  # seconds in 1 s windows with the air -> ground wire at >= 90 % of the link
    wire_bytes_up: int  # ground -> air (acknowledgements, service calls)
    tbf_drops: dict[str, int]  # packets the shaper dropped, per end (queue over TBF_LATENCY)
    render_views: int
    render_bytes: int
    replay_s: float  # first frame (its pose on the ground) until the last
    finish_s: float  # the finish service: final iterations, exact flush, snapshot (onboard; called from the ground)
    final_training_s: float  # of which the final iterations (the mapper's log; nan if not found)
    convergence_s: float  # last frame until the merger's stats show the final map
    identical: bool  # merger's map == mapper's map (same ids, parameters within 1e-6)
    max_abs_diff: float
    merger_resyncs: int
    fault_dropped_deltas: int
    leftover_processes: int  # processes teardown had to kill (0: every node stopped when asked)
    netns: tuple[str, str]  # (air, ground), deleted at the end
    out_dir: str
    # The final iterations' end (finish called + their time) until the merger's stats show the final
    # map: the flush crossing the link (nan in results saved before it was measured).
    after_final_map_s: float = float("nan")
    pace_kbytes_per_s: float = 0.0  # the mapper's link writers paced to this (0: unpaced)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def rates(samples: Sequence[tuple[float, float]], window_s: float) -> list[float]:
    """Bytes per second of a growing byte counter over consecutive windows of >= ``window_s``."""
    out: list[float] = []
    i = 0
    for j in range(1, len(samples)):
        dt = samples[j][0] - samples[i][0]
        if dt >= window_s:
            out.append((samples[j][1] - samples[i][1]) / dt)
            i = j
    return out


def _between(samples: Sequence[tuple[float, float]], t0: float, t1: float) -> float:
    """Counter growth between t0 and t1 (the last sample at or before each)."""
    def at(t: float) -> float:
        before = [v for s, v in samples if s <= t]
        return before[-1] if before else (samples[0][1] if samples else 0.0)
    return at(t1) - at(t0)


def run_two_hosts(opts: TwoHostsOptions) -> TwoHostsResult:
    """Run the graph across the shaped link and measure it (see the module docstring)."""
    reason = netns_unavailable_reason()
    if reason is not None:
        raise PipelineError(reason)
    out = Path(opts.out_dir or tempfile.mkdtemp(prefix="memgs_two_hosts_")).resolve()
    (out / LOGS_DIR).mkdir(parents=True, exist_ok=True)
    config = opts.config or guess_config(opts.source)
    overrides = dict(opts.overrides)
    if opts.drop_every:  # the merger reads the deltas through the ground station's lossy relay
        overrides.update(LOSSY_MERGER)
    # As memgs run does before any node starts: a misspelt --set or a source that does not open
    # is one line here, not a node failing across the link.
    for warning in check_inputs(opts.source, config, opts.frames, overrides):
        print(f"warning: {warning}", file=sys.stderr)
    namespace = f"/memgs_2h_{os.getpid()}_{secrets.token_hex(3)}"
    domain = opts.domain_id if opts.domain_id is not None else random.randrange(100, 200)
    params = build_params(RunOptions(source=opts.source, config=config, out_dir=out, namespace=namespace,
                                     domain_id=domain, max_frames=opts.frames, overrides=overrides,
                                     timeout_s=opts.timeout_s), out / MAP_FILE)
    (out / PARAMS_FILE).write_text(yaml.safe_dump(params, sort_keys=False))
    result_path = out / "two_hosts_ground.json"
    result_path.unlink(missing_ok=True)
    pace = _pace(opts)
    qdisc: dict[str, dict[str, int]] = {}
    with Link(opts.rate_mbit) as link:
        spec = {"parent_pid": os.getpid(), "out_dir": str(out), "namespace": namespace, "domain_id": domain,
                "params_file": str(out / PARAMS_FILE), "air_netns": link.air,
                "profiles": write_profiles(out, namespace, pace),
                "render_view": opts.render_view, "timeout_s": opts.timeout_s, "result_path": str(result_path),
                "drop_every": opts.drop_every}
        spec_path = out / "two_hosts_spec.json"
        spec_path.write_text(json.dumps(spec, indent=1))
        driver: subprocess.Popen | None = None
        meter: WireMeter | None = None
        try:
            with open(out / LOGS_DIR / "ground_station.log", "wb") as log:
                driver = subprocess.Popen(
                    ["ip", "netns", "exec", link.ground, sys.executable, str(Path(__file__).resolve()),
                     "--ground-station", str(spec_path)],
                    stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"),
                    start_new_session=True)
            meter = WireMeter(driver.pid, link.dev[link.ground]).start()
            driver.wait(timeout=opts.timeout_s + 120.0)
        finally:
            if driver is not None and driver.poll() is None:
                driver.send_signal(signal.SIGTERM)  # it stops its nodes in order
                try:
                    driver.wait(timeout=45.0)
                except subprocess.TimeoutExpired:
                    driver.kill()
                    driver.wait()
            if meter is not None:
                meter.stop()
            for side, ns in (("air", link.air), ("ground", link.ground)):
                try:
                    qdisc[side] = link.qdisc(ns)
                except (RuntimeError, StopIteration, ValueError):
                    qdisc[side] = {}
    if not result_path.exists():
        tail = (out / LOGS_DIR / "ground_station.log").read_text(errors="replace").splitlines()[-20:]
        raise PipelineError("the ground station ended without a result:\n  " + "\n  ".join(tail))
    raw = json.loads(result_path.read_text())
    if "error" in raw:
        raise PipelineError(f"{raw['error']} (logs in {out / LOGS_DIR})")
    return _result(opts, raw, meter.samples if meter else [], qdisc, link, out)


def _result(opts: TwoHostsOptions, raw: Mapping[str, Any], wire: Sequence[tuple[float, int, int]],
            qdisc: Mapping[str, Mapping[str, int]], link: Link, out: Path) -> TwoHostsResult:
    stats: dict[str, dict[str, str]] = raw["stats"]

    def stat(node: str, key: str) -> int:
        return int(float(stats.get(node, {}).get(key, 0)))

    t0, t1 = raw["t_first"], raw["t_conv"]
    link_bytes_per_s = opts.rate_mbit * 1e6 / 8
    series = raw["merger_series"]
    deltas = [(float(t), float(b)) for t, b, _ in series]
    singles = [b1 - b0 for (_, b0, n0), (_, b1, n1) in itertools.pairwise(series) if n1 == n0 + 1]
    t_last = raw["t_last"]
    down = [(t, float(rx)) for t, rx, _ in wire]
    up = [(t, float(tx)) for t, _, tx in wire]
    wire_rates = rates([s for s in down if t0 <= s[0] <= t1], 1.0)
    return TwoHostsResult(
        link_mbit=opts.rate_mbit, pace_kbytes_per_s=_pace(opts), source=opts.source,
        frames=stat("tracker", "frames_in"),
        source_complete=bool(raw["source_ok"]), poses_on_ground=int(raw["poses"]),
        keyframes=stat("tracker", "keyframes"), gaussians=int(raw["gaussians"]),
        delta_messages=stat("merger", "deltas"), delta_bytes=stat("merger", "delta_bytes"),
        delta_replay_bytes_per_s=_between(deltas, t0, t_last) / max(t_last - t0, 1e-9),
        delta_mean_bytes_per_s=_between(deltas, t0, t1) / max(t1 - t0, 1e-9),
        delta_peak_bytes_per_s=max(rates(deltas, 10.0), default=0.0), delta_largest_bytes=int(max(singles, default=0)),
        wire_bytes=int(_between(down, t0, t1)),
        wire_replay_bytes_per_s=_between(down, t0, t_last) / max(t_last - t0, 1e-9),
        wire_mean_bytes_per_s=_between(down, t0, t1) / max(t1 - t0, 1e-9),
        wire_peak_bytes_per_s=max(wire_rates, default=0.0),
        saturated_s=float(sum(r >= 0.9 * link_bytes_per_s for r in wire_rates)),
        wire_bytes_up=int(_between(up, t0, t1)),
        tbf_drops={side: q.get("drops", 0) for side, q in qdisc.items()},
        render_views=int(raw["render_views"]), render_bytes=int(raw["render_bytes"]),
        replay_s=t_last - t0, finish_s=raw["t_finished"] - raw["t_finish"], final_training_s=_final_training_s(out),
        convergence_s=t1 - t_last,
        after_final_map_s=t1 - (raw["t_finish"] + _final_training_s(out)), identical=bool(raw["identical"]),
        max_abs_diff=float(raw["max_abs_diff"]),
        merger_resyncs=sum(int(float(v)) for k, v in stats.get("merger", {}).items() if k.startswith("resync.")),
        fault_dropped_deltas=int(raw.get("dropped_deltas", 0)), leftover_processes=len(link.leftover),
        netns=(link.air, link.ground), out_dir=str(out))


def _pace(opts: TwoHostsOptions) -> float:
    """The mapper's link writers' pace, kB/s: 90 % of the link unless set (0: unpaced)."""
    return 0.9 * opts.rate_mbit * 1e3 / 8 if opts.pace_kbytes_per_s is None else float(opts.pace_kbytes_per_s)


def _final_training_s(out: Path) -> float:
    """The final iterations' time, from the mapper's log line "final N iterations in S s"."""
    log = out / LOGS_DIR / "mapper.log"
    text = log.read_text(errors="replace") if log.is_file() else ""
    found = re.findall(r"final \d+ iterations in ([0-9.]+) s", text)
    return float(found[-1]) if found else float("nan")


def table(r: TwoHostsResult) -> str:
    """The result as a Markdown table."""
    link = r.link_mbit * 1e6 / 8

    def rate(b: float) -> str:
        return f"{b / 1e3:.1f} kB/s = {100 * b / link:.0f} % of the link"

    rows = [
        ("link rate (tbf, each way)", f"{r.link_mbit:g} Mbit/s = {link / 1e3:.1f} kB/s"),
        ("mapper's link writers paced to (config/fastdds_radio.xml)",
         f"{r.pace_kbytes_per_s:.1f} kB/s = {100 * r.pace_kbytes_per_s * 1e3 / link:.0f} % of the link"
         if r.pace_kbytes_per_s else "unpaced"),
        ("frames tracked / poses on the ground / keyframes",
         f"{r.frames} / {r.poses_on_ground} / {r.keyframes}" + ("" if r.source_complete else " (source failed)")),
        ("map deltas received", f"{r.delta_messages} messages, {r.delta_bytes / 1e6:.2f} MB"),
        ("delta rate, mean over the replay", rate(r.delta_replay_bytes_per_s)),
        ("delta rate, mean first frame to merger converged", rate(r.delta_mean_bytes_per_s)),
        ("delta rate, peak (10 s, as the merger took them in)", rate(r.delta_peak_bytes_per_s)),
        ("largest single delta", f"{r.delta_largest_bytes / 1e6:.2f} MB = {r.delta_largest_bytes / link:.1f} s "
                                 "of the link"),
        ("wire air->ground, mean over the replay", rate(r.wire_replay_bytes_per_s)),
        ("wire air->ground, mean first frame to converged", f"{rate(r.wire_mean_bytes_per_s)} "
                                                            f"({r.wire_bytes / 1e6:.2f} MB)"),
        ("wire air->ground, peak (1 s)", rate(r.wire_peak_bytes_per_s)),
        ("wire air->ground besides deltas and renders (snapshots, stats, DDS)",
         f"{(r.wire_bytes - r.delta_bytes - r.render_bytes) / 1e6:.2f} MB"),
        ("link saturated (1 s windows >= 90 %)", f"{r.saturated_s:.0f} s"),
        ("wire ground->air", f"{r.wire_bytes_up / 1e6:.2f} MB"),
        ("tbf drops air / ground end", f"{r.tbf_drops.get('air', 0)} / {r.tbf_drops.get('ground', 0)} packets"),
        ("live render views on the ground", f"{r.render_views} ({r.render_bytes / 1e6:.2f} MB)"),
        ("replay, first to last frame", f"{r.replay_s:.1f} s"),
        ("finish call (final iterations, exact flush, snapshot; over the link)",
         f"{r.finish_s:.1f} s, of which final iterations {r.final_training_s:.1f} s"),
        ("convergence after the last frame (merger stats, +-1 s)", f"{r.convergence_s:.1f} s"),
        ("of which after the final iterations (the flush crossing the link)",
         f"{r.after_final_map_s:.1f} s"),
        ("merger == mapper", f"{'yes' if r.identical else 'NO'} ({r.gaussians} Gaussians)"),
        ("max abs diff", f"{r.max_abs_diff:.3g}"),
        ("merger resyncs / deltas dropped (fault injection)", f"{r.merger_resyncs} / {r.fault_dropped_deltas}"),
        ("processes left at teardown", str(r.leftover_processes)),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"| {'quantity':<{width}} | value |", f"| {'-' * width} | --- |"]
    lines += [f"| {k:<{width}} | {v} |" for k, v in rows]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rate", type=float, default=5.0, help="link rate each way, Mbit/s (default 5)")
    p.add_argument("--frames", type=int, default=100, help="frames to play (0 = all; default 100)")
    p.add_argument("--source", default=str(tum_path(check=False)),
                   help=f"TUM folder, bag or synthetic spec (default: ${TUM_ENV}, else the shared fr1/rpy head)")
    p.add_argument("--config", default="", help="node config (default: from the source's name, as memgs run)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", help="override a parameter")
    p.add_argument("--drop-every", type=int, default=0, help="the merger ignores every n-th delta (0 = none)")
    p.add_argument("--pace", type=float, default=None, metavar="KB/S",
                   help="pace the mapper's writers that cross the link (config/fastdds_radio.xml; "
                        "default 90%% of the link; 0 = unpaced, config/fastdds.xml)")
    p.add_argument("--no-render-view", action="store_true", help="no ground subscriber to the live render")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: a new temporary one)")
    p.add_argument("--domain-id", type=int, default=None)
    p.add_argument("--timeout", type=float, default=1800.0)
    p.add_argument("--json", type=Path, default=None, help="also write the result as JSON here")
    p.add_argument("--table", type=Path, default=None, metavar="JSON", help="print the table of a saved run and exit")
    p.add_argument("--ground-station", type=Path, default=None, help=argparse.SUPPRESS)  # the inner process
    args = p.parse_args(argv)
    if args.table is not None:
        saved = json.loads(args.table.read_text())["result"]
        fields = {f.name for f in dataclasses.fields(TwoHostsResult)}
        print(table(TwoHostsResult(**{k: (tuple(v) if isinstance(v, list) else v)
                                      for k, v in saved.items() if k in fields})), end="")
        return 0
    if args.ground_station is not None:
        return _ground_station_main(args.ground_station)
    overrides = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            p.error(f"--set needs NODE.PARAM=VALUE, got '{item}'")
        overrides[key.strip()] = yaml.safe_load(value)
    opts = TwoHostsOptions(source=args.source, frames=args.frames, rate_mbit=args.rate, config=args.config,
                           overrides=overrides, drop_every=args.drop_every, render_view=not args.no_render_view,
                           pace_kbytes_per_s=args.pace,
                           out_dir=args.out, domain_id=args.domain_id, timeout_s=args.timeout)
    try:
        with stop_on_signals():  # SIGTERM/SIGHUP take Ctrl-C's path: the finally blocks tear everything down
            r = run_two_hosts(opts)
    except KeyboardInterrupt as err:
        code, name = exit_status(err)
        print(f"bench_two_hosts: stopped by {name}; namespaces and processes removed", file=sys.stderr)
        return code
    except MemgsError as err:  # a bad input or a failed run: one line, no traceback
        print(f"bench_two_hosts: {err}", file=sys.stderr)
        return 2
    print(f"two hosts: {Path(r.source).name}, onboard {', '.join(ONBOARD)} | ground: merger + ground station; "
          f"output {r.out_dir}")
    print(table(r))
    if args.json is not None:
        write_results(args.json, {"options": {**asdict(opts), "out_dir": r.out_dir}, "result": r.as_dict()})
    return 0 if r.identical else 1


if __name__ == "__main__":
    sys.exit(main())

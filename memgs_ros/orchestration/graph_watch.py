"""Watching the running graph from the runner's side: ``GraphObserver`` (an rclpy node in the
graph's namespace and domain: poses, stats, latched maps, the map services) and the steps a run
takes with it, public so that a harness that starts the nodes its own way
(``test/system/harness/bench_two_hosts.py``: the drone's nodes in one network namespace, the ground
station in another) takes the same ones. A step reads only what :class:`GraphWatcher` names.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path as NavPath
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Image, PointCloud2
from std_msgs.msg import Bool
from std_srvs.srv import Trigger

from memgs_ros.core.map_io.map_delta import decode
from memgs_ros.core.runtime.telemetry import TELEMETRY, parse_stats
from memgs_ros.errors import PipelineError
from memgs_ros.orchestration.processes import VIEW_NODE
from memgs_ros.orchestration.run_files import GRAPH_NODE_NAMES
from memgs_ros.ros import qos
from memgs_ros.ros.codecs import pointcloud2_to_structured, pose_to_matrix, stamp_to_ns
from memgs_ros.ros.diagnostics import stats_values

logger = logging.getLogger(__name__)

__all__ = ["READY_TOPICS", "STATS_NODES", "GraphObserver", "GraphWatcher", "NodeChecker", "compare_maps", "end_flight",
           "wait_for_graph"]

STATS_NODES = (*GRAPH_NODE_NAMES, "player", VIEW_NODE, "recorder")  # the names on memgs/<name>/stats
_PATH_DECODE_PERIOD_S = 10.0  # the runner decodes memgs/path this often (and at the end)


class NodeChecker(Protocol):
    def check(self) -> None:
        """Raise PipelineError (with the node's log) when a node process has ended."""


class GraphWatcher(Protocol):
    """What the steps read of a harness's watcher (``pipeline``'s own observer has all of it)."""

    node: Any  # an rclpy Node in the graph's namespace and domain (wait_for_graph, compare_maps)
    # "mapper" / "merger": the last PointCloud2 on memgs/mapper/snapshot / memgs/map/gaussians
    # (latched subscriptions the watcher keeps; compare_maps clears it first)
    maps: dict[str, Any]
    snapshot_client: Any  # Trigger client of memgs/mapper/publish_snapshot (compare_maps)
    publish_map_client: Any  # Trigger client of memgs/merger/publish_map (compare_maps)

    def call(self, client: Any, timeout_s: float) -> str:
        """Call a Trigger service and return its message; PipelineError when it fails."""


class GraphObserver:
    """An rclpy node that watches the graph and drives its end (created after rclpy.init)."""

    def __init__(self, context: Any) -> None:
        self.node = Node("memgs_run_observer", context=context)
        self.done = threading.Event()
        self.bring_up_s: float | None = None  # the managed nodes' configure -> active (bring_up.py)
        self.source_ok = True  # False when the player reported a source that failed part-way
        self.stats: dict[str, dict[str, str]] = {}  # each node's latest stats, replaced whole
        self._parsed: dict[str, tuple[dict[str, str], Any]] = {}  # node -> (values, their record)
        self.trajectory: list[tuple[int, np.ndarray]] = []
        self.pose_frame = ""  # memgs/pose's frame_id
        self.corrected: dict[int, np.ndarray] = {}  # memgs/path: poses re-expressed after BA / loop closure
        self._path_raw: bytes | None = None  # the newest memgs/path, serialized, not decoded yet
        self._path_decoded_t = -float("inf")
        self.keyframes: list[tuple[int, np.ndarray]] = []
        self.timeline: list[dict[str, Any]] = []  # every stats message: {"t_s", "node", values...}
        self._t0 = time.monotonic()
        self._lock = threading.Lock()

        def on_pose(msg: PoseStamped) -> None:
            with self._lock:
                self.trajectory.append((stamp_to_ns(msg.header.stamp), pose_to_matrix(msg.pose)))
                self.pose_frame = msg.header.frame_id

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

        def on_path(raw: bytes) -> None:
            # The whole path (up to the tracker's path_max_len poses) comes once a second; decoding
            # it is Python work per pose (at 10000 poses most of a core, and the poses the runner
            # then missed). A pose leaves the path's window only after minutes: decode one message
            # every _PATH_DECODE_PERIOD_S, and the newest when the run ends (corrected_poses).
            now = time.monotonic()
            with self._lock:
                self._path_raw = raw
                if now - self._path_decoded_t < _PATH_DECODE_PERIOD_S:
                    return
                self._path_decoded_t = now
            self.corrected_poses()

        self.node.create_subscription(PoseStamped, "memgs/pose", on_pose, qos.reliable(1000))
        self.node.create_subscription(NavPath, "memgs/path", on_path, qos.reliable(5), raw=True)
        self.node.create_subscription(PoseStamped, "memgs/keyframe/pose", on_keyframe, qos.reliable(1000))
        for name in STATS_NODES:
            self.node.create_subscription(DiagnosticArray, f"memgs/{name}/stats", stats_cb(name), qos.reliable(5))

        self.maps: dict[str, Any] = {}
        self.render: Any = None
        self.node.create_subscription(PointCloud2, "memgs/mapper/snapshot",
                                      lambda m: self.maps.__setitem__("mapper", m), qos.latched())
        self.node.create_subscription(PointCloud2, "memgs/map/gaussians",
                                      lambda m: self.maps.__setitem__("merger", m), qos.latched())
        self.node.create_subscription(Image, "memgs/render/color", lambda m: setattr(self, "render", m),
                                      qos.reliable(2))
        self.view_request = self.node.create_publisher(PoseStamped, "memgs/render/view_pose", qos.reliable(5))
        self.finish_client = self.node.create_client(Trigger, "memgs/mapper/finish")
        self.end_flight_client = self.node.create_client(Trigger, "memgs/tracker/end_flight")
        self.snapshot_client = self.node.create_client(Trigger, "memgs/mapper/publish_snapshot")
        self.publish_map_client = self.node.create_client(Trigger, "memgs/merger/publish_map")
        self.save_client = self.node.create_client(Trigger, "memgs/save_map")
        self._trigger = Trigger

    def corrected_poses(self) -> dict[int, np.ndarray]:
        """stamp (ns) -> T_wc of every pose memgs/path has corrected so far, the newest path decoded."""
        with self._lock:
            raw, self._path_raw = self._path_raw, None
        if raw is not None:
            msg = deserialize_message(raw, NavPath)
            poses = {stamp_to_ns(p.header.stamp): pose_to_matrix(p.pose) for p in msg.poses}
            with self._lock:
                self.corrected.update(poses)
        with self._lock:
            return dict(self.corrected)

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

    def heard(self, node: str) -> bool:
        """Whether ``node`` has published its stats at least once."""
        return node in self.stats

    def telemetry(self, node: str) -> Any:  # noqa: ANN401 - the node's record (core/runtime/telemetry.py)
        """``node``'s latest stats as its typed record (its defaults before the first message); a
        key the record does not name is a StatsError, not a figure silently read as 0."""
        values = self.stats.get(node, {})
        cached = self._parsed.get(node)
        if cached is None or cached[0] is not values:
            cached = (values, parse_stats(TELEMETRY[node], values))
            self._parsed[node] = cached
        return cached[1]



READY_TOPICS = {"tracker": "memgs/pose", "keyframe_sampler": "memgs/keyframe/seeds",
                 "mapper": "memgs/frame_ack", "merger": "memgs/map/gaussians",
                 VIEW_NODE: f"memgs/{VIEW_NODE}/stats"}


def wait_for_graph(obs: GraphWatcher, procs: NodeChecker, nodes: Sequence[str], deadline: float) -> None:
    """Block until every node in ``nodes`` is discovered, so the first frame reaches all of them."""
    missing = list(nodes)
    while missing:
        procs.check()
        if time.monotonic() > deadline:
            raise PipelineError(f"nodes did not come up: {', '.join(missing)}")
        missing = [n for n in missing if obs.node.count_publishers(READY_TOPICS[n]) == 0]
        time.sleep(0.1)
    time.sleep(0.5)  # endpoint matching between the nodes themselves settles just after discovery


def compare_maps(obs: GraphWatcher, final_seq: int, epoch: int, end: float) -> tuple[bool, float]:
    """Ask mapper and merger for their whole maps at ``final_seq`` of ``epoch`` and compare them:
    (identical within 1e-6, the largest absolute difference; inf when their ids differ).
    PipelineError when they do not arrive by ``end`` (time.monotonic())."""

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


_END_FLIGHT_WAIT_S = 15.0  # for the mapper to hold the flight's last keyframe: tracker, sampler, mapper insert


def end_flight(obs: GraphObserver) -> None:
    """The flight's last view made a keyframe where no keyframe sees it (``memgs/tracker/end_flight``),
    and the mapper's insertion of it awaited (its stats count it), so the finish trains it. A tracker
    that does not answer (gone, restarting) costs a warning, not the run."""
    before = obs.telemetry("mapper").keyframes  # read first: the new keyframe cannot be in it yet
    try:
        answer = obs.call(obs.end_flight_client, 10.0)
    except PipelineError as err:
        logger.warning("the last view was not offered as a keyframe: %s", err)
        return
    if not answer.startswith("keyframe"):
        return
    end = time.monotonic() + _END_FLIGHT_WAIT_S
    while obs.telemetry("mapper").keyframes <= before:
        if time.monotonic() > end:
            logger.warning("the mapper did not count the flight's last keyframe within %.0f s; finishing",
                           _END_FLIGHT_WAIT_S)
            return
        time.sleep(0.05)

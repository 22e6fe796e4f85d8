"""The composed executable (``ros2 run memgs_ros composed``): the four graph nodes as components of
one process, each under its own name with its own section of the params file, all of them warm,
a node's own --param, and a clean stop on SIGINT (exit 0). Real process, real DDS."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from memgs_ros.nodes.registry import GRAPH  # noqa: E402
from memgs_ros.orchestration.run_files import RunOptions, build_params  # noqa: E402
from memgs_ros.ros import qos  # noqa: E402
from memgs_ros.ros.diagnostics import stats_values  # noqa: E402

pytestmark = pytest.mark.ros


def test_composed_process_hosts_the_graph_and_stops_cleanly(tmp_path: Path, ros_domain_id: int,
                                                            context) -> None:  # noqa: ANN001
    ns = f"/composed{os.getpid()}"
    params = build_params(RunOptions("synthetic:w=64,h=48,n=2", config="synthetic"), tmp_path / "map.ply")
    params_file = tmp_path / "params.yaml"
    params_file.write_text(yaml.safe_dump(params))
    env = {**os.environ, "ROS_DOMAIN_ID": str(ros_domain_id)}
    log = open(tmp_path / "composed.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "memgs_ros.nodes.composed",
                             "--param", f"merger:map_path:={tmp_path / 'mine.ply'}", "--ros-args", "--params-file",
                             str(params_file), "-r", f"__ns:={ns}"], env=env, stdout=log, stderr=subprocess.STDOUT)
    peer = rclpy.create_node("composed_peer", context=context)
    warm: dict[str, int] = {}

    def on_stats(name: str):  # noqa: ANN202
        return lambda msg: warm.__setitem__(name, int(float(stats_values(msg).get("kernels_warm", "0"))))

    for name in GRAPH:
        peer.create_subscription(DiagnosticArray, f"{ns}/memgs/{name}/stats", on_stats(name), qos.reliable(5))
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(peer)
    try:
        end = time.monotonic() + 120
        while time.monotonic() < end and not (len(warm) == len(GRAPH) and all(warm.values())):
            ex.spin_once(timeout_sec=0.1)
            assert proc.poll() is None, (tmp_path / "composed.log").read_text()[-3000:]
        assert warm == dict.fromkeys(GRAPH, 1), warm
        nodes = {(n, s) for n, s in peer.get_node_names_and_namespaces() if s == ns}
        assert nodes == {(name, ns) for name in GRAPH}  # each under its own name: one process, four nodes
        # --param reached the merger alone (a namespaced node, which ROS's -p node:name:= misses).
        saved = peer.create_client(Trigger, f"{ns}/memgs/save_map")
        assert saved.wait_for_service(timeout_sec=30)
        future = saved.call_async(Trigger.Request())
        ex.spin_until_future_complete(future, timeout_sec=30)
        assert future.result() is not None and future.result().message.startswith(str(tmp_path / "mine.ply"))
        proc.send_signal(signal.SIGINT)
        assert proc.wait(60) == 0, (tmp_path / "composed.log").read_text()[-3000:]
        text = (tmp_path / "composed.log").read_text()
        assert "Traceback" not in text, text[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        log.close()
        ex.shutdown()
        peer.destroy_node()

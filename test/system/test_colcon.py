"""colcon builds the package into an ament prefix where `ros2 run` would find every executable,
and each installed executable starts and shuts down cleanly on SIGINT."""
from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from colcon_install import PKG, install_env
from conftest import own_domain_ids

pytestmark = [pytest.mark.ros, pytest.mark.slow]

NODES = ("tracker", "keyframe_sampler", "mapper", "merger", "bag_player", "recorder")
# Extra arguments a node needs to start and then idle: the player waits for subscribers; the
# recorder needs its file (written into the build workspace when it stops).
NODE_ARGS: dict[str, list[str]] = {
    "bag_player": ["-p", "source:=synthetic:w=32,h=24,n=3", "-p", "start_delay_s:=600.0"],
    "recorder": ["-p", "path:={ws}/recorder_test.mcap"],
    # This fresh workspace's mapper compiles its kernels at start (numba caches by source path); at
    # its default niceness (10) beside busy cores that took minutes, which is not what is tested here.
    "mapper": ["-p", "niceness:=0"],
}
EXECUTABLES = [*NODES, "memgs"]
START_TIMEOUT_S = 90.0  # all nodes start at once on a shared 2-core machine (the mapper loads torch)
STOP_TIMEOUT_S = 15.0
WARM_TIMEOUT_S = 180.0  # a first compile of the mapper's kernels beside the other nodes, on busy cores


@pytest.fixture(scope="module")
def prefix(colcon_prefix: Path) -> Path:
    """The session's colcon install (conftest.py); isolated layout: <prefix>/memgs_ros/..."""
    return colcon_prefix


def test_install_layout_has_ament_index_and_every_executable(prefix: Path) -> None:
    base = prefix / PKG
    assert (base / "share/ament_index/resource_index/packages" / PKG).is_file()
    assert (base / "share" / PKG / "package.xml").is_file()
    for name in ("tum_fr1", "tum_fr2", "tum_fr3", "realsense_d435i", "synthetic"):
        assert (base / "share" / PKG / "config" / f"{name}.yaml").is_file(), f"config {name} not installed"
    assert (base / "share" / PKG / "config" / "fastdds.xml").is_file()
    for exe in EXECUTABLES:
        path = base / "lib" / PKG / exe
        assert path.is_file() and os.access(path, os.X_OK), f"missing executable {path}"
    # The installed copy is what runs, not the source tree.
    site = next((base / "lib").glob("python3*/site-packages"))
    assert (site / PKG / "nodes" / "bag_player" / "node.py").is_file()


def test_memgs_cli_runs(prefix: Path, ros_domain_id: int) -> None:
    proc = subprocess.run([str(prefix / PKG / "lib" / PKG / "memgs"), "--help"],
                          env=install_env(prefix, ros_domain_id), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "usage: memgs" in proc.stdout


@pytest.fixture(scope="module")
def node_procs(prefix: Path) -> Iterator[dict[str, tuple[subprocess.Popen, int]]]:
    """Start every node at once as `ros2 run memgs_ros <node> --ros-args --params-file <installed
    config> -r __ns:=/uav1` would, each in a DDS domain of its own so their (slow) imports
    overlap; each test below then checks and stops one of them."""
    exes = list(NODES)
    config = prefix / PKG / "share" / PKG / "config" / "tum_fr1.yaml"
    domains = own_domain_ids(len(exes))  # this worker's share: never a domain a test beside it draws
    procs: dict[str, tuple[subprocess.Popen, int]] = {}
    try:
        for exe, domain in zip(exes, domains):
            procs[exe] = (subprocess.Popen(
                [str(prefix / PKG / "lib" / PKG / exe), "--ros-args", "--params-file", str(config),
                 "-r", "__ns:=/uav1", *(a.format(ws=prefix.parent) for a in NODE_ARGS.get(exe, []))],
                env=install_env(prefix, domain), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            ), domain)
        yield procs
    finally:
        for proc, _ in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def _wait_for_node(domain_id: int, proc: subprocess.Popen, timeout_s: float) -> list[str]:
    """Watch the ROS graph of ``domain_id`` until a node other than ours shows up."""
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    watcher = rclpy.create_node("colcon_test_watcher", context=ctx)
    try:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and proc.poll() is None:
            names = [f"{ns.rstrip('/')}/{n}" for n, ns in watcher.get_node_names_and_namespaces()
                     if n != "colcon_test_watcher"]
            if names:
                return names
            time.sleep(0.1)
        return []
    finally:
        watcher.destroy_node()
        rclpy.try_shutdown(context=ctx)


def _wait_for_message(domain_id: int, topic: str, timeout_s: float, key: str | None = None) -> bool:
    """Whether a DiagnosticArray arrives on ``topic`` in ``domain_id`` within ``timeout_s`` (with
    ``key``: one whose stats value ``key`` is "1")."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor

    from memgs_ros.ros import qos
    from memgs_ros.ros.diagnostics import stats_values

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    watcher = rclpy.create_node("colcon_test_listener", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(watcher)
    got: list[DiagnosticArray] = []
    watcher.create_subscription(DiagnosticArray, topic, lambda m: got.append(m) if key is None
                                or stats_values(m).get(key) == "1" else None, qos.reliable(5))
    try:
        deadline = time.monotonic() + timeout_s
        while not got and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        return bool(got)
    finally:
        executor.shutdown()
        watcher.destroy_node()
        rclpy.try_shutdown(context=ctx)


@pytest.mark.parametrize("exe", NODES)
def test_node_starts_and_stops_on_sigint(node_procs: dict[str, tuple[subprocess.Popen, int]], exe: str,
                                         prefix: Path) -> None:
    proc, domain = node_procs[exe]
    names = _wait_for_node(domain, proc, START_TIMEOUT_S)
    if not names:
        proc.kill()
        out, _ = proc.communicate()
        pytest.fail(f"{exe} never appeared in the ROS graph (exit {proc.returncode}):\n{out[-4000:]}")
    assert names == [f"/uav1/{exe}"], names
    # Spinning once the first stats message is out (a timer of the executor sends it): the
    # recorder's file is open by then. The mapper loads (here: compiles, this workspace's copy has
    # no cache) its kernels on its session's thread after that, and a SIGINT then waits for the
    # compile: wait for kernels_warm, as the runner does.
    stats = {"bag_player": "player"}.get(exe, exe)
    assert _wait_for_message(domain, f"/uav1/memgs/{stats}/stats", WARM_TIMEOUT_S,
                             key="kernels_warm" if exe == "mapper" else None), f"{exe} never spun"
    proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        pytest.fail(f"{exe} did not exit within {STOP_TIMEOUT_S} s of SIGINT:\n{out[-4000:]}")
    assert proc.returncode == 0, f"{exe} exited {proc.returncode} on SIGINT:\n{out[-4000:]}"
    assert "Traceback" not in out, out[-4000:]
    if exe == "recorder":  # its file is complete once it has stopped (an empty recording here)
        assert (prefix.parent / "recorder_test.mcap").is_file(), out[-4000:]

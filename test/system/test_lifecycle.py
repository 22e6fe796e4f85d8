"""Every way ``memgs run`` ends, it ends the nodes it started: SIGTERM and SIGHUP stop them in order
(the merger saves its map), SIGKILL of the runner ends them through the kernel
(PR_SET_PDEATHSIG), and a second Ctrl-C kills them at once. Real processes, real DDS."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from memgs_ros.core.map_io.ply import load_ply  # noqa: E402
from memgs_ros.nodes.registry import node_name  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]

NODES = ("tracker", "keyframe_sampler", "mapper", "merger", "bag_player")


def node_pids(out: Path) -> dict[int, str]:
    """{pid: node} of the processes started with this run's params file."""
    marker = str(out.resolve() / "params.yaml").encode()
    found: dict[int, str] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            cmdline = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if marker in cmdline:
            module = next((a.decode() for a in cmdline if a.startswith(b"memgs_ros.nodes.")), "?")
            found[int(entry)] = node_name(module) if module != "?" else module
    return found


def start_run(out: Path, domain: int) -> subprocess.Popen:
    # 2 minutes of frames: still running when a test interrupts it, on a busy machine too
    cmd = [sys.executable, "-m", "memgs_ros", "run", "--bag", "synthetic:w=96,h=72,n=3600,seed=3",
           "--config", "synthetic", "--out", str(out), "--domain-id", str(domain), "--realtime"]
    log = open(out.parent / f"{out.name}.log", "wb")  # noqa: SIM115 - the child's
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)


def wait_until_mapping(run: subprocess.Popen, out: Path, domain: int, timeout_s: float = 120.0) -> None:
    """All nodes up and the merger holding Gaussians (read from its stats on the run's domain)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray

    from memgs_ros.ros import qos
    from memgs_ros.ros.diagnostics import stats_values

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("lifecycle_test_peer", context=ctx)
    stats: dict[str, str] = {}
    node.create_subscription(DiagnosticArray, "memgs/merger/stats", lambda m: stats.update(stats_values(m)),
                             qos.reliable(5))
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            assert run.poll() is None, (out.parent / f"{out.name}.log").read_text()[-3000:]
            executor.spin_once(timeout_sec=0.1)
            if float(stats.get("gaussians", 0)) > 0 and set(node_pids(out).values()) >= set(NODES):
                return
        pytest.fail(f"no map in the merger after {timeout_s} s: nodes {node_pids(out)}, merger stats {stats}")
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def wait_for_no_nodes(out: Path, timeout_s: float) -> float:
    t0 = time.monotonic()
    while node_pids(out):
        if time.monotonic() - t0 > timeout_s:
            left = node_pids(out)
            for pid in left:
                os.kill(pid, signal.SIGKILL)  # leave nothing behind for the other tests
            pytest.fail(f"nodes still running {timeout_s} s after the runner ended: {left}")
        time.sleep(0.1)
    return time.monotonic() - t0


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGKILL], ids=lambda s: s.name)
def test_runner_end_ends_every_node(tmp_path: Path, sig: signal.Signals, ros_domain_id: int) -> None:
    out = tmp_path / "run"
    out.mkdir()
    run = start_run(out, ros_domain_id)
    try:
        wait_until_mapping(run, out, ros_domain_id)
        run.send_signal(sig)
        code = run.wait(timeout=60)
        waited = wait_for_no_nodes(out, timeout_s=20.0)
    finally:
        if run.poll() is None:
            run.kill()
    log = (out.parent / f"{out.name}.log").read_text()
    assert code == (-signal.SIGKILL if sig == signal.SIGKILL else 128 + int(sig)), log[-2000:]
    if sig != signal.SIGKILL:
        assert f"interrupted ({sig.name})" in log, log[-2000:]
        summary = json.loads((out / "summary.json").read_text())  # the run says how it ended
        assert summary["outcome"] == "interrupted" and sig.name in summary["error"], summary
    assert not list(out.glob(".*.tmp")), "atomic writes left temporary files"
    # SIGTERM / SIGHUP: the runner stopped the nodes; SIGKILL: the kernel's SIGTERM did. Either
    # way the merger saved the map it held.
    assert waited < 20.0
    assert len(load_ply(out / "map.ply").ids) > 0


def test_second_interrupt_kills_the_nodes_at_once(tmp_path: Path, ros_domain_id: int) -> None:
    out = tmp_path / "run"
    out.mkdir()
    run = start_run(out, ros_domain_id)
    try:
        wait_until_mapping(run, out, ros_domain_id)
        run.send_signal(signal.SIGINT)
        log_path = out.parent / f"{out.name}.log"
        end = time.monotonic() + 5.0  # the runner says when its orderly stop begins; at most 5 s
        while "stopping the nodes" not in log_path.read_text(errors="replace") and time.monotonic() < end:
            assert run.poll() is None, log_path.read_text(errors="replace")[-2000:]
            time.sleep(0.05)
        run.send_signal(signal.SIGINT)
        code = run.wait(timeout=30)
        waited = wait_for_no_nodes(out, timeout_s=5.0)
    finally:
        if run.poll() is None:
            run.kill()
    log = (out.parent / f"{out.name}.log").read_text()
    assert code == 130, log[-2000:]
    assert "killing them" in log, log[-2000:]
    assert waited < 5.0



def test_stop_spinning_returns_once_the_spin_thread_has_ended(context) -> None:  # noqa: ANN001
    """The runner's observer spins on a thread of its own. A daemon spin thread still waiting in
    rclpy's C++ wait set as the interpreter finalizes makes rclpy abort the process (exit -6,
    "terminate called without an active exception": 29 of 30 tries of a bare script, and once a
    SIGHUP'd runner in CI); stop_spinning returns only once that thread has ended."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from memgs_ros.orchestration.processes import spin_in_background, stop_spinning

    node = rclpy.create_node("spin_exit_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        ticked = threading.Event()

        def once() -> None:  # one callback, then nothing wakes the wait set but stop_spinning
            timer.cancel()
            ticked.set()

        timer = node.create_timer(0.01, once)
        thread = spin_in_background(executor)
        assert ticked.wait(30)  # the thread spins, and after this callback waits inside the wait set
        stop_spinning(executor, thread)
        assert not thread.is_alive()
    finally:
        node.destroy_node()

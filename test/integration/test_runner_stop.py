"""The runner's executor thread ends with the graph, also when a second Ctrl-C kills the nodes:
a thread left waiting in rclpy's C++ code crashed the exiting runner (SIGSEGV, exit -11)."""
from __future__ import annotations

from typing import Any

import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")
from rclpy.executors import SingleThreadedExecutor  # noqa: E402

from memgs_ros.orchestration.pipeline import _stop_graph  # noqa: E402
from memgs_ros.orchestration.processes import spin_in_background  # noqa: E402


class _InterruptedProcs:
    """The node processes as a second Ctrl-C leaves them: ``stop`` killed them and re-raised."""

    def stop(self) -> None:
        raise KeyboardInterrupt


def test_a_second_interrupt_still_ends_the_spin_thread(context: Any) -> None:
    executor = SingleThreadedExecutor(context=context)
    node = rclpy.create_node("memgs_run_stop_probe", context=context)
    executor.add_node(node)
    spin = spin_in_background(executor)
    assert spin.is_alive()
    with pytest.raises(KeyboardInterrupt):
        _stop_graph(_InterruptedProcs(), [], executor, spin, None, context)  # type: ignore[arg-type]
    assert not spin.is_alive()  # joined before the interrupt went on to the CLI
    node.destroy_node()

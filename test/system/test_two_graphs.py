"""Two graphs on one network do not mix: a `memgs run` on a domain and namespace where another memgs
graph runs refuses before starting a node, naming the way out; another namespace is welcome."""
from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from memgs_ros.errors import PipelineError  # noqa: E402
from memgs_ros.orchestration.processes import open_context  # noqa: E402

pytestmark = pytest.mark.ros


def test_a_second_graph_in_the_same_namespace_is_refused(tmp_path: Path, ros_domain_id: int) -> None:
    ns = f"/memgs_test_{os.getpid()}_{os.urandom(3).hex()}"
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id)
    other = rclpy.create_node("tracker", namespace=ns, context=ctx)  # the first run's tracker
    try:
        t0 = time.monotonic()
        with pytest.raises(PipelineError, match=rf"another memgs graph runs on ROS domain {ros_domain_id} in "
                                                rf"namespace {ns} \(its tracker\).*--namespace"):
            open_context(ros_domain_id, [], namespace=ns, probe_s=1.0)
        assert time.monotonic() - t0 < 5.0
        # Another namespace on the same domain runs apart.
        context, domain = open_context(ros_domain_id, [], namespace=ns + "_b", probe_s=1.0)
        assert domain == ros_domain_id
        rclpy.try_shutdown(context=context)
    finally:
        other.destroy_node()
        rclpy.try_shutdown(context=ctx)

"""A node's part of a map bundle (ros/map_bundles.py: PartService) over real DDS: refused without a
bundle folder or before there is a part, an error writing it answered with the path, a part
written answered with its path and counted once."""
from __future__ import annotations

import os
from concurrent.futures import Future
from pathlib import Path

import pytest

pytest.importorskip("rclpy", reason="the ROS extra is not installed (pip install -e '.[ros]')")

import rclpy  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from memgs_ros.ros.hand_over import HandOver  # noqa: E402
from memgs_ros.ros.map_bundles import PartService  # noqa: E402

pytestmark = pytest.mark.ros


def test_part_service_answers_each_case(context, tmp_path: Path) -> None:  # noqa: ANN001
    ns = f"/part_{os.getpid()}"
    node = rclpy.create_node("part_node", namespace=ns, context=context)
    peer = rclpy.create_node("part_peer", namespace=ns, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(peer)
    outcome: dict[str, object] = {"next": "no part yet"}
    saved: list[Path] = []
    written: list[Path] = []

    def write(path: Path) -> Future | str:
        nxt = outcome["next"]
        if isinstance(nxt, str):
            return nxt
        done: Future = Future()
        if isinstance(nxt, Exception):
            done.set_exception(nxt)
        else:
            path.write_bytes(b"part")
            written.append(path)
            done.set_result(path)
        return done

    hand_over = HandOver(node)
    PartService(node, "thing", "", hand_over, write, lambda: saved.append(Path()), "the thing")
    service = PartService(node, "other", str(tmp_path / "bundles"), hand_over, write,
                          lambda: saved.append(written[-1]), "the other thing", " extra=1")

    def call(name: str) -> Trigger.Response:
        client = peer.create_client(Trigger, f"memgs/{name}/save_map_part")
        future = client.call_async(Trigger.Request())
        executor.spin_until_future_complete(future, timeout_sec=20.0)
        assert future.done(), f"{name} did not answer"
        return future.result()

    try:
        r = call("thing")
        assert (r.success, r.message) == (False, "bundle_dir is not set: no map bundle to save into")
        r = call("other")
        assert (r.success, r.message) == (False, "no part yet")
        outcome["next"] = OSError(28, "No space left on device")
        r = call("other")
        assert not r.success and r.message.startswith("could not write the other thing ")
        assert r.message.endswith("No space left on device") and ".parts" in r.message
        assert saved == []
        outcome["next"] = None
        r = call("other")
        assert r.success and r.message == f"{written[-1]} extra=1"
        assert saved == written and written[-1].read_bytes() == b"part"
        assert written[-1].parent == tmp_path / "bundles" / ".parts" and service.name == "other"
    finally:
        hand_over.close()
        executor.shutdown()
        peer.destroy_node()
        node.destroy_node()

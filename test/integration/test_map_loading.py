"""A saved map loaded at run time (ros/map_loading.py): the mapper node restarts on a bundle through
its lifecycle and answers with Nav2's LoadMap result codes; a map it cannot take leaves the old one."""
from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from nav_msgs.srv import LoadMap  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from ros_spin import spin_until  # noqa: E402

from memgs_ros.core.gaussians.records import GaussianRecords  # noqa: E402
from memgs_ros.core.mapping import checkpoint  # noqa: E402
from memgs_ros.core.map_io.bundle import (  # noqa: E402
    MANIFEST,
    MAPPER_FILE,
    PLY_FILE,
    TRACKER_FILE,
    Manifest,
    commit_bundle,
    new_staging,
)
from memgs_ros.core.map_io.ply import save_ply  # noqa: E402

pytestmark = pytest.mark.ros
R = LoadMap.Response


_spin_until = functools.partial(spin_until, timeout_s=60.0)  # a node restart saves, closes and starts a session


def _bundle(root: Path, n: int, depth_scale: float = 1000.0, mapper_bytes: bytes | None = None) -> Path:
    """A bundle whose mapper part holds ``n`` Gaussians (or ``mapper_bytes``, hashed as saved)."""
    rng = np.random.default_rng(n)
    g = GaussianRecords.from_arrays(
        np.arange(n), rng.normal(0, 1, (n, 3)).astype(np.float32) + [0, 0, 3], rng.random((n, 3)).astype(np.float32),
        np.zeros((n, 45), np.float32), np.zeros(n, np.float32), np.full((n, 3), -3.0, np.float32),
        np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32))
    staging = new_staging(root)
    if mapper_bytes is None:
        checkpoint.save(checkpoint.MapperCheckpoint(g, np.zeros(n, np.int64), np.zeros(n, np.int64), (), 100, n, 0,
                                                    1.0), staging / MAPPER_FILE)
    else:
        (staging / MAPPER_FILE).write_bytes(mapper_bytes)
    save_ply(g, staging / PLY_FILE)
    (staging / TRACKER_FILE).write_bytes(b"the tracker's part")  # the mapper never reads it
    cam = {"width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0, "dist": []}
    return commit_bundle(staging, Manifest(0, cam, "rgbd", depth_scale, 3, "map_optical", 10, 1, n, "test", "now"))


def test_the_mapper_restarts_on_a_loaded_map_and_keeps_it_when_the_next_cannot_be_taken(
        context, tmp_path: Path) -> None:  # noqa: ANN001
    from memgs_ros.nodes.mapper.node import MapperNode

    good = _bundle(tmp_path / "maps", 300)
    other_version = _bundle(tmp_path / "maps", 10)
    manifest = json.loads((other_version / MANIFEST).read_text())
    (other_version / MANIFEST).write_text(json.dumps({**manifest, "format_version": 99}))
    unreadable = _bundle(tmp_path / "maps", 10, mapper_bytes=b"not a checkpoint")  # whole, but no mapper state
    ckpt = tmp_path / "run" / "mapper_checkpoint.npz"
    node = MapperNode(context=context, parameter_overrides=[
        Parameter("device", value="cpu"), Parameter("render_rate_hz", value=0.0),
        Parameter("checkpoint_path", value=str(ckpt))])
    peer = rclpy.create_node("peer", context=context)
    client = peer.create_client(LoadMap, "memgs/mapper/load_map")
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    ex.add_node(peer)

    def load(url: str) -> int:
        future = client.call_async(LoadMap.Request(map_url=url))
        assert spin_until(ex, future.done, 120.0)
        return int(future.result().result)

    try:
        assert _spin_until(ex, client.service_is_ready)
        node.save_checkpoint(force=True).result(60)  # the map it had (empty) is on disk
        assert load(f"file://{good}") == R.RESULT_SUCCESS
        assert node.active and node.params.map_bundle == str(good)
        assert _spin_until(ex, lambda: node.session.status.gaussians == 300), node.session.status.gaussians
        assert list(ckpt.parent.glob("mapper_checkpoint.npz.before-load-*"))  # the old map moved aside, kept
        assert load(str(tmp_path / "nowhere")) == R.RESULT_MAP_DOES_NOT_EXIST
        assert load(str(other_version)) == R.RESULT_INVALID_MAP_METADATA
        assert load(str(unreadable)) == R.RESULT_INVALID_MAP_DATA
        # Still active on the loaded map: the refused ones changed nothing.
        assert node.active and node.params.map_bundle == str(good)
        assert _spin_until(ex, lambda: node.session.status.gaussians == 300)
    finally:
        node.close()
        ex.shutdown()
        peer.destroy_node()
        node.destroy_node()


def test_memgs_load_map_restarts_the_graph_on_a_bundle_and_the_merger_follows(context, tmp_path: Path) -> None:  # noqa: ANN001
    """The merger's memgs/load_map checks the bundle, restarts the mapper on it (then the tracker,
    here a stand-in that records the request) and takes the new map from the mapper's snapshot."""
    from memgs_ros.nodes.mapper.node import MapperNode
    from memgs_ros.nodes.merger.node import MergerNode

    good = _bundle(tmp_path / "maps", 200)
    mapper = MapperNode(context=context, parameter_overrides=[
        Parameter("device", value="cpu"), Parameter("render_rate_hz", value=0.0),
        Parameter("checkpoint_path", value=str(tmp_path / "run" / "mapper_checkpoint.npz"))])
    merger = MergerNode(context=context, parameter_overrides=[Parameter("map_path", value=str(tmp_path / "m.ply")),
                                                              Parameter("save_period_s", value=0.0)])
    peer = rclpy.create_node("tracker_stand_in", context=context)
    asked: list[str] = []

    def tracker_load(req: LoadMap.Request, res: LoadMap.Response) -> LoadMap.Response:
        asked.append(req.map_url)
        res.result = R.RESULT_SUCCESS
        return res

    peer.create_service(LoadMap, "memgs/tracker/load_map", tracker_load)
    client = peer.create_client(LoadMap, "memgs/load_map")
    ex = SingleThreadedExecutor(context=context)
    for n in (mapper, merger, peer):
        ex.add_node(n)
    try:
        assert _spin_until(ex, client.service_is_ready)
        missing = client.call_async(LoadMap.Request(map_url=str(tmp_path / "nowhere")))
        assert _spin_until(ex, missing.done) and missing.result().result == R.RESULT_MAP_DOES_NOT_EXIST
        assert asked == []  # refused before any node was asked
        future = client.call_async(LoadMap.Request(map_url=str(tmp_path / "maps")))  # "latest"
        assert spin_until(ex, future.done, 120.0) and future.result().result == R.RESULT_SUCCESS
        assert asked == [str(good)] and mapper.params.map_bundle == str(good)
        assert _spin_until(ex, lambda: len(merger.map.replica) == 200), len(merger.map.replica)
    finally:
        for n in (mapper, merger):
            n.close()
        ex.shutdown()
        for n in (peer, mapper, merger):
            n.destroy_node()

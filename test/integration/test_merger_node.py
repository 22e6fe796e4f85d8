"""The merger node in-process: deltas, a gap and its resync, a requested view, the viewer cloud and
the save service."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from memgs_ros.core.gaussians.gaussian_map import GaussianMap  # noqa: E402
from memgs_ros.core.gaussians.records import base_rgb8  # noqa: E402
from memgs_ros.core.map_io.map_delta import DeltaOutbox, unpack_rgb  # noqa: E402
from memgs_ros.core.map_io.ply import load_ply  # noqa: E402
from memgs_ros.io.image_decoding import image_to_numpy  # noqa: E402
from memgs_ros.nodes.merger.node import MergerNode  # noqa: E402
from memgs_ros.ros import qos  # noqa: E402
from memgs_ros.ros.codecs import (  # noqa: E402
    matrix_to_pose_stamped,
    pointcloud2_to_structured,
    structured_to_pointcloud2,
)

pytestmark = pytest.mark.ros


def _wall_map(n: int, seed: int = 0) -> GaussianMap:
    """Coloured Gaussians on a wall 2 m in front of a camera at the origin looking down +z."""
    rng = np.random.default_rng(seed)
    pts = np.stack([rng.uniform(-1, 1, n), rng.uniform(-0.8, 0.8, n), np.full(n, 2.0)], axis=1)
    g = GaussianMap(max_sh_degree=0)
    g.add_from_points(pts, rng.uniform(0.2, 0.9, (n, 3)), keyframe_id=0, iteration=0)
    return g


def test_merger_applies_deltas_resyncs_renders_and_saves(tmp_path: Path, ros_domain_id: int) -> None:
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id)
    path = tmp_path / "map.ply"
    merger = MergerNode(context=ctx, parameter_overrides=[
        Parameter("map_path", value=str(path)), Parameter("render_width", value=64),
        Parameter("render_height", value=48), Parameter("render_fx", value=50.0), Parameter("render_fy", value=50.0),
        Parameter("render_cx", value=31.5), Parameter("render_cy", value=23.5), Parameter("resync_interval_s", value=0.0)])
    peer = rclpy.create_node("mapper_stand_in", context=ctx)
    pub_delta = peer.create_publisher(PointCloud2, "memgs/map/delta", qos.reliable(50))
    pub_snap = peer.create_publisher(PointCloud2, "memgs/mapper/snapshot", qos.latched())
    pub_view = peer.create_publisher(PoseStamped, "memgs/merger/view_pose", qos.reliable(5))
    renders: list[Image] = []
    peer.create_subscription(Image, "memgs/merger/render/color", renders.append, qos.reliable(5))
    infos: list[CameraInfo] = []
    peer.create_subscription(CameraInfo, "memgs/merger/render/camera_info", infos.append, qos.reliable(5))
    clouds: dict[str, list[PointCloud2]] = {"gaussians": [], "points": []}
    for name, got in clouds.items():
        peer.create_subscription(PointCloud2, f"memgs/map/{name}", got.append, qos.latched())
    outbox = DeltaOutbox(sh_degree=0)
    g = _wall_map(300)
    requests = []

    def serve_snapshot(_req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        requests.append(1)
        pub_snap.publish(structured_to_pointcloud2(outbox.snapshot(g.to_records()), 0, "map"))
        res.success = True
        return res

    peer.create_service(Trigger, "memgs/mapper/publish_snapshot", serve_snapshot)
    save = peer.create_client(Trigger, "memgs/save_map")
    publish = peer.create_client(Trigger, "memgs/merger/publish_map")
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(merger)
    ex.add_node(peer)

    def spin_until(cond, timeout_s: float = 20.0) -> bool:  # noqa: ANN001
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
            if cond():
                return True
        return False

    try:
        assert spin_until(lambda: pub_delta.get_subscription_count() > 0 and save.service_is_ready())
        pub_delta.publish(structured_to_pointcloud2(outbox.next_delta(g.to_records()), 0, "map"))
        assert spin_until(lambda: len(merger.map.replica) == 300)
        # Remove 50, then lose that delta: the next one is a gap and forces a resync.
        g.remove(np.arange(len(g)) < 50)
        outbox.next_delta(g.to_records())  # "lost" on the link
        g.add_from_points(np.array([[0.0, 0.0, 1.5]]), np.array([[1.0, 0.0, 0.0]]), keyframe_id=1, iteration=1)
        pub_delta.publish(structured_to_pointcloud2(outbox.next_delta(g.to_records()), 0, "map"))
        # The snapshot is the map delta 3 made: it keeps seq 3 (DeltaOutbox.snapshot).
        assert spin_until(lambda: requests and merger.map.replica.seq >= 3 and not merger.map.resyncing)
        assert np.array_equal(merger.map.replica.records.ids, np.sort(g.to_records().ids))
        pub_view.publish(matrix_to_pose_stamped(np.eye(4), 123, "map"))
        assert spin_until(lambda: renders and infos)  # rendered on the merger's render thread
        assert (infos[0].width, infos[0].height, infos[0].k[0]) == (64, 48, 50.0)
        assert infos[0].header.frame_id == renders[0].header.frame_id
        img = image_to_numpy(renders[0])
        assert img.shape == (48, 64, 3) and img.std() > 5.0
        merger.stats.apply_posted()
        assert merger.stats.values["renders"] == 1
        # Its stats say what it holds: the replica's rows and the render inputs, no training state.
        merger._gauges()
        gauges = merger.stats.values
        assert gauges["map_bytes"] == merger.map.replica.records.nbytes > 0
        assert 0 < gauges["render_cache_bytes"] <= 2 * gauges["map_bytes"] and gauges["buffered_deltas"] == 0
        # The viewer cloud: every row a Gaussian of the map, in the map frame, near the others (the
        # delta protocol's full map opens with its META row, whose x, y hold the 32-bit epoch).
        done = publish.call_async(Trigger.Request())
        assert spin_until(lambda: done.done() and clouds["points"] and clouds["gaussians"])
        pts = pointcloud2_to_structured(clouds["points"][-1])
        assert clouds["points"][-1].header.frame_id == merger.world_frame
        assert pts.dtype.names == ("x", "y", "z", "rgb", "opacity") and len(pts) == len(g)
        xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1)
        far = np.linalg.norm(xyz - np.median(xyz, axis=0), axis=1) > 10.0
        assert far.sum() == 0
        rec = merger.map.replica.records
        assert np.array_equal(unpack_rgb(pts["rgb"]), base_rgb8(rec.f_dc))
        assert np.allclose(pts["opacity"], 1 / (1 + np.exp(-rec.opacity)), atol=1e-6)
        assert clouds["points"][-1].row_step < clouds["gaussians"][-1].row_step / 4  # 20 B a Gaussian
        future = save.call_async(Trigger.Request())
        assert spin_until(future.done)
        assert future.result().success and str(path) in future.result().message
        assert len(load_ply(path)) == len(g)
        assert not list(tmp_path.glob("*.tmp*"))
    finally:
        ex.shutdown()
        merger.renderer.close()
        merger.destroy_node()
        peer.destroy_node()
        rclpy.try_shutdown(context=ctx)

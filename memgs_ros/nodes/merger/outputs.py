"""The merger's rendered views on ``memgs/merger/render/{color,depth,camera_info}``: published from
the renderer's thread when a render finishes, so the executor never waits for one."""
from __future__ import annotations

from concurrent.futures import Future

from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.map_io.view_renderer import RenderedView
from memgs_ros.core.runtime.worker import WorkerStopped
from memgs_ros.nodes.merger.stats import MergerStats
from memgs_ros.ros import qos
from memgs_ros.ros.images import camera_to_camera_info, depth_to_image, numpy_to_image

__all__ = ["ViewOutbox"]

RENDER_FRAME = "render_camera"


class ViewOutbox:
    """Publishes each finished view (rgb8 colour, 32FC1 depth and the render ``camera``'s
    camera_info, stamped as requested) and counts it as ``renders``; a failed render is counted as
    ``problem.render_failed`` (posted: this runs on the renderer's thread)."""

    def __init__(self, node: Node, stats: MergerStats, prefix: str, camera: PinholeCamera) -> None:
        self._stats, self._camera = stats, camera
        self._color = node.create_publisher(Image, f"{prefix}/color", qos.reliable(2))
        self._depth = node.create_publisher(Image, f"{prefix}/depth", qos.reliable(2))
        self._info = node.create_publisher(CameraInfo, f"{prefix}/camera_info", qos.reliable(2))

    def when_done(self, future: Future[RenderedView]) -> None:
        future.add_done_callback(self._publish)

    def _publish(self, future: Future[RenderedView]) -> None:
        if future.cancelled():
            return  # a newer request replaced it before it ran
        try:
            view = future.result(0)  # done: never waits
        except WorkerStopped:
            return  # the node is shutting down
        except Exception as err:  # noqa: BLE001 - counted and logged; the next request may succeed
            self._stats.post_problem("render_failed", f"view not rendered: {type(err).__name__}: {err}")
            return
        self._stats.post_add(MergerStats.renders)  # before the images: whoever receives them sees the count
        self._color.publish(numpy_to_image(view.rgb, "rgb8", view.stamp_ns, RENDER_FRAME))
        self._depth.publish(depth_to_image(view.depth_m, "32FC1", view.stamp_ns, RENDER_FRAME))
        self._info.publish(camera_to_camera_info(self._camera, view.stamp_ns, RENDER_FRAME))

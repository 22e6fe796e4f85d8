"""keyframe_sampler node: Patch-Grid sampling of each keyframe into seeds for new Gaussians.

Subscribes (reliable): ``memgs/keyframe/{color,depth,camera_info,pose,keypoints}`` (one stamp per
keyframe; depth only in RGB-D mode, in REP-118 units as the tracker sends it; images undistorted
here). Publishes ``memgs/keyframe/seeds``: PointCloud2 with x, y, z (world, float32), rgb
(float32-packed 0x00RRGGBB, the PCL/RViz convention) and source (uint8: 0 keypoint, 1 Patch-Grid
sample), stamped like the keyframe.

A keyframe that cannot be used is refused whole (nothing is published for it) and counted on
``memgs/keyframe_sampler/stats`` as ``problem.<kind>``, with one warning per kind: ``camera_info``
(zero/NaN focal length, a distortion other than 5 plumb_bob coefficients), ``bad_image`` (unknown
or wrong encoding, step/size/data length disagreeing, 16UC1/32FC1 mix-ups), ``size_mismatch``
(colour, depth and camera_info of different sizes), ``empty_depth`` (RGB-D without a single valid
depth pixel), ``bad_pose``, ``bad_keypoints`` (missing u/v/depth fields, wrong row sizes) and
``bad_keyframe`` (anything else the sampler refuses).
"""
from __future__ import annotations

import sys

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from memgs_ros.core.geometry.view import undistorter_for, view_preparation
from memgs_ros.core.runtime.telemetry_fields import SamplerFields
from memgs_ros.core.sampling import PatchGridConfig, seeds_mono, seeds_rgbd
from memgs_ros.errors import DataError, MessageError
from memgs_ros.nodes.params import NODE_CONFIGS, KeyframeSamplerParams
from memgs_ros.ros import qos
from memgs_ros.ros.codecs import (
    pointcloud2_to_structured,
    stamp_to_ns,
    structured_to_pointcloud2,
)
from memgs_ros.ros.config_params import declare_config
from memgs_ros.ros.diagnostics import NodeStats
from memgs_ros.ros.keyframe_bundle import KeyframeBundleError, decode_keyframe_images
from memgs_ros.ros.lifecycle import ManagedNode
from memgs_ros.ros.node_main import run_node
from memgs_ros.ros.seed_cloud import encode_seeds
from memgs_ros.ros.stamp_sync import StampBundler

CONFIGS = NODE_CONFIGS["keyframe_sampler"]


class SamplerStats(NodeStats, SamplerFields):
    stats_name = "keyframe_sampler"


class KeyframeSamplerNode(ManagedNode):
    def __init__(self, **node_kwargs: object) -> None:
        super().__init__("keyframe_sampler", **node_kwargs)
        v = declare_config(self, KeyframeSamplerParams, "")
        self.niceness = v.niceness  # applied by run_node to this node's process
        self.mode, self.world_frame = v.mode, v.world_frame
        self.cfg: PatchGridConfig = declare_config(self, PatchGridConfig, "patch_grid")
        self.start_lifecycle(v.autostart)

    def configure_node(self) -> None:
        self.stats = SamplerStats(self)
        self.stats.kernels_warm = 1  # nothing to compile: warm as soon as it runs
        parts = {"color", "camera_info", "pose", "keypoints"} | ({"depth"} if self.mode == "rgbd" else set())
        self.bundler = StampBundler(parts, max_pending=16)
        self.n_keyframes = 0

        self.pub = self.create_publisher(PointCloud2, "memgs/keyframe/seeds", qos.keyframes())
        kf = qos.keyframes()  # a restarted sampler gets the latest keyframes again
        self.create_subscription(Image, "memgs/keyframe/color", lambda m: self._add("color", m), kf)
        self.create_subscription(CameraInfo, "memgs/keyframe/camera_info", lambda m: self._add("camera_info", m), kf)
        self.create_subscription(PoseStamped, "memgs/keyframe/pose", lambda m: self._add("pose", m), kf)
        self.create_subscription(PointCloud2, "memgs/keyframe/keypoints", lambda m: self._add("keypoints", m), kf)
        if self.mode == "rgbd":
            self.create_subscription(Image, "memgs/keyframe/depth", lambda m: self._add("depth", m), kf)

    def _add(self, part: str, msg) -> None:  # noqa: ANN001 - any of the bundle's message types
        if not self.active:  # paused (lifecycle inactive): the keyframe's parts are counted, not sampled
            self.stats.skipped["inactive"] += 1
            return
        bundle = self.bundler.add(part, stamp_to_ns(msg.header.stamp), msg)
        self.stats.pending_bundles, self.stats.dropped_bundles = self.bundler.pending, self.bundler.dropped
        if bundle is not None:
            self._sample(stamp_to_ns(msg.header.stamp), bundle)

    def _sample(self, stamp_ns: int, b: dict) -> None:
        # Each stage names the problem kind a failure in it is counted under (module docstring).
        stage = "bad_keypoints"
        try:
            kf = decode_keyframe_images(b, stamp_ns)
            cam, T_wc = kf.camera, kf.T_wc
            kps = pointcloud2_to_structured(b["keypoints"], required=("u", "v", "depth"))
            uv = np.stack([kps["u"], kps["v"]], axis=1).astype(np.float32)
            kp_depth = kps["depth"].astype(np.float32)
            placed = np.isfinite(uv).all(axis=1)  # a keypoint without a position is no keypoint
            uv, kp_depth = uv[placed], kp_depth[placed]
            stage = "bad_keyframe"
            kf_id = self.n_keyframes
            view = view_preparation(cam)  # full size: seeds are back-projected at source resolution
            rgb, depth = view(kf.rgb, kf.depth, kf.depth_scale)
            # Keypoints come undistorted in the source K; move them into the prepared view.
            uv = undistorter_for(cam).from_pinhole_uv(uv).astype(np.float32)
            cam = view.camera
            if depth is not None:
                seeds = seeds_rgbd(rgb, depth, cam, T_wc, kf_id, uv, kp_depth, self.cfg)  # rng from (seed, kf_id)
            else:
                seeds = seeds_mono(rgb, cam, T_wc, kf_id, uv, kp_depth, self.cfg)
        except KeyframeBundleError as err:
            self.stats.problem(err.kind, f"keyframe {stamp_ns} refused: {err}")
            return
        except (MessageError, DataError) as err:
            self.stats.problem(stage, f"keyframe {stamp_ns} refused: {err}")
            return
        self.n_keyframes += 1
        self.pub.publish(structured_to_pointcloud2(encode_seeds(seeds.points_w, seeds.colors, seeds.source),
                                                   stamp_ns, self.world_frame))
        self.stats.keyframes += 1
        self.stats.seeds_keypoint += int((seeds.source == 0).sum())
        self.stats.seeds_patch_grid += int((seeds.source == 1).sum())


def main(args: list[str] | None = None) -> int:
    return run_node(KeyframeSamplerNode, "keyframe_sampler", args)


if __name__ == "__main__":
    sys.exit(main())

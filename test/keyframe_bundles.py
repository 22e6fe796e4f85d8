"""Keyframe bundles as the tracker and sampler publish them (colour, depth, camera_info, pose,
keypoints, seeds), for the tests that feed a sampler or mapper node and those that decode bundles;
each test breaks one part at a time."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from memgs_ros.core.geometry.frame import Frame
from memgs_ros.ros.codecs import matrix_to_pose_stamped, structured_to_pointcloud2
from memgs_ros.ros.images import camera_to_camera_info, depth_to_image, numpy_to_image
from memgs_ros.ros.keyframe_bundle import KEYPOINT_DTYPE
from memgs_ros.ros.seed_cloud import encode_seeds

SPEC = "synthetic:w=64,h=48,n=6,seed=3"


@dataclass
class Bundle:
    """The messages of one keyframe, all stamped ``stamp``; tests break one part at a time."""

    stamp: int
    color: Image
    depth: Image
    info: CameraInfo
    pose: PoseStamped
    keypoints: PointCloud2
    seeds: PointCloud2


def _bundle(f: Frame, stamp: int) -> Bundle:
    rng = np.random.default_rng(stamp % 1000)
    h, w = f.depth_m.shape
    u, v = rng.integers(4, w - 4, 40), rng.integers(4, h - 4, 40)
    kps = np.zeros(40, KEYPOINT_DTYPE)
    kps["u"], kps["v"], kps["depth"], kps["active"] = u, v, f.depth_m[v, u], 1
    pts = rng.uniform(-1.0, 1.0, (50, 3)) + np.array([0.0, 0.0, 2.0])
    seeds = encode_seeds(pts, rng.uniform(0, 1, (50, 3)), np.ones(50, np.uint8))
    return Bundle(stamp, numpy_to_image(f.rgb, "rgb8", stamp, "cam"), depth_to_image(f.depth_m, "32FC1", stamp, "cam"),
                  camera_to_camera_info(f.camera, stamp, "cam"), matrix_to_pose_stamped(f.T_wc_gt, stamp, "map"),
                  structured_to_pointcloud2(kps, stamp, "cam"), structured_to_pointcloud2(seeds, stamp, "map"))


def _without_field(cloud: PointCloud2, name: str) -> PointCloud2:
    cloud.fields = [f for f in cloud.fields if f.name != name]
    return cloud

"""The keyframe as it crosses the tracker -> keyframe_sampler / mapper boundary, apart from the
mapper's torch code (``keyframes``): the sampler node handles it without loading torch."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.geometry.view import check_depth_scale


@dataclass(frozen=True, eq=False)
class KeyframeInput:
    """Stage boundary tracker -> keyframe_sampler / mapper: a keyframe as it arrives (a decoded
    bundle, images as recorded, not yet prepared), owned by the receiving node. The sampler reads
    its images; the mapper adds the sampler's seeds (``dataclasses.replace``) and hands it to the
    mapping session, which prepares it into a ``TrainingKeyframe``.

    stamp_ns: capture time (the keyframe's name on the wire); T_wc: [4, 4] camera-to-world;
    rgb: [H, W, 3] uint8; depth: [H, W] float32 metres (NaN/0 invalid) or uint16 raw units
    (``depth_scale`` per metre, 0 invalid), or None; camera: the images' intrinsics with
    distortion; points_w: [M, 3] world seeds; colors: [M, 3] in [0, 1] (None: no seeds);
    decided_ns: when the tracker decided on the keyframe (its wall clock, ns; 0 unknown), from
    which the mapper counts the keyframe's latency to its first training step.

    The images may be read-only views on the received messages: nothing writes them.
    """

    stamp_ns: int
    T_wc: np.ndarray
    rgb: np.ndarray
    depth: np.ndarray | None
    camera: PinholeCamera
    points_w: np.ndarray | None = None
    colors: np.ndarray | None = None
    depth_scale: float = 1.0
    decided_ns: int = 0


SEED_CHECK_POINTS = 256  # seeds projected to check the depth scale (~0.1 ms)


def check_seed_depths(kf: KeyframeInput, depth_scale_param: float) -> None:
    """DataError when the keyframe's depth image, read with this node's ``depth_scale``, puts the
    surfaces at another scale than the seeds the keyframe_sampler made from it (its own reading):
    the two nodes' depth_scale parameters disagree. Seeds are projected into the source image
    (with its distortion) and compared with the raw depth there. Nothing to check without depth
    or with fewer than 20 seeds that land on a measured pixel."""
    if kf.depth is None or kf.points_w is None or len(kf.points_w) == 0:
        return
    pts = np.asarray(kf.points_w, dtype=np.float64)
    pts = pts[:: max(1, len(pts) // SEED_CHECK_POINTS)]
    T_cw = invert_pose(np.asarray(kf.T_wc, dtype=np.float64))
    p_c = pts @ T_cw[:3, :3].T + T_cw[:3, 3]
    p_c = p_c[p_c[:, 2] > 1e-3]
    if len(p_c) == 0:
        return
    cam = kf.camera
    uv, _ = cv2.projectPoints(p_c.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    check_depth_scale(kf.depth, uv.reshape(-1, 2), p_c[:, 2], "the keyframe_sampler's seeds", depth_scale_param,
                      kf.depth_scale)

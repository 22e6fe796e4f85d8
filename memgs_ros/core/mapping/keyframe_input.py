"""The keyframe as it crosses the tracker -> keyframe_sampler / mapper boundary, apart from the
mapper's torch code (``keyframes``): the sampler node handles it without loading torch."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera


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

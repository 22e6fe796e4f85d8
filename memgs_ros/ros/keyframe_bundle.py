"""The common part of a keyframe bundle (tracker -> sampler, mapper): camera, images and pose.

Both consumers refuse a bad keyframe whole and count the problem by kind, so the decoder says
which check failed: ``camera_info``, ``bad_image``, ``size_mismatch``, ``empty_depth`` or
``bad_pose`` (see the nodes' docstrings).
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from memgs_ros.core.mapping.keyframe_input import KeyframeInput
from memgs_ros.errors import DataError, MessageError
from memgs_ros.io.image_decoding import (
    DEFAULT_DEPTH_SCALE as REP118_MM,  # 16UC1 in REP-118: millimetres
)
from memgs_ros.io.image_decoding import (
    check_image_sizes,
    decode_camera_info,
    depth_view,
    has_valid_depth,
    rgb_view,
)
from memgs_ros.ros.codecs import pose_to_matrix


class KeyframeBundleError(MessageError):
    """A keyframe bundle refused; ``kind`` is the problem kind it is counted under."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def decode_keyframe_images(bundle: Mapping[str, Any], stamp_ns: int, decided_ns: int = 0) -> KeyframeInput:
    """Decode ``camera_info``, ``color``, ``pose`` and, when present, ``depth`` of the bundle of
    keyframe ``stamp_ns`` (no seeds: the mapper adds the sampler's).

    The images stay as the tracker forwarded them: colour a read-only view on the message where
    it is rgb8, depth in REP-118's units as the tracker sends it (16UC1 millimetres or 32FC1
    metres, ``codecs.rep118_depth``). The
    bundle's messages must outlive the returned keyframe's use (the caller holds them).
    Raises KeyframeBundleError naming the kind of the first check that fails.
    """
    kind = "camera_info"
    try:
        camera = decode_camera_info(bundle["camera_info"])
        kind = "bad_image"
        rgb = rgb_view(bundle["color"])
        depth, scale = depth_view(bundle["depth"], REP118_MM) if "depth" in bundle else (None, 1.0)
        kind = "size_mismatch"
        check_image_sizes(rgb, depth, camera)
        if depth is not None and not has_valid_depth(depth):
            kind = "empty_depth"
            raise MessageError("depth has no valid pixel (all zero, NaN, inf or negative)")
        kind = "bad_pose"
        T_wc = pose_to_matrix(bundle["pose"].pose)
    except (MessageError, DataError) as err:
        raise KeyframeBundleError(kind, str(err)) from err
    return KeyframeInput(stamp_ns, T_wc, rgb, depth, camera, depth_scale=scale, decided_ns=decided_ns)

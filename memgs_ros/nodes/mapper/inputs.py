"""The mapper's inputs as the session takes them: each keyframe's parts (``memgs/keyframe/*``,
one stamp) gathered and decoded into a ``KeyframeInput`` with the sampler's seeds, or refused
whole by kind; keyframe poses from a ``Path`` (refined or loop-corrected)."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from nav_msgs.msg import Path

from memgs_ros.core.mapper_service.keyframe_decisions import DecisionTimes
from memgs_ros.core.mapping.keyframe_input import KeyframeInput
from memgs_ros.errors import DataError, MessageError
from memgs_ros.ros.codecs import pointcloud2_to_structured, pose_to_matrix, stamp_to_ns
from memgs_ros.ros.keyframe_bundle import KeyframeBundleError, decode_keyframe_images
from memgs_ros.ros.seed_cloud import decode_seeds
from memgs_ros.ros.stamp_sync import KeyframeIntake

__all__ = ["KeyframeReceiver", "ReceivedKeyframe", "keyframe_poses"]


@dataclass(frozen=True)
class ReceivedKeyframe:
    """A complete bundle: its ``keyframe``, or None and the ``problem`` kind and log line that
    refused it (the bundle decoder's kinds, ``bad_seeds``)."""

    stamp_ns: int
    keyframe: KeyframeInput | None
    problem: str = ""
    message: str = ""


class KeyframeReceiver:
    """Gathers a mapper's keyframe parts by stamp (``KeyframeIntake``: replayed parts of keyframes
    seen complete, or ``known`` from a checkpoint, are counted and ignored) and decodes each
    complete bundle, its depth in REP-118's units as the tracker sends it. The pose's publication
    time is the tracker's decision: the keyframe's latency counts from it."""

    def __init__(self, parts: set[str], known: frozenset[int]) -> None:
        self.intake = KeyframeIntake(parts, known=known)
        self._decided = DecisionTimes()

    def add(self, part: str, msg: Any, info: dict[str, Any]) -> ReceivedKeyframe | None:
        """One part (``info``: rclpy's message info); the keyframe once its bundle is complete."""
        stamp = stamp_to_ns(msg.header.stamp)
        if part == "pose":
            self._decided.decided(stamp, int(info.get("source_timestamp") or 0))
        bundle = self.intake.add(part, stamp, msg)
        if bundle is None:
            return None
        stage = "bad_seeds"
        try:
            kf = decode_keyframe_images(bundle, stamp, decided_ns=self._decided.take(stamp))
            points, colors = decode_seeds(pointcloud2_to_structured(bundle["seeds"]))
            kf = replace(kf, points_w=points, colors=colors)
        except KeyframeBundleError as err:
            return ReceivedKeyframe(stamp, None, err.kind, f"keyframe {stamp} refused: {err}")
        except (MessageError, DataError) as err:
            return ReceivedKeyframe(stamp, None, stage, f"keyframe {stamp} refused: {err}")
        return ReceivedKeyframe(stamp, kf)


def keyframe_poses(msg: Path) -> tuple[dict[int, np.ndarray], list[str]]:
    """{keyframe stamp: T_wc [4, 4]} of a Path, and a line for each pose refused (``bad_pose``)."""
    poses: dict[int, np.ndarray] = {}
    refused: list[str] = []
    for p in msg.poses:
        try:
            poses[stamp_to_ns(p.header.stamp)] = pose_to_matrix(p.pose)
        except (MessageError, DataError) as err:
            refused.append(f"refined pose of keyframe {stamp_to_ns(p.header.stamp)} ignored: {err}")
    return poses, refused

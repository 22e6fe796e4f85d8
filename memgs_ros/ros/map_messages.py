"""Map messages on the wire (sensor_msgs/PointCloud2) for the nodes that receive or publish whole
maps: the merger and the Rerun bridge. The format itself is :mod:`memgs_ros.core.map_io.map_delta`;
``viewer_cloud_message`` is the plain cloud for RViz and Foxglove (``memgs/map/points``)."""
from __future__ import annotations

import numpy as np
from sensor_msgs.msg import PointCloud2

from memgs_ros.core.map_io.map_delta import MapMessage, MapReplica, MessageKind, decode, encode, viewer_points
from memgs_ros.errors import MessageError
from memgs_ros.ros.codecs import pointcloud2_to_structured, structured_to_pointcloud2
from memgs_ros.ros.diagnostics import NodeStats

__all__ = ["decode_map_message", "full_map_message", "viewer_cloud_message"]


def decode_map_message(msg: PointCloud2, stats: NodeStats) -> MapMessage | None:
    """The delta or snapshot in ``msg``; None for one that cannot be decoded (missing fields,
    rows of the wrong size, a malformed META row), counted as ``problem.bad_map_message``."""
    try:
        return decode(pointcloud2_to_structured(msg))
    except MessageError as err:
        stats.problem("bad_map_message", f"map message dropped: {err}")
        return None


def full_map_message(replica: MapReplica, stamp_ns: int, frame_id: str) -> PointCloud2:
    """The whole replica as a snapshot message with the packed ``rgb`` colour viewers read."""
    rows = encode(MessageKind.SNAPSHOT, replica.seq, len(replica), replica.records, np.zeros(0, np.int64),
                  sh_degree=3, epoch=replica.epoch, rgb=True)
    return structured_to_pointcloud2(rows, stamp_ns, frame_id)


def viewer_cloud_message(replica: MapReplica, stamp_ns: int, frame_id: str) -> PointCloud2:
    """The replica's Gaussians as x, y, z, rgb, opacity points: every row a Gaussian (the map
    message's row 0 is its META row, whose x and y hold the map epoch: a viewer drew it as a point
    kilometres away)."""
    return structured_to_pointcloud2(viewer_points(replica.records), stamp_ns, frame_id)

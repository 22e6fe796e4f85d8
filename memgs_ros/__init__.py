"""memgs_ros: MemGS memory-efficient Gaussian-splatting SLAM as ROS 2 nodes.

``memgs_ros.core`` and ``memgs_ros.io`` never import rclpy; ``memgs_ros.ros`` and
``memgs_ros.nodes`` are the thin ROS layer.
"""
import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

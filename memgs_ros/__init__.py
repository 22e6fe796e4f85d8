"""memgs_ros: MemGS memory-efficient Gaussian-splatting SLAM as ROS 2 nodes.

``memgs_ros.core`` and ``memgs_ros.io`` never import rclpy; ``memgs_ros.ros`` and
``memgs_ros.nodes`` are the thin ROS layer.
"""
import logging
import os
import sys

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())


def _default_numba_cache() -> None:
    """Compiled kernels are cached in a writable per-user folder ($XDG_CACHE_HOME or ~/.cache,
    then memgs_ros/numba) unless NUMBA_CACHE_DIR says where: numba's default, beside the sources,
    is read-only in an installed package (/opt/ros/...), and a node would then compile its kernels
    anew at every start. Set here, before anything imports numba (child processes inherit it)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    os.environ["NUMBA_CACHE_DIR"] = os.path.join(base, "memgs_ros", "numba")
    config = sys.modules.get("numba.core.config")
    if config is not None and not getattr(config, "CACHE_DIR", ""):  # numba came first: tell it too
        setattr(config, "CACHE_DIR", os.environ["NUMBA_CACHE_DIR"])  # noqa: B010 - a module numba made


_default_numba_cache()

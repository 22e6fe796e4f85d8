"""The mapper node's own ROS parameters as one typed config (declared with ``declare_config``;
the mapping and merge parameters are ``mapping.*`` / ``merge.*``, see core/mapping.py, core/merge.py)."""
from __future__ import annotations

from dataclasses import dataclass

from memgs_ros.errors import ConfigError


@dataclass(frozen=True)
class MapperParams:
    mode: str = "rgbd"  # camera mode: rgbd, or mono (keyframes carry no depth)
    depth_scale: float = 1000.0  # 16UC1 keyframe depth units per metre (the tracker publishes 32FC1 metres)
    device: str = "auto"  # torch device for the map: auto (CUDA when present), cpu, cuda, cuda:N
    lockstep: bool = False  # train a fixed number of iterations per frame and acknowledge each (deterministic replay)
    lockstep_iterations: int = 10  # training iterations per frame in lockstep mode
    final_iterations: int = 0  # extra training iterations run by the finish service before the final flush
    # densify during the final iterations too (false: they only refine the map, which then keeps its size)
    final_densify: bool = True
    delta_rate_hz: float = 1.0  # map deltas per second
    # link budget for map deltas; the largest changes go first, the rest wait (the final flush ignores it)
    delta_budget_kbytes_per_s: float = 500.0
    # send a Gaussian again only when a parameter moved more than this (m, or pre-activation units);
    # the final flush is exact
    delta_tolerance: float = 1e-3
    snapshot_period_s: float = 0.0  # publish a full snapshot this often (0 = only on request)
    render_rate_hz: float = 1.0  # live view renders per second (0 = off)
    world_frame: str = "map"  # frame id of published maps and poses
    ack_topic: str = "memgs/frame_ack"  # lockstep acknowledgement topic (to the player)
    checkpoint_path: str = ""  # file for map + keyframe checkpoints (.npz); empty = no checkpoints
    # write a checkpoint this often while the map changes (0 = only at finish/shutdown)
    checkpoint_period_s: float = 30.0
    resume: bool = True  # start from the checkpoint at checkpoint_path when one exists
    # free-running: complete keyframes waiting for insertion; when full the oldest is dropped and counted
    # (problem.keyframe_overload)
    insert_queue: int = 4

    def __post_init__(self) -> None:
        if self.mode not in ("rgbd", "mono"):
            raise ConfigError(f"mode must be rgbd or mono, got {self.mode!r}")


RANGES: dict[str, tuple[float, float]] = {
    "depth_scale": (1e-3, 1e6), "lockstep_iterations": (0, 10000), "final_iterations": (0, 10**7),
    "delta_rate_hz": (0.01, 100.0), "delta_budget_kbytes_per_s": (1.0, 1e7), "delta_tolerance": (0.0, 10.0),
    "snapshot_period_s": (0.0, 1e6), "render_rate_hz": (0.0, 60.0), "checkpoint_period_s": (0.0, 1e6),
    "insert_queue": (1, 1000),
}

"""A mapper's start, without ROS: the device and rasterizer checked and chosen, the checkpoint
resumed from (or set aside when this mapper cannot take it), the mapping session started, and the
kernels its first command loads."""
from __future__ import annotations

import pathlib
import secrets
from dataclasses import dataclass

from memgs_ros.core.map_io.bundle import MAPPER_FILE, resolve_bundle
from memgs_ros.core.mapper_service.session import MappingSession
from memgs_ros.core.mapping import losses
from memgs_ros.core.mapping.checkpoint import CheckpointFile, MapperCheckpoint
from memgs_ros.core.mapping.checkpoint import load as load_checkpoint
from memgs_ros.core.mapping.config import MappingConfig
from memgs_ros.core.merge.config import MergeConfig
from memgs_ros.core.raster import warm_up
from memgs_ros.core.raster.backend_choice import BackendChoice, choose_backend, device_problem, resolve_device
from memgs_ros.core.runtime.cpu import configure_cpu_runtime
from memgs_ros.core.runtime.replay import Pacing
from memgs_ros.errors import ConfigError, DataError

__all__ = ["MapperStart", "SessionOptions", "start_mapper", "warm_kernels"]


@dataclass(frozen=True)
class SessionOptions:
    """The mapper's parameters that shape its session (``MapperParams``: pacing, insert_queue,
    delta_tolerance, niceness; checkpoint_path empty: no checkpoints)."""

    pacing: Pacing = Pacing.LIVE
    insert_queue: int = 4
    delta_tolerance: float = 1e-3
    niceness: int = 0
    checkpoint_path: str = ""
    resume: bool = True
    map_bundle: str = ""  # a saved map bundle to continue when there is no checkpoint of this mapper's own
    frozen: bool = False  # never train (localize: the loaded map is only rendered)


@dataclass(frozen=True)
class MapperStart:
    """A started mapper: its session on ``device`` with the ``raster`` backend; ``checkpoint``
    the file it writes (None: none); ``resumed`` the state it started from (None: an empty map),
    ``from_bundle`` the map bundle it came from (None: this mapper's own checkpoint);
    ``set_aside`` the line to log when a checkpoint could not be resumed and was moved away."""

    session: MappingSession
    device: str
    raster: BackendChoice
    checkpoint: CheckpointFile | None
    resumed: MapperCheckpoint | None
    set_aside: str | None
    from_bundle: pathlib.Path | None = None


def start_mapper(cfg: MappingConfig, merge_cfg: MergeConfig, device_param: str, opts: SessionOptions) -> MapperStart:
    """Check and choose the device (``device_param``: auto, cpu, cuda, cuda:N) and rasterizer
    (ConfigError naming what to install or set), then start the session, from the checkpoint when
    ``opts.resume`` and there is one."""
    problem = device_problem(device_param, cfg.raster_backend)
    if problem:
        raise ConfigError(problem)
    device = resolve_device(device_param)
    raster = choose_backend(device, cfg.raster_backend)  # what warm_up and training will run
    if device == "cpu":
        configure_cpu_runtime()
    ckpt = CheckpointFile(pathlib.Path(opts.checkpoint_path).expanduser()) if opts.checkpoint_path else None
    resumed, why = ckpt.read_or_set_aside() if opts.resume and ckpt else (None, None)
    bundle = None
    if resumed is None and opts.map_bundle:  # a crash's own checkpoint is newer than any bundle
        try:
            bundle = resolve_bundle(opts.map_bundle)
            resumed = load_checkpoint(bundle / MAPPER_FILE)
        except DataError as err:
            raise ConfigError(f"cannot continue map bundle {opts.map_bundle}: {err}") from err

    def start(state: MapperCheckpoint | None) -> MappingSession:
        # A new delta epoch every start: a merger that held the map of an earlier life resynchronises.
        free_running = not (opts.pacing.acknowledged or opts.frozen)
        return MappingSession(cfg, device, merge_cfg=merge_cfg, free_running=free_running,
                              insert_queue=opts.insert_queue, delta_tolerance=opts.delta_tolerance,
                              delta_epoch=secrets.randbits(32), niceness=opts.niceness, checkpoint=state)

    try:
        session = start(resumed)
    except DataError as err:  # read, but not a state this mapper can take: set it aside
        if bundle is not None:  # a saved map is never moved away: refused, named
            raise ConfigError(f"cannot continue map bundle {opts.map_bundle}: {err}") from err
        if ckpt is None or resumed is None:
            raise
        resumed, why = None, ckpt.set_aside(err)
        session = start(None)
    return MapperStart(session, device, raster, ckpt, resumed, why, bundle)


def warm_kernels(device: str, cfg: MappingConfig) -> None:
    """Load (on a fresh install: compile) the rasterizer's and SSIM's kernels: the session's first
    command, so a keyframe's first training step does not wait for them."""
    warm_up(device, cfg.raster_backend, cfg.max_sh_degree)
    losses.warm_up(device)

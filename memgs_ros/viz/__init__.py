"""The Rerun view of a run or a saved map (the optional ``[viz]`` extra: ``pip install 'memgs_ros[viz]'``).

- :mod:`memgs_ros.viz.splats`: map records to splat arrays (numpy only, no Rerun).
- :mod:`memgs_ros.viz.rerun_log`: typed functions that log map, poses, frusta, images and
  scalars to a given ``rerun.RecordingStream`` (imports rerun: load it after
  :func:`require_rerun`).
- :class:`RerunTarget`: where a recording goes (spawned viewer, remote viewer, ``.rrd`` file).

Nothing here imports rclpy; importing this package does not import rerun either, so everything
else works without the extra and a Rerun option fails with one line naming it.
"""
from __future__ import annotations

import os
import socket
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from types import ModuleType
from typing import Any

from memgs_ros.errors import ConfigError

__all__ = ["MIN_RERUN", "VIEWER_PORT", "RerunTarget", "require_rerun"]

# The first rerun-sdk with the GaussianSplats3D archetype (0.35 has none); setup.py's [viz] pins it.
MIN_RERUN = "0.36"
VIEWER_PORT = 9876  # rerun's default gRPC port: `rerun` and rr.spawn listen here
INSTALL_HINT = "pip install 'memgs_ros[viz]'"


def require_rerun() -> ModuleType:
    """The ``rerun`` module; ConfigError naming the extra when it is missing or too old."""
    try:
        import rerun
    except ImportError as err:
        raise ConfigError(f"the Rerun view needs rerun-sdk >= {MIN_RERUN}, which is not installed: "
                          f"{INSTALL_HINT}") from err
    if not hasattr(rerun, "GaussianSplats3D"):
        version = getattr(rerun, "__version__", "?")
        raise ConfigError(f"rerun-sdk {version} has no Gaussian splats (needs >= {MIN_RERUN}): "
                          f"pip install -U 'memgs_ros[viz]'")
    return rerun


@dataclass(frozen=True)
class RerunTarget:
    """Where a Rerun recording goes; any combination of the three sinks, at least one.

    spawn: start a local viewer (or use the one already listening on :data:`VIEWER_PORT`).
    connect_url: stream to a viewer elsewhere, e.g. ``rerun+http://192.168.1.5:9876/proxy``.
    save_path: write an ``.rrd`` file (rerun writes it as the run goes).
    """

    spawn: bool = False
    connect_url: str = ""
    save_path: Path | None = None

    def __post_init__(self) -> None:
        if not (self.spawn or self.connect_url or self.save_path):
            raise ConfigError("a Rerun target needs a viewer to spawn, a URL or a file to save")
        if self.connect_url and not self.connect_url.startswith(("rerun://", "rerun+http://", "rerun+https://")):
            raise ConfigError(f"Rerun URL must look like rerun+http://HOST:9876/proxy, got {self.connect_url!r}")

    def check(self) -> None:
        """Fail before any node starts: rerun-sdk importable, a display (or a viewer already
        listening) for ``spawn``, and a folder for the ``.rrd`` file."""
        require_rerun()
        if self.spawn and not _can_show_viewer():
            raise ConfigError("cannot spawn a Rerun viewer: no display (DISPLAY / WAYLAND_DISPLAY unset) and no "
                              f"viewer listening on port {VIEWER_PORT}; save an .rrd file instead, or stream to a "
                              "viewer elsewhere (rerun+http://HOST:9876/proxy)")
        if self.save_path is not None:
            folder = Path(self.save_path).expanduser().resolve().parent
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as err:
                raise ConfigError(f"cannot write the Rerun recording {self.save_path}: {err.strerror or err}") from err
            if Path(self.save_path).is_dir():
                raise ConfigError(f"Rerun recording {self.save_path} is a folder; give a file name (run.rrd)")

    def node_params(self) -> dict[str, Any]:
        """The rerun_bridge parameters that select these sinks."""
        return {"spawn": bool(self.spawn), "connect_url": self.connect_url,
                "save_path": str(Path(self.save_path).expanduser().resolve()) if self.save_path else ""}

    def for_variant(self, name: str) -> RerunTarget:
        """The target of one of several runs (an ablation's variants): ``run.rrd`` -> ``run_<name>.rrd``
        so the runs do not overwrite one file; live sinks are shared (each run is its own recording)."""
        if self.save_path is None:
            return self
        path = Path(self.save_path)
        return replace(self, save_path=path.with_name(f"{path.stem}_{name}{path.suffix or '.rrd'}"))

    def open(self, application_id: str, recording_name: str = "", recording_id: str | None = None) -> Any:
        """A ``rerun.RecordingStream`` sending to every sink of this target (spawning the viewer first)."""
        rr = require_rerun()
        rec = rr.RecordingStream(application_id, recording_id=recording_id)
        sinks: list[Any] = []
        if self.spawn:
            # connect=False: the sinks below carry the data, so the file and the viewer get the same stream.
            rec.spawn(port=VIEWER_PORT, connect=False)
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{VIEWER_PORT}/proxy"))
        if self.connect_url:
            sinks.append(rr.GrpcSink(self.connect_url))
        if self.save_path is not None:
            sinks.append(rr.FileSink(str(Path(self.save_path).expanduser())))
        rec.set_sinks(*sinks)
        if recording_name:
            rec.send_recording_name(recording_name)
        return rec


def _can_show_viewer() -> bool:
    """True where a spawned viewer can open a window, or a viewer already listens locally."""
    if sys.platform != "linux" or os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return True
    try:
        with socket.create_connection(("127.0.0.1", VIEWER_PORT), timeout=0.5):
            return True
    except OSError:
        return False

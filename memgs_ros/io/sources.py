"""One entry point for every frame input: ``open_source(spec)``.

``spec`` is a TUM RGB-D folder, a bag (ROS 1 ``.bag`` file, ROS 2 bag directory, bare
``.mcap`` / ``.db3`` file) or a synthetic spec string (``synthetic:w=160,h=120,n=60``, keys
in ``memgs_ros.io.synthetic``). Every source has ``.camera`` (with distortion), ``.name``,
``len()``, iteration over ``Frame`` in stamp order, and ``ground_truth()`` -> the whole
ground-truth trajectory (stamps_ns [M], T_wc [M, 4, 4]), empty arrays when there is none.
"""
from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.io.bag_reader import BagSource, BagTopics
from memgs_ros.io.frame_source import FrameSource as FrameSource  # the readers' protocol, here too
from memgs_ros.io.image_decoding import DEFAULT_DEPTH_SCALE
from memgs_ros.io.repeat import PlannedSource, RepeatedSource
from memgs_ros.io.synthetic import (
    SyntheticScene,
    SyntheticSpec,
    build_scene,
    generate_frames,
    is_spec_string,
    parse_spec,
    trajectory,
)
from memgs_ros.io.tum import TumFolder, folder_depth_factor

BAG_SUFFIXES = (".bag", ".mcap", ".db3")


class SyntheticSource:
    """The synthetic room as a frame source; the scene is baked once, on first iteration."""

    def __init__(self, spec: SyntheticSpec, with_depth: bool = True, max_frames: int | None = None) -> None:
        self.spec = spec
        self.with_depth = with_depth
        self._n = spec.total_frames if max_frames is None else min(max_frames, spec.total_frames)
        self.name = spec.to_string()
        self._scene: SyntheticScene | None = None

    @property
    def camera(self) -> PinholeCamera:
        return self.spec.camera

    def __len__(self) -> int:
        return self._n

    def __iter__(self) -> Iterator[Frame]:
        if self._scene is None:
            self._scene = build_scene(self.spec.seed)
        for f in itertools.islice(generate_frames(self.spec, self._scene), self._n):
            yield f if self.with_depth else replace(f, depth_m=None)

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        stamps, poses = trajectory(self.spec)
        return stamps[: self._n], poses[: self._n]

    def frame_stamps(self) -> np.ndarray:
        """[N] int64 the stamps of the frames, in order."""
        return trajectory(self.spec)[0][: self._n]


def source_kind(spec: str | os.PathLike[str]) -> str:
    """'synthetic', 'tum' or 'bag' for a spec; DataError when it is none of them."""
    if is_spec_string(spec):  # type: ignore[arg-type]
        return "synthetic"
    p = Path(spec)
    if not p.exists():
        raise DataError(f"{p}: no such file or directory (expected a TUM folder, a bag or 'synthetic:...')")
    if p.is_dir():
        if (p / "rgb.txt").is_file():
            return "tum"
        if (p / "metadata.yaml").is_file() or any(q.suffix in (".mcap", ".db3") for q in p.iterdir()):
            return "bag"
        raise DataError(f"{p}: directory is neither a TUM folder (rgb.txt) nor a ROS 2 bag (metadata.yaml)")
    if p.suffix in BAG_SUFFIXES:
        return "bag"
    raise DataError(f"{p}: unknown input; expected a TUM folder, a {'/'.join(BAG_SUFFIXES)} bag or 'synthetic:...'")


_TUM_TOPICS = BagTopics()


def player_depth_units(spec: str | os.PathLike[str]) -> float:
    """The units a metre of the 16UC1 depth a replay of ``spec`` publishes: a TUM folder's PNGs go
    out as stored (its depth factor, 5000 for TUM's own), depth read as metres in REP-118's
    millimetres. The tracker reads the replay with these (``memgs run`` sets its ``depth_scale``)."""
    is_tum = not is_spec_string(spec) and (Path(spec) / "rgb.txt").is_file()  # type: ignore[arg-type]
    return folder_depth_factor(Path(spec)) if is_tum else 1000.0


def open_source(spec: str | os.PathLike[str], camera: PinholeCamera | None = None, max_dt_s: float = 0.02, *,
                depth_factor: float | None = None, depth_scale: float = DEFAULT_DEPTH_SCALE,
                topics: BagTopics = _TUM_TOPICS, with_depth: bool = True,
                max_frames: int | None = None, default_camera: PinholeCamera | None = None,
                strict: bool = False, repeat: int = 1, repeat_forward: bool = False,
                raw_depth: bool = False) -> FrameSource:
    """Open any frame input (module docstring).

    camera: overrides the camera from the data (TUM name/camera.json, bag CameraInfo);
      not allowed for synthetic specs, whose camera the spec defines.
    default_camera: the camera of a TUM folder that names none (no camera.json, no
      freiburg1/2/3 in its name), e.g. a configured calibration; ignored by other sources.
    max_dt_s: colour/depth pairing tolerance. depth_factor: TUM PNG units per metre
      (default from the folder). depth_scale: 16UC1 bag depth units per metre.
    topics: bag topic/frame names. with_depth: False = colour only (monocular).
    max_frames: keep only the first N frames. strict: a bad frame of a TUM folder or bag is a
      DataError instead of being skipped and counted in the source's ``skipped``.
    repeat: play the (first ``max_frames``) frames this many times, every other pass backward,
      ground truth re-stamped with them (:class:`memgs_ros.io.repeat.RepeatedSource`: a long
      flight over the same room); ``repeat_forward``: every pass forward, jumping back between them.
    raw_depth: a TUM folder's frames carry its depth PNGs as stored (``DepthUnits``) instead of metres.
    """
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"max_frames must be >= 1, got {max_frames}")
    if not isinstance(repeat, int) or repeat < 1:
        raise ConfigError(f"repeat must be an integer >= 1, got {repeat!r}")
    kind = source_kind(spec)
    if kind == "synthetic":
        if camera is not None:
            raise ConfigError("a synthetic source defines its own camera (w=, h=); do not pass one")
        s = parse_spec(str(spec))
        if max_frames is not None and s.laps == 1 and max_frames < s.n_frames:
            s = replace(s, n_frames=max_frames)
        source: PlannedSource = SyntheticSource(s, with_depth=with_depth, max_frames=max_frames)
    elif kind == "tum":
        source = TumFolder(spec, camera=camera, depth_factor=depth_factor, max_dt_s=max_dt_s, with_depth=with_depth,
                           max_frames=max_frames, default_camera=default_camera, strict=strict, raw_depth=raw_depth)
    else:
        source = BagSource(spec, topics=topics, camera=camera, max_dt_s=max_dt_s, depth_scale=depth_scale,
                           with_depth=with_depth, max_frames=max_frames, strict=strict)
    return source if repeat == 1 else RepeatedSource(source, repeat, forward_only=repeat_forward)


__all__ = ["FrameSource", "SyntheticSource", "open_source", "player_depth_units", "source_kind"]

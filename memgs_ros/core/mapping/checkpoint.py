"""Mapper checkpoints: the Gaussian map and the keyframes it trains on, in one atomic file.

The mapper writes its own state (``GaussianMapper.state_dict`` / ``load_state_dict``, wrapped by
``MappingSession.state_dict`` which adds its keyframe-stamp table); this module holds the record
types and the file format, nothing that reaches into a mapper.

A mapper that dies mid-flight (out of memory, a crash, a power cut on the vehicle) resumes
from its last checkpoint instead of from nothing. The file is a NumPy ``.npz`` archive
(uncompressed zip of ``.npy`` arrays, read with ``allow_pickle=False``: nothing in it is
executable) holding:

- the Gaussians: ids, parameters (PLY layout, pre-activation), creating keyframe id and
  creation iteration;
- every keyframe as the mapper trains on it: id, stamp, camera-to-world pose, the prepared
  (undistorted, resized) colour image as uint8, depth, valid-pixel mask, pinhole camera and
  exposure correction;
- a JSON header: format version, training iteration, next Gaussian id, active SH degree,
  scene extent, the time it was written, and the caller's ``extra`` (the mapper node keeps
  its keyframe-stamp table and delta sequence there).

Adam moments are not saved (a restored map restarts them at zero, as merged Gaussians do).
Files are written to a temporary name in the same folder, flushed to disk, then renamed over
the old one, so a reader only ever sees a complete checkpoint.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from memgs_ros.core.gaussians.gaussian_map import PLY_F_REST, GaussianRecords
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.runtime.npz_file import read_npz, write_npz
from memgs_ros.errors import DataError

FORMAT_VERSION = 1
# A resumed mapper numbers new Gaussians from the next multiple of this, above every id the
# dead one could have handed out after its checkpoint: ids are never reused.
ID_BLOCK = 1 << 32


@dataclass(frozen=True, eq=False)
class KeyframeState:
    """Stage boundary mapper -> checkpoint file: one keyframe as trained on, in host memory (the
    mapper's ``TrainingKeyframe`` on its way to disk and back). image: [h, w, 3] uint8; depth_m:
    [h, w] float32 (0 = none) or None; valid_mask: [h, w] bool or None; T_wc: [4, 4] float64."""

    kf_id: int
    stamp_ns: int
    T_wc: np.ndarray
    image: np.ndarray
    depth_m: np.ndarray | None
    valid_mask: np.ndarray | None
    camera: PinholeCamera
    exposure: tuple[float, ...] | None = None  # (gain offsets rgb, biases rgb), core/mapping/exposure.py
    uses: int = -1  # training draws so far (the coarse-to-fine schedule); -1: unknown (taken as trained)


@dataclass(frozen=True, eq=False)
class MapperCheckpoint:
    """Everything a mapper needs to resume. keyframe_ids / created_iter: [N] int64, aligned
    with ``gaussians``."""

    gaussians: GaussianRecords
    keyframe_ids: np.ndarray
    created_iter: np.ndarray
    keyframes: tuple[KeyframeState, ...]  # the training store
    iteration: int  # training steps so far
    next_id: int  # the next Gaussian id (ids are never reused)
    active_sh_degree: int  # the SH degree training had reached
    scene_extent: float  # m, the densification scale
    saved_at_s: float = 0.0  # wall clock
    extra: dict[str, Any] = field(default_factory=dict)  # free-form, for diagnosis


# ------------------------------------------------------------------------------ files
def save(ckpt: MapperCheckpoint, path: str | os.PathLike[str]) -> Path:
    """Write ``ckpt`` to ``path`` atomically (temporary file, fsync, rename). Returns the path."""
    path = Path(path)
    g = ckpt.gaussians
    header = {"format": FORMAT_VERSION, "iteration": ckpt.iteration, "next_id": ckpt.next_id,
              "active_sh_degree": ckpt.active_sh_degree, "scene_extent": ckpt.scene_extent,
              "saved_at_s": ckpt.saved_at_s, "extra": ckpt.extra,
              "keyframes": [{"kf_id": k.kf_id, "stamp_ns": k.stamp_ns, "camera": k.camera.as_dict(),
                             "depth": k.depth_m is not None, "mask": k.valid_mask is not None,
                             "exposure": None if k.exposure is None else [float(x) for x in k.exposure],
                             "uses": int(k.uses)}
                            for k in ckpt.keyframes]}
    arrays: dict[str, np.ndarray] = {
        "ids": g.ids.astype(np.int64), "xyz": g.xyz, "f_dc": g.f_dc, "f_rest": g.f_rest,
        "opacity": g.opacity, "scale": g.scale, "rot": g.rot,
        "keyframe_ids": ckpt.keyframe_ids.astype(np.int64), "created_iter": ckpt.created_iter.astype(np.int64),
    }
    for i, k in enumerate(ckpt.keyframes):
        arrays[f"kf{i}_T_wc"] = k.T_wc
        arrays[f"kf{i}_image"] = k.image
        if k.depth_m is not None:
            arrays[f"kf{i}_depth"] = k.depth_m
        if k.valid_mask is not None:
            arrays[f"kf{i}_mask"] = k.valid_mask
    return write_npz(path, header, arrays)


def load(path: str | os.PathLike[str]) -> MapperCheckpoint:
    """Read a checkpoint written by :func:`save`; DataError naming the file when it is not one."""
    path = Path(path)
    header, z = read_npz(path, "mapper checkpoint")
    try:  # the archive is read whole; its arrays are checked here
        if header.get("format") != FORMAT_VERSION:
            raise DataError(f"{path}: checkpoint format {header.get('format')!r}, expected {FORMAT_VERSION}")
        n = int(z["ids"].shape[0])
        g = GaussianRecords.from_arrays(z["ids"], z["xyz"], z["f_dc"], z["f_rest"], z["opacity"], z["scale"],
                                        z["rot"])
        if g.f_rest.shape != (n, PLY_F_REST):
            raise DataError(f"{path}: f_rest must be [{n}, {PLY_F_REST}], got {g.f_rest.shape}")
        kf_of, created = z["keyframe_ids"], z["created_iter"]
        if kf_of.shape != (n,) or created.shape != (n,):
            raise DataError(f"{path}: keyframe_ids/created_iter do not match {n} Gaussians")
        kfs = []
        for i, k in enumerate(header["keyframes"]):
            cam = PinholeCamera.from_dict(k["camera"])
            image = z[f"kf{i}_image"]
            if image.dtype != np.uint8 or image.shape != (cam.height, cam.width, 3):
                raise DataError(f"{path}: keyframe {k['kf_id']} image is {image.dtype} {image.shape}, "
                                f"camera {cam.width}x{cam.height}")
            depth = z[f"kf{i}_depth"].astype(np.float32) if k["depth"] else None
            mask = z[f"kf{i}_mask"].astype(bool) if k["mask"] else None
            for name, a in (("depth", depth), ("mask", mask)):
                if a is not None and a.shape != (cam.height, cam.width):
                    raise DataError(f"{path}: keyframe {k['kf_id']} {name} is {a.shape}")
            T = z[f"kf{i}_T_wc"].astype(np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise DataError(f"{path}: keyframe {k['kf_id']} pose is not a finite 4x4 matrix")
            exposure = k.get("exposure")
            if exposure is not None:
                exposure = tuple(float(x) for x in exposure)
                if len(exposure) != 6 or not all(np.isfinite(exposure)):
                    raise DataError(f"{path}: keyframe {k['kf_id']} exposure is not 6 finite numbers")
            kfs.append(KeyframeState(int(k["kf_id"]), int(k["stamp_ns"]), T, image, depth, mask, cam,
                                     exposure, int(k.get("uses", -1))))
        return MapperCheckpoint(g, kf_of.astype(np.int64), created.astype(np.int64), tuple(kfs),
                                int(header["iteration"]), int(header["next_id"]),
                                int(header["active_sh_degree"]), float(header["scene_extent"]),
                                float(header.get("saved_at_s", 0.0)), dict(header.get("extra", {})))
    except (ValueError, KeyError, TypeError) as err:
        raise DataError(f"{path}: not a readable mapper checkpoint ({type(err).__name__}: {err})") from err


@dataclass(frozen=True)
class CheckpointFile:
    """Where a mapper keeps its checkpoint: resumed from, set aside when unreadable (never
    overwritten: it may be the only copy of a long flight's map), written atomically."""

    path: Path

    def read_or_set_aside(self) -> tuple[MapperCheckpoint | None, str | None]:
        """(the checkpoint, None), (None, None) when there is none, or (None, what was done with
        a file that cannot be read)."""
        if not self.path.exists():
            return None, None
        try:
            return load(self.path), None
        except DataError as err:
            return None, self.set_aside(err)

    def set_aside(self, err: Exception) -> str:
        """Move the file to ``<name>.unreadable-<unix time>``; returns the line to log."""
        aside = self.path.with_name(f"{self.path.name}.unreadable-{int(time.time())}")
        self.path.replace(aside)
        return f"cannot resume: {err}; moved it to {aside} and starting an empty map"

    def write(self, ckpt: MapperCheckpoint) -> Path:
        return save(ckpt, self.path)

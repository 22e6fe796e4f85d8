"""A mapper's state in and out: the checkpoint a crashed mapper resumes from and a map bundle's
mapper part (a mixin of ``GaussianMapper``)."""
from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from memgs_ros.core.gaussians.gaussian_map import GaussianMap
from memgs_ros.core.mapping.checkpoint import ID_BLOCK, KeyframeState, MapperCheckpoint
from memgs_ros.core.mapping.exposure import ExposureCompensation
from memgs_ros.core.mapping.keyframes import KeyframeStore, TrainingKeyframe, make_keyframe
from memgs_ros.errors import DataError

__all__ = ["MapperState"]


class MapperState:
    """Mixin of ``GaussianMapper``: ``state_dict`` and ``load_state_dict``. Its state leaves and
    enters only through these."""

    gmap: GaussianMap
    keyframes: KeyframeStore
    exposure: ExposureCompensation | None
    iteration: int
    device: torch.device

    @property
    def scene_extent(self) -> float:
        raise NotImplementedError

    def add_prepared_keyframe(self, kf: TrainingKeyframe, points_w: np.ndarray | None = None,
                              colors: np.ndarray | None = None, enforce_budget: bool = True) -> int:
        raise NotImplementedError

    def state_dict(self, extra: Mapping[str, Any] | None = None) -> MapperCheckpoint:
        """Everything needed to resume, in host memory (no Adam moments: restored, they restart at zero,
        as merged Gaussians do). ``extra``: JSON-able additions (the session's keyframe-stamp table)."""
        gmap, kfs = self.gmap, []
        for kf in self.keyframes.all():
            kfs.append(KeyframeState(
                int(kf.kf_id), int(kf.stamp_ns), np.array(kf.T_wc, dtype=np.float64),
                kf.rgb.permute(1, 2, 0).contiguous().cpu().numpy(),
                None if kf.depth_m is None else kf.depth_m.detach().cpu().numpy().astype(np.float32),
                None if kf.valid_mask is None else kf.valid_mask.detach().cpu().numpy().astype(bool),
                kf.camera, None if self.exposure is None else self.exposure.get(kf.kf_id),
                self.keyframes.uses(kf.kf_id)))
        return MapperCheckpoint(gmap.to_records(), gmap.keyframe_ids.detach().cpu().numpy().astype(np.int64),
                                gmap.created_iter.detach().cpu().numpy().astype(np.int64), tuple(kfs),
                                int(self.iteration), int(gmap.next_id), int(gmap.active_sh_degree),
                                float(self.scene_extent), time.time(), dict(extra or {}))

    def load_state_dict(self, ckpt: MapperCheckpoint) -> None:
        """Load ``ckpt`` into this fresh mapper (no keyframes, no Gaussians yet).

        New Gaussians get ids from the next ``ID_BLOCK`` boundary above the checkpoint's next id,
        above every id the writer could have handed out after it: ids are never reused.
        """
        if len(self.gmap) or len(self.keyframes):
            raise DataError("a checkpoint can only be restored into an empty mapper")
        dev = self.device
        for k in ckpt.keyframes:
            image = torch.from_numpy(np.ascontiguousarray(k.image)).to(dev).permute(2, 0, 1)  # uint8
            depth = None if k.depth_m is None else torch.from_numpy(k.depth_m).to(dev)
            mask = None if k.valid_mask is None else torch.from_numpy(k.valid_mask).to(dev)
            self.add_prepared_keyframe(make_keyframe(k.kf_id, k.stamp_ns, k.T_wc, image.contiguous(), depth,
                                                     k.camera, valid_mask=mask))
            self.keyframes.restored(k.kf_id, k.uses)  # trained already: no new keyframe's coarse draws
            if self.exposure is not None and k.exposure is not None:
                self.exposure.set(k.kf_id, k.exposure)
        gmap = self.gmap
        if len(ckpt.gaussians):
            gmap.load_records(ckpt.gaussians, iteration=0)
            gmap.keyframe_ids[:] = torch.from_numpy(ckpt.keyframe_ids).to(gmap.keyframe_ids)
            gmap.created_iter[:] = torch.from_numpy(ckpt.created_iter).to(gmap.created_iter)
        gmap.next_id = -(-max(ckpt.next_id, 1) // ID_BLOCK) * ID_BLOCK
        while gmap.active_sh_degree < min(ckpt.active_sh_degree, gmap.max_sh_degree):
            gmap.raise_sh_degree()
        self.iteration = ckpt.iteration

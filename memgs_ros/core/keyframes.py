"""Keyframes for the mapper and Photo-SLAM's training-view selection (reference section 5).

A ``TrainingKeyframe`` is immutable; its pose changes by replacing it in the ``KeyframeStore``
(``update_pose``), so a training step that already took a keyframe keeps a consistent view.

View selection (``KeyframeStore.next_view``):

- every keyframe has a use budget; a new one gets ``new_keyframe_budget`` (TUM 2, Replica 8);
- views are drawn from a shuffled list of the keyframes with budget left, each draw spends one
  use; when every budget is spent, every keyframe gets +1 and the list is reshuffled;
- a keyframe is trained coarse-to-fine: its first ``uses_per_level`` draws render its 1/8
  pyramid level, the next ones 1/4, then 1/2, then full resolution.
"""
from __future__ import annotations

import random
import threading
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F

from memgs_ros.core.camera import PinholeCamera
from memgs_ros.errors import DataError

PYRAMID_FACTORS: tuple[float, ...] = (0.125, 0.25, 0.5, 1.0)  # coarse to fine


@dataclass(frozen=True, eq=False)
class PyramidLevel:
    """One resolution of a keyframe. image: [3, h, w] float in [0, 1]; depth_m: [h, w] or None;
    valid_mask: [h, w] bool (pixels with real image content) or None (all valid)."""

    factor: float
    image: torch.Tensor
    depth_m: torch.Tensor | None
    camera: PinholeCamera
    valid_mask: torch.Tensor | None = None


@dataclass(frozen=True, eq=False)
class TrainingKeyframe:
    """A keyframe as the mapper trains on it.

    kf_id: keyframe id; stamp_ns: capture time; T_wc: [4, 4] float64 camera-to-world.
    image: [3, H, W] float32 in [0, 1]; depth_m: [H, W] float32 metres (NaN/0 invalid) or None;
    camera: undistorted intrinsics of ``image``; levels: coarse-to-fine pyramid, the last
    level is the full-resolution image itself; valid_mask: [H, W] bool, the pixels that carry
    image content (undistortion leaves a border that maps outside the source image), or None.
    """

    kf_id: int
    stamp_ns: int
    T_wc: np.ndarray
    image: torch.Tensor
    depth_m: torch.Tensor | None
    camera: PinholeCamera
    levels: tuple[PyramidLevel, ...]
    valid_mask: torch.Tensor | None = None


def _resize_depth(depth: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Nearest-neighbour depth downsampling (averaging would blend across depth edges)."""
    return F.interpolate(depth[None, None], size=(h, w), mode="nearest")[0, 0]


def make_keyframe(kf_id: int, stamp_ns: int, T_wc: np.ndarray, image: torch.Tensor,
                  depth_m: torch.Tensor | None, camera: PinholeCamera,
                  factors: tuple[float, ...] = PYRAMID_FACTORS,
                  valid_mask: torch.Tensor | None = None) -> TrainingKeyframe:
    """Build a keyframe and its pyramid (area-averaged colour, nearest depth; a coarse pixel
    of the mask is valid only when every fine pixel it averages is).

    image: [3, H, W] float in [0, 1] matching ``camera``; depth_m: [H, W] or None;
    valid_mask: [H, W] bool or None.
    """
    if image.dim() != 3 or image.shape[0] != 3 or tuple(image.shape[1:]) != (camera.height, camera.width):
        raise DataError(f"keyframe {kf_id}: image must be [3, {camera.height}, {camera.width}], "
                        f"got {tuple(image.shape)}")
    if depth_m is not None and tuple(depth_m.shape) != (camera.height, camera.width):
        raise DataError(f"keyframe {kf_id}: depth must be [{camera.height}, {camera.width}], "
                        f"got {tuple(depth_m.shape)}")
    if valid_mask is not None and (tuple(valid_mask.shape) != (camera.height, camera.width)
                                   or valid_mask.dtype != torch.bool):
        raise DataError(f"keyframe {kf_id}: valid_mask must be bool [{camera.height}, {camera.width}], "
                        f"got {valid_mask.dtype} {tuple(valid_mask.shape)}")
    T = np.asarray(T_wc, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DataError(f"keyframe {kf_id}: T_wc must be a finite 4x4 matrix")
    levels = []
    for f in factors:
        if f == 1.0:
            levels.append(PyramidLevel(1.0, image, depth_m, camera, valid_mask))
            continue
        cam = camera.scaled(f)
        img = F.interpolate(image[None], size=(cam.height, cam.width), mode="area")[0]
        dep = None if depth_m is None else _resize_depth(depth_m, cam.height, cam.width)
        msk = None
        if valid_mask is not None:
            frac = F.interpolate(valid_mask[None, None].float(), size=(cam.height, cam.width), mode="area")[0, 0]
            msk = frac > 0.999
        levels.append(PyramidLevel(f, img.contiguous(), dep, cam, msk))
    return TrainingKeyframe(int(kf_id), int(stamp_ns), T.copy(), image, depth_m, camera, tuple(levels), valid_mask)


@dataclass(frozen=True)
class TrainingView:
    """What one iteration trains on: a keyframe and the pyramid level to render."""

    keyframe: TrainingKeyframe
    level: PyramidLevel


class KeyframeStore:
    """Thread-safe keyframes plus the Photo-SLAM view schedule (see module docstring)."""

    def __init__(self, new_keyframe_budget: int = 2, uses_per_level: int = 8, seed: int = 0) -> None:
        if new_keyframe_budget < 1 or uses_per_level < 0:
            raise DataError(f"keyframe budget must be >= 1 and uses per level >= 0, got "
                            f"{new_keyframe_budget} and {uses_per_level}")
        self.new_keyframe_budget = int(new_keyframe_budget)
        self.uses_per_level = int(uses_per_level)
        self._lock = threading.RLock()
        self._kfs: dict[int, TrainingKeyframe] = {}
        self._budget: dict[int, int] = {}
        self._uses: dict[int, int] = {}  # draws so far, drives the pyramid level
        self._pool: list[int] = []
        self._rng = random.Random(seed)

    def __len__(self) -> int:
        with self._lock:
            return len(self._kfs)

    def __contains__(self, kf_id: int) -> bool:
        with self._lock:
            return kf_id in self._kfs

    def ids(self) -> list[int]:
        with self._lock:
            return sorted(self._kfs)

    def add(self, kf: TrainingKeyframe) -> None:
        """Insert a new keyframe with the new-keyframe budget, at a random place in the list."""
        with self._lock:
            if kf.kf_id in self._kfs:
                raise DataError(f"keyframe {kf.kf_id} is already in the store")
            self._kfs[kf.kf_id] = kf
            self._budget[kf.kf_id] = self.new_keyframe_budget
            self._uses[kf.kf_id] = 0
            self._pool.insert(self._rng.randrange(len(self._pool) + 1), kf.kf_id)

    def remove(self, kf_id: int) -> None:
        """Drop a keyframe from training (its Gaussians stay in the map)."""
        with self._lock:
            if kf_id not in self._kfs:
                raise DataError(f"no keyframe with id {kf_id}")
            del self._kfs[kf_id], self._budget[kf_id], self._uses[kf_id]
            self._pool = [k for k in self._pool if k != kf_id]

    def get(self, kf_id: int) -> TrainingKeyframe:
        with self._lock:
            try:
                return self._kfs[kf_id]
            except KeyError as err:
                raise DataError(f"no keyframe with id {kf_id}") from err

    def all(self) -> list[TrainingKeyframe]:
        """Every keyframe, in id order."""
        with self._lock:
            return [self._kfs[k] for k in sorted(self._kfs)]

    def update_pose(self, kf_id: int, T_wc: np.ndarray) -> None:
        """Replace keyframe ``kf_id``'s camera-to-world pose ([4, 4])."""
        T = np.asarray(T_wc, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise DataError(f"keyframe {kf_id}: T_wc must be a finite 4x4 matrix")
        with self._lock:
            self._kfs[kf_id] = replace(self.get(kf_id), T_wc=T.copy())

    def prioritise(self, kf_id: int) -> None:
        """Give keyframe ``kf_id`` a new keyframe's budget of views again and put it back in the
        list of views to draw (a keyframe whose pose a loop closure corrected: retrain it first)."""
        with self._lock:
            if kf_id not in self._kfs:
                raise DataError(f"no keyframe with id {kf_id}")
            self._budget[kf_id] = max(self._budget[kf_id], self.new_keyframe_budget)
            if kf_id not in self._pool:
                self._pool.append(kf_id)  # next_view draws from the end: it comes next

    def level_index(self, kf_id: int) -> int:
        """Pyramid level the keyframe's next draw renders (0 = coarsest)."""
        with self._lock:
            n_levels = len(self._kfs[kf_id].levels)
            if self.uses_per_level == 0:
                return n_levels - 1
            return min(self._uses[kf_id] // self.uses_per_level, n_levels - 1)

    def next_view(self) -> TrainingView | None:
        """Draw the next training view (None when the store is empty)."""
        with self._lock:
            if not self._kfs:
                return None
            if not self._pool:
                for k in self._budget:
                    self._budget[k] += 1
                self._pool = list(self._kfs)
                self._rng.shuffle(self._pool)
            kf_id = self._pool[-1]
            level = self._kfs[kf_id].levels[self.level_index(kf_id)]
            self._budget[kf_id] -= 1
            self._uses[kf_id] += 1
            if self._budget[kf_id] <= 0:
                self._pool.pop()
            else:
                # Move it to a random place so one keyframe's uses are not consecutive.
                self._pool.pop()
                self._pool.insert(self._rng.randrange(len(self._pool) + 1), kf_id)
            return TrainingView(self._kfs[kf_id], level)

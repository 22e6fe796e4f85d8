"""Keyframes for the mapper and Photo-SLAM's training-view selection (reference section 5).

A ``TrainingKeyframe`` is immutable; its pose changes by replacing it in the ``KeyframeStore``
(``update_pose``), so a training step that already took a keyframe keeps a consistent view.

View selection (``KeyframeStore.next_view``):

- every keyframe has a use budget; a new one gets ``new_keyframe_budget`` (TUM 2, Replica 8) and
  is drawn next (the first training step after its insertion trains it: on a long flight a new
  keyframe drawn at a random place waited for half the store, 17.6 s median on 2 cores);
- views are drawn from a shuffled list of the keyframes with budget left, each draw spends one
  use; when every budget is spent, every keyframe gets +1 and the list is reshuffled;
- a keyframe is trained coarse-to-fine: its first ``uses_per_level`` draws render its 1/8
  pyramid level, the next ones 1/4, then 1/2, then full resolution.
"""
from __future__ import annotations

import random
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.mapping.keyframe_input import KeyframeInput  # noqa: F401 - re-exported
from memgs_ros.errors import DataError

PYRAMID_FACTORS: tuple[float, ...] = (0.125, 0.25, 0.5, 1.0)  # coarse to fine


@dataclass(frozen=True, eq=False)
class PyramidLevel:
    """One resolution of a keyframe. image: [3, h, w] float in [0, 1]; depth_m: [h, w] or None;
    valid_mask: [h, w] bool (pixels with real image content) or None (all valid).

    Made on demand from the keyframe's compact storage (``TrainingKeyframe.level``) and dropped
    after the step that uses it."""

    factor: float
    image: torch.Tensor
    depth_m: torch.Tensor | None
    camera: PinholeCamera
    valid_mask: torch.Tensor | None = None


@dataclass(frozen=True, eq=False)
class TrainingKeyframe:
    """Inside the mapping stage: a keyframe as the mapper trains on it, stored compactly (its
    host copy at the checkpoint boundary is ``checkpoint.KeyframeState``).

    kf_id: keyframe id; stamp_ns: capture time; T_wc: [4, 4] float64 camera-to-world.
    rgb: [3, H, W] uint8 (the undistorted, resized colour: exactly what the float image was,
    at a quarter of its bytes); depth_half: [H, W] float16 metres, 0 where invalid, or None
    (float16 keeps 11 significant bits: 1 mm at 2 m, below the sensor's noise); camera:
    undistorted intrinsics of ``rgb``; valid_mask: [H, W] bool, the pixels that carry image
    content (undistortion leaves a border that maps outside the source image), or None;
    factors: the coarse-to-fine pyramid, made per draw by ``level`` instead of being stored.
    At 320x240 this is 230 KB + 154 KB + 77 KB = 461 KB a keyframe (1.65 MB as float32 with
    a stored pyramid).
    """

    kf_id: int
    stamp_ns: int
    T_wc: np.ndarray
    rgb: torch.Tensor
    depth_half: torch.Tensor | None
    camera: PinholeCamera
    valid_mask: torch.Tensor | None = None
    factors: tuple[float, ...] = PYRAMID_FACTORS

    @property
    def image(self) -> torch.Tensor:
        """[3, H, W] float32 in [0, 1] (decoded per call)."""
        return self.rgb.float().div_(255.0)

    @property
    def depth_m(self) -> torch.Tensor | None:
        """[H, W] float32 metres, 0 where invalid (decoded per call), or None."""
        return None if self.depth_half is None else self.depth_half.float()

    @property
    def n_levels(self) -> int:
        return len(self.factors)

    @property
    def nbytes(self) -> int:
        """Bytes the keyframe holds in tensors (colour, depth, mask); the pose and camera are
        a few hundred bytes of Python objects."""
        return sum(t.numel() * t.element_size() for t in (self.rgb, self.depth_half, self.valid_mask)
                   if t is not None)

    def level(self, index: int) -> PyramidLevel:
        """Pyramid level ``index`` (0 = coarsest), made now: area-averaged colour, nearest depth,
        and a coarse pixel of the mask is valid only when every fine pixel it averages is."""
        f = self.factors[index]
        image, depth = self.image, self.depth_m
        if f == 1.0:
            return PyramidLevel(1.0, image, depth, self.camera, self.valid_mask)
        cam = self.camera.scaled(f)
        img = F.interpolate(image[None], size=(cam.height, cam.width), mode="area")[0].contiguous()
        dep = None if depth is None else _resize_depth(depth, cam.height, cam.width)
        msk = None
        if self.valid_mask is not None:
            frac = F.interpolate(self.valid_mask[None, None].float(), size=(cam.height, cam.width),
                                 mode="area")[0, 0]
            msk = frac > 0.999
        return PyramidLevel(f, img, dep, cam, msk)

    @property
    def levels(self) -> tuple[PyramidLevel, ...]:
        """Every pyramid level, coarse to fine (made now; training uses ``level``)."""
        return tuple(self.level(i) for i in range(self.n_levels))


def _resize_depth(depth: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Nearest-neighbour depth downsampling (averaging would blend across depth edges)."""
    return F.interpolate(depth[None, None], size=(h, w), mode="nearest")[0, 0]


def make_keyframe(kf_id: int, stamp_ns: int, T_wc: np.ndarray, image: torch.Tensor,
                  depth_m: torch.Tensor | None, camera: PinholeCamera,
                  factors: tuple[float, ...] = PYRAMID_FACTORS,
                  valid_mask: torch.Tensor | None = None) -> TrainingKeyframe:
    """Build a keyframe in its compact storage (see ``TrainingKeyframe``).

    image: [3, H, W] uint8, or float in [0, 1] (stored rounded to uint8) matching ``camera``;
    depth_m: [H, W] metres (NaN/0 invalid, stored as 0) or None; valid_mask: [H, W] bool or None.
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
    if not factors or factors[-1] != 1.0:
        raise DataError(f"keyframe {kf_id}: pyramid factors must end at full resolution, got {factors}")
    if image.dtype == torch.uint8:
        rgb = image.contiguous()
    else:
        rgb = (image.detach().float().clamp(0.0, 1.0) * 255.0).round_().to(torch.uint8).contiguous()
    depth_half = None
    if depth_m is not None:
        d = depth_m.detach().float()
        depth_half = torch.where(torch.isfinite(d) & (d > 0), d, torch.zeros_like(d)).to(torch.float16)
    mask = None if valid_mask is None else valid_mask.contiguous()
    return TrainingKeyframe(int(kf_id), int(stamp_ns), T.copy(), rgb, depth_half, camera, mask, tuple(factors))


@dataclass(frozen=True)
class TrainingView:
    """What one iteration trains on: a keyframe and the pyramid level to render."""

    keyframe: TrainingKeyframe
    level: PyramidLevel


class KeyframeStore:
    """Keyframes plus the Photo-SLAM view schedule (see module docstring). Not thread-safe: it
    belongs to one ``GaussianMapper``, which one thread drives (the session's worker)."""

    def __init__(self, new_keyframe_budget: int = 2, uses_per_level: int = 8, seed: int = 0) -> None:
        if new_keyframe_budget < 1 or uses_per_level < 0:
            raise DataError(f"keyframe budget must be >= 1 and uses per level >= 0, got "
                            f"{new_keyframe_budget} and {uses_per_level}")
        self.new_keyframe_budget = int(new_keyframe_budget)
        self.uses_per_level = int(uses_per_level)
        self._kfs: dict[int, TrainingKeyframe] = {}
        self._budget: dict[int, int] = {}
        self._uses: dict[int, int] = {}  # draws so far, drives the pyramid level
        self._pool: list[int] = []
        self._rng = random.Random(seed)

    def __len__(self) -> int:
        return len(self._kfs)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._kfs

    def ids(self) -> list[int]:
        return sorted(self._kfs)

    def add(self, kf: TrainingKeyframe) -> None:
        """Insert a new keyframe with the new-keyframe budget, drawn next (``next_view`` draws from
        the end of the list; after its first draw it goes to a random place like any other)."""
        if kf.kf_id in self._kfs:
            raise DataError(f"keyframe {kf.kf_id} is already in the store")
        self._kfs[kf.kf_id] = kf
        self._budget[kf.kf_id] = self.new_keyframe_budget
        self._uses[kf.kf_id] = 0
        self._pool.append(kf.kf_id)

    def uses(self, kf_id: int) -> int:
        """Draws of keyframe ``kf_id`` so far (a checkpoint keeps them)."""
        return self._uses[kf_id]

    def restored(self, kf_id: int, uses: int) -> None:
        """Keyframe ``kf_id`` came from a checkpoint with ``uses`` draws (< 0: unknown, taken as
        trained through every level): no new keyframe's budget, and its next draw at the level
        it had reached, not again from the coarsest (a continued session on the fr1/rpy head:
        +0.3-0.5 dB on the frames next to the loaded map's edge)."""
        full = self.uses_per_level * len(PYRAMID_FACTORS)
        self._uses[kf_id] = full if uses < 0 else int(uses)
        self._budget[kf_id] = 0
        self._pool = [k for k in self._pool if k != kf_id]

    def remove(self, kf_id: int) -> None:
        """Drop a keyframe from training (its Gaussians stay in the map)."""
        if kf_id not in self._kfs:
            raise DataError(f"no keyframe with id {kf_id}")
        del self._kfs[kf_id], self._budget[kf_id], self._uses[kf_id]
        self._pool = [k for k in self._pool if k != kf_id]

    def get(self, kf_id: int) -> TrainingKeyframe:
        try:
            return self._kfs[kf_id]
        except KeyError as err:
            raise DataError(f"no keyframe with id {kf_id}") from err

    def nbytes(self) -> int:
        """Bytes of every stored keyframe's tensors (``TrainingKeyframe.nbytes``)."""
        return sum(kf.nbytes for kf in self._kfs.values())

    def all(self) -> list[TrainingKeyframe]:
        """Every keyframe, in id order."""
        return [self._kfs[k] for k in sorted(self._kfs)]

    def update_pose(self, kf_id: int, T_wc: np.ndarray) -> None:
        """Replace keyframe ``kf_id``'s camera-to-world pose ([4, 4])."""
        T = np.asarray(T_wc, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise DataError(f"keyframe {kf_id}: T_wc must be a finite 4x4 matrix")
        self._kfs[kf_id] = replace(self.get(kf_id), T_wc=T.copy())

    def prioritise(self, kf_id: int) -> None:
        """Give keyframe ``kf_id`` a new keyframe's budget of views again and put it back in the
        list of views to draw (a keyframe whose pose a loop closure corrected: retrain it first)."""
        if kf_id not in self._kfs:
            raise DataError(f"no keyframe with id {kf_id}")
        self._budget[kf_id] = max(self._budget[kf_id], self.new_keyframe_budget)
        if kf_id not in self._pool:
            self._pool.append(kf_id)  # next_view draws from the end: it comes next

    def level_index(self, kf_id: int) -> int:
        """Pyramid level the keyframe's next draw renders (0 = coarsest)."""
        n_levels = self._kfs[kf_id].n_levels
        if self.uses_per_level == 0:
            return n_levels - 1
        return min(self._uses[kf_id] // self.uses_per_level, n_levels - 1)

    def next_view(self) -> TrainingView | None:
        """Draw the next training view (None when the store is empty)."""
        if not self._kfs:
            return None
        if not self._pool:
            for k in self._budget:
                self._budget[k] += 1
            self._pool = list(self._kfs)
            self._rng.shuffle(self._pool)
        kf_id = self._pool[-1]
        level_index = self.level_index(kf_id)
        self._budget[kf_id] -= 1
        self._uses[kf_id] += 1
        if self._budget[kf_id] <= 0:
            self._pool.pop()
        else:
            # Move it to a random place so one keyframe's uses are not consecutive.
            self._pool.pop()
            self._pool.insert(self._rng.randrange(len(self._pool) + 1), kf_id)
        kf = self._kfs[kf_id]
        return TrainingView(kf, kf.level(level_index))

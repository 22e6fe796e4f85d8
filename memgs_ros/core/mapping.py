"""The mapping back-end: keyframes in, an optimised Gaussian map out (reference section 5).

``GaussianMapper`` owns a ``GaussianMap`` and a ``KeyframeStore``. Each ``step()`` draws one
training view (Photo-SLAM schedule, coarse-to-fine pyramid), renders it, applies the loss
(photometric + isotropic + optional depth L1), back-propagates, accumulates densification and
merge statistics, takes an Adam step and, on schedule, densifies/prunes (3DGS clone/split),
merges (MemGS voxel merge, ``memgs_ros.core.merge.merge_pass``) and raises the SH degree.

Thread safety: one re-entrant lock guards the map, the optimiser and the iteration counter, so
a ROS node may call ``add_keyframe`` / ``update_keyframe_pose`` / ``render`` / ``pop_changes``
from callbacks while another thread loops on ``step()``. Image preparation (undistortion,
pyramid) in ``add_keyframe`` runs outside the lock.

Densification choices (documented differences from plain 3DGS): no opacity reset (reference
section 5); a Gaussian younger than ``prune_min_age_iters`` is never pruned, because seeds start
at opacity 0.1, at the prune threshold, and a new keyframe's seeds may not have been rendered yet;
in an iteration where a merge is scheduled, densification waits for the next interval (merge and
densification alternate, reference section 4).
"""
from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from dataclasses import dataclass, fields
from collections.abc import Iterator, Mapping
from typing import Any, Callable

import numpy as np
import torch

from memgs_ros.core.camera import PinholeCamera
from memgs_ros.core.gaussians import GaussianLearningRates, GaussianMap, GaussianRecords
from memgs_ros.core.geometry import invert_pose, nearest_pose_distance, quat_wxyz_to_rotmat_torch
from memgs_ros.core.keyframes import Keyframe, KeyframeStore, make_keyframe
from memgs_ros.core.losses import mapping_loss
from memgs_ros.core.view import view_preparation
from memgs_ros.errors import ConfigError, DataError

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

# Budget merge passes per enforcement: each pass merges at most one pair per voxel, so a map far
# over budget may need several; the rest is pruned.
_BUDGET_MERGE_PASSES = 3
# MergeConfig.tau must be finite: a bound no mean positional gradient reaches turns the gate off.
_NO_GRADIENT_GATE = 1e30


@dataclass(frozen=True)
class MappingConfig:
    """Every mapping parameter (reference section 5); defaults are the paper's RGB-D TUM values.

    Learning rates: ``lr_means`` is multiplied by the scene extent; with ``lr_means_decay`` it
    decays log-linearly to ``lr_means_final`` over ``lr_means_decay_steps`` (3DGS schedule).
    ``scene_extent`` <= 0 means automatic: max(1.1 x radius of the keyframe camera centres,
    ``min_scene_extent``) (the floor matters for a camera that mostly rotates in place).
    Densification: every ``densify_interval`` iterations in [densify_start_iter,
    densify_stop_iter], Gaussians whose mean NDC 2D gradient exceeds ``densify_grad_threshold``
    are cloned (max scale <= percent_dense x extent) or split into ``split_children`` scaled by
    1/``split_scale_factor``; then Gaussians with opacity < ``prune_opacity`` (and, when
    ``max_screen_size_px`` > 0, larger on screen than that or wider than 0.1 x extent) are pruned.
    Merge (reference section 4): every ``merge_interval`` iterations in [merge_start_iter,
    merge_stop_iter] when ``merge_enabled`` and memgs_ros.core.merge is importable.
    ``mask_invalid_pixels``: leave the border that undistortion fills with black (no source
    pixel, see ``undistortion_valid_mask``) out of the photometric and depth losses, so the map
    is not taught that the scene is black wherever some view's border falls; the whole-image
    evaluation still compares that border with black. ``seed_opacity``: initial opacity of
    keyframe seeds (3DGS and the paper: 0.1; higher makes short CPU runs converge faster).
    Memory budget (``max_gaussians`` / ``max_model_mbytes``, 0 = none; both set: the tighter
    wins): see ``GaussianMapper.enforce_budget``. The MiB budget is converted to a Gaussian
    count at a trained map's cost per Gaussian (parameters + gradients + both Adam moments,
    944 B at SH degree 3, ``GaussianMap.memory_bytes``), so seeds inserted before training
    already respect it.
    """

    # Optimiser (Adam, eps 1e-15)
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_means_decay: bool = False
    lr_means_decay_steps: int = 30_000
    lr_sh_dc: float = 0.0025
    lr_sh_rest: float = 0.0025 / 20.0
    lr_opacity: float = 0.05
    lr_scaling: float = 0.005
    lr_rotation: float = 0.001
    scene_extent: float = 0.0
    min_scene_extent: float = 1.0
    # Loss
    ssim_lambda: float = 0.2
    iso_weight: float = 1.0
    depth_weight: float = 0.1
    mask_invalid_pixels: bool = True
    # Initial opacity of keyframe seeds (3DGS: 0.1)
    seed_opacity: float = 0.1
    # Spherical harmonics
    max_sh_degree: int = 3
    sh_up_interval: int = 1000
    # Densify / prune
    densify_start_iter: int = 500
    densify_stop_iter: int = 15_000
    densify_interval: int = 100
    densify_grad_threshold: float = 0.001
    percent_dense: float = 0.01
    split_children: int = 2
    split_scale_factor: float = 1.6
    prune_opacity: float = 0.1
    prune_min_age_iters: int = 200
    max_screen_size_px: float = 0.0
    # Training views
    min_keyframes: int = 10
    new_keyframe_budget: int = 2
    pyramid_uses_per_level: int = 8
    resolution_scale: float = 1.0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    raster_backend: str = "auto"
    near_m: float = 0.01
    # Merge schedule (the merge itself: memgs_ros.core.merge.merge_pass)
    merge_enabled: bool = True
    merge_start_iter: int = 1000
    merge_interval: int = 1000
    merge_stop_iter: int = 15_000
    seed: int = 0
    # Memory budget (0 = none): when the map exceeds it, relaxed merge passes then pruning of
    # the least contributing Gaussians bring it to budget_target_fraction of it; densification
    # never grows it past the budget
    max_gaussians: int = 0  # budget on the number of Gaussians (0 = none)
    # Keyframes kept for training (0 = all). Over it, the most redundant one (nearest pose to
    # another keyframe; never the newest) leaves the store: its Gaussians stay in the map. Bounds
    # the mapper's image memory on long runs that revisit places
    max_keyframes: int = 0
    max_model_mbytes: float = 0.0  # budget in MiB of parameters + gradients + Adam moments (0 = none)
    budget_target_fraction: float = 0.95  # enforcement stops at this fraction of the budget (hysteresis)
    budget_merge: bool = True  # merge (all keyframes, no gradient gate) before pruning, when merging is on
    budget_merge_voxel_scale: float = 1.0  # voxel of the budget merge = merge voxel x this

    def __post_init__(self) -> None:
        for name in ("lr_means", "lr_means_final", "lr_sh_dc", "lr_sh_rest", "lr_opacity",
                     "lr_scaling", "lr_rotation", "min_scene_extent", "split_scale_factor",
                     "resolution_scale"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"MappingConfig.{name} must be positive, got {v}")
        for name in ("ssim_lambda",):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"MappingConfig.{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("iso_weight", "depth_weight", "densify_grad_threshold", "percent_dense",
                     "prune_opacity", "max_screen_size_px", "near_m", "max_model_mbytes"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"MappingConfig.{name} must be >= 0, got {v}")
        for name in ("sh_up_interval", "densify_interval", "merge_interval", "split_children",
                     "new_keyframe_budget", "lr_means_decay_steps"):
            if getattr(self, name) < 1:
                raise ConfigError(f"MappingConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("min_keyframes", "pyramid_uses_per_level", "prune_min_age_iters",
                     "densify_start_iter", "merge_start_iter", "max_gaussians", "max_keyframes"):
            if getattr(self, name) < 0:
                raise ConfigError(f"MappingConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 < self.budget_target_fraction <= 1.0:
            raise ConfigError("MappingConfig.budget_target_fraction must be in (0, 1], "
                              f"got {self.budget_target_fraction}")
        if not (math.isfinite(self.budget_merge_voxel_scale) and self.budget_merge_voxel_scale >= 1.0):
            raise ConfigError("MappingConfig.budget_merge_voxel_scale must be >= 1, "
                              f"got {self.budget_merge_voxel_scale}")
        if not 0.0 < self.seed_opacity < 1.0:
            raise ConfigError(f"MappingConfig.seed_opacity must be in (0, 1), got {self.seed_opacity}")
        if not 0 <= self.max_sh_degree <= 3:
            raise ConfigError(f"MappingConfig.max_sh_degree must be in 0..3, got {self.max_sh_degree}")
        if len(self.background) != 3:
            raise ConfigError(f"MappingConfig.background must have 3 values, got {self.background}")

    def learning_rates(self) -> GaussianLearningRates:
        return GaussianLearningRates(
            means=self.lr_means, means_final=self.lr_means_final,
            means_decay_steps=self.lr_means_decay_steps, means_decay=self.lr_means_decay,
            sh_dc=self.lr_sh_dc, sh_rest=self.lr_sh_rest, opacity=self.lr_opacity,
            scaling=self.lr_scaling, rotation=self.lr_rotation)

    @staticmethod
    def from_dict(values: dict[str, Any]) -> "MappingConfig":
        """Build from a flat dict (e.g. ROS parameters), refusing unknown names."""
        known = {f.name for f in fields(MappingConfig)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown mapping parameter(s): {', '.join(unknown)}")
        v = dict(values)
        if "background" in v:
            v["background"] = tuple(float(x) for x in v["background"])
        return MappingConfig(**v)


@dataclass(frozen=True)
class StepStats:
    """What one ``step()`` did. ``terms`` are the loss terms (see ``losses.mapping_loss``).

    ``budget_merged`` / ``budget_pruned``: Gaussians the memory budget removed since the previous
    step (``enforce_budget``, including its runs after ``add_keyframe`` / ``load_map``):
    merged pairs (each pair's two ids replaced by one new Gaussian, so the map shrank by that
    many) and pruned Gaussians.
    """

    iteration: int
    kf_id: int
    level_factor: float
    terms: dict[str, float]
    num_gaussians: int
    densified: int = 0
    pruned: int = 0
    merged_removed: int = 0
    merged_added: int = 0
    seconds: float = 0.0
    budget_merged: int = 0
    budget_pruned: int = 0


@dataclass(frozen=True, eq=False)
class MapChanges:
    """Map delta since the last ``pop_changes``: removed ids [R] int64 and the rows added or
    changed (their current values)."""

    removed_ids: np.ndarray
    changed: GaussianRecords


def _load_merge() -> Callable[..., Any] | None:
    """memgs_ros.core.merge.merge_pass and its default config, when that module exists."""
    try:
        from memgs_ros.core import merge as merge_mod
    except ImportError:
        return None
    return getattr(merge_mod, "merge_pass", None)


class GaussianMapper:
    """Trains a Gaussian map on keyframes (see module docstring). ``device``: torch device."""

    def __init__(self, cfg: MappingConfig | None = None, device: torch.device | str = "cpu",
                 merge_fn: Callable[..., Any] | None = None, merge_cfg: Any = None) -> None:
        self.cfg = cfg if cfg is not None else MappingConfig()
        self.device = torch.device(device)
        extent = self.cfg.scene_extent if self.cfg.scene_extent > 0 else self.cfg.min_scene_extent
        self.gmap = GaussianMap(self.cfg.max_sh_degree, self.device, self.cfg.learning_rates(), extent)
        self.keyframes = KeyframeStore(self.cfg.new_keyframe_budget, self.cfg.pyramid_uses_per_level,
                                       seed=self.cfg.seed)
        self.iteration = 0
        self._lock = threading.RLock()
        self._newest_kf_id = -1
        self._background = torch.tensor(self.cfg.background, dtype=torch.float32, device=self.device)
        self._generator = torch.Generator(device="cpu").manual_seed(self.cfg.seed)
        self._merge_fn = merge_fn if merge_fn is not None else (_load_merge() if self.cfg.merge_enabled else None)
        self._merge_cfg = merge_cfg
        self.last_merge: Any = None
        self.keyframes_dropped = 0  # by max_keyframes
        self.last_budget_merge: Any = None  # MergeResult of the budget's latest merge pass
        self._budget_pending = (0, 0)  # (merged, pruned) by the budget since the last StepStats

    # ----------------------------------------------------------- properties
    @property
    def lock(self) -> threading.RLock:
        """The mapper's lock (hold it to read ``gmap`` consistently from another thread)."""
        return self._lock

    @property
    def scene_extent(self) -> float:
        return self.gmap.spatial_lr_scale

    @property
    def ready(self) -> bool:
        """True once ``min_keyframes`` keyframes exist (training starts then)."""
        return len(self.keyframes) >= max(self.cfg.min_keyframes, 1)

    @property
    def merge_available(self) -> bool:
        return self._merge_fn is not None

    @property
    def budget_gaussians(self) -> int:
        """The memory budget as a Gaussian count (0 = none): the tighter of ``max_gaussians`` and
        ``max_model_mbytes`` at a trained map's bytes per Gaussian (at least 1 when set)."""
        cfg = self.cfg
        limits = [cfg.max_gaussians] if cfg.max_gaussians > 0 else []
        if cfg.max_model_mbytes > 0:
            limits.append(max(int(cfg.max_model_mbytes * 2**20 // self.trained_bytes_per_gaussian()), 1))
        return min(limits) if limits else 0

    def trained_bytes_per_gaussian(self) -> int:
        """Bytes ``GaussianMap.memory_bytes().total`` counts per Gaussian once the map trains:
        every parameter row four times (value, gradient, Adam exp_avg and exp_avg_sq)."""
        return 4 * sum(math.prod(p.shape[1:]) * p.element_size() for p in self.gmap.params().values())

    # ------------------------------------------------------------ keyframes
    def add_keyframe(self, kf_id: int, stamp_ns: int, T_wc: np.ndarray, rgb: np.ndarray,
                     depth_m: np.ndarray | None, camera: PinholeCamera,
                     points_w: np.ndarray | None = None, colors: np.ndarray | None = None,
                     enforce_budget: bool = True) -> int:
        """Insert a keyframe and seed Gaussians at its points.

        T_wc: [4, 4] camera-to-world; rgb: [H, W, 3] uint8; depth_m: [H, W] float32 metres
        (NaN/0 invalid) or None; camera: intrinsics of rgb (distorted images are undistorted
        here); points_w: [M, 3] world seeds (from undistorted pixels); colors: [M, 3] in [0, 1].
        enforce_budget: False leaves the memory budget to the next ``step`` (the map may exceed
        it by this keyframe's seeds until then): an insert thread that must keep up with the
        tracker then pays ~35 ms instead of ~180 ms on a 60k map at 320x240 (CPU).
        Returns the number of Gaussians added.
        """
        if rgb.dtype != np.uint8 or rgb.shape != (camera.height, camera.width, 3):
            raise DataError(f"keyframe {kf_id}: rgb must be uint8 [{camera.height}, {camera.width}, 3], "
                            f"got {rgb.dtype} {rgb.shape}")
        if depth_m is not None and depth_m.shape != (camera.height, camera.width):
            raise DataError(f"keyframe {kf_id}: depth must be [{camera.height}, {camera.width}], got {depth_m.shape}")
        prep = view_preparation(camera, self.cfg.resolution_scale)
        rgb, depth = prep(rgb, depth_m)
        camera = prep.camera
        image = torch.from_numpy(np.ascontiguousarray(rgb)).to(self.device).permute(2, 0, 1).float() / 255.0
        depth_t = None
        if depth is not None:
            d = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
            depth_t = torch.from_numpy(d).to(self.device)
        mask_t = None
        if self.cfg.mask_invalid_pixels:
            mask = prep.valid_mask
            mask_t = None if mask is None else torch.from_numpy(mask).to(self.device)
        kf = make_keyframe(kf_id, stamp_ns, T_wc, image.contiguous(), depth_t, camera, valid_mask=mask_t)
        with self._lock:
            self.keyframes.add(kf)
            self._newest_kf_id = max(self._newest_kf_id, int(kf_id))
            self._drop_redundant_keyframes()
            self._update_extent()
            added = 0
            if points_w is not None and len(points_w):
                if colors is None:
                    raise DataError(f"keyframe {kf_id}: points_w given without colors")
                ids = self.gmap.add_from_points(points_w, colors, kf_id, self.iteration)
                added = int(ids.numel())
                if added and abs(self.cfg.seed_opacity - 0.1) > 1e-12:
                    with torch.no_grad():
                        logit = math.log(self.cfg.seed_opacity / (1.0 - self.cfg.seed_opacity))
                        self.gmap.opacity_logits[self.gmap.index_of(ids)] = logit
                if enforce_budget:
                    self._enforce_budget_and_record()
            return added

    def _drop_redundant_keyframes(self) -> None:
        """Keep at most ``max_keyframes``: drop the keyframe whose pose is closest to another
        one (translation in metres + 0.5 m per radian of rotation), never the newest."""
        cap = self.cfg.max_keyframes
        while cap > 0 and len(self.keyframes) > cap:
            kfs = self.keyframes.all()
            nearest = nearest_pose_distance(np.stack([k.T_wc for k in kfs]))
            nearest[[i for i, k in enumerate(kfs) if k.kf_id == self._newest_kf_id]] = np.inf
            victim = kfs[int(np.argmin(nearest))].kf_id
            self.keyframes.remove(victim)
            self.keyframes_dropped += 1

    def add_prepared_keyframe(self, kf: Keyframe) -> None:
        """Insert a keyframe whose images are prepared already (a restored checkpoint)."""
        with self._lock:
            self.keyframes.add(kf)
            self._newest_kf_id = max(self._newest_kf_id, int(kf.kf_id))
            self._update_extent()

    def update_keyframe_pose(self, kf_id: int, T_wc: np.ndarray) -> bool:
        """Replace a keyframe's pose (e.g. after loop closure / bundle adjustment). Returns False
        (and changes nothing) for a keyframe no longer trained on (dropped by max_keyframes)."""
        return self.update_keyframe_poses({kf_id: T_wc}) == 1

    def update_keyframe_poses(self, poses: Mapping[int, np.ndarray]) -> int:
        """``update_keyframe_pose`` for many keyframes ({kf_id: T_wc [4, 4]}) under one lock
        acquisition; returns how many were updated (the rest are no longer trained on)."""
        with self._lock:
            updated = 0
            for kf_id, T_wc in poses.items():
                if kf_id in self.keyframes:
                    self.keyframes.update_pose(kf_id, T_wc)
                    updated += 1
            if updated:
                self._update_extent()
            return updated

    def _update_extent(self) -> None:
        if self.cfg.scene_extent > 0:
            return
        centres = np.stack([kf.T_wc[:3, 3] for kf in self.keyframes.all()])
        radius = float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
        extent = max(1.1 * radius, self.cfg.min_scene_extent)
        if abs(extent - self.gmap.spatial_lr_scale) > 1e-9:
            self.gmap.set_spatial_lr_scale(extent)
            self.gmap.update_learning_rate(self.iteration)

    def load_map(self, records: GaussianRecords) -> None:
        """Replace the map by ``records`` (e.g. handed back by the merger after a restart)."""
        with self._lock:
            self.gmap.remove(torch.ones(len(self.gmap), dtype=torch.bool, device=self.device))
            self.gmap.pop_changes()
            self.gmap.load_records(records, keyframe_id=-1, iteration=self.iteration)
            self.gmap.pop_changes()
            self._enforce_budget_and_record()  # its removals reach the next pop_changes

    # ------------------------------------------------------------- training
    def _rasterize(self, T_wc: np.ndarray, camera: PinholeCamera):  # -> RenderOutput
        from memgs_ros.core.raster import rasterize

        T_cw = torch.as_tensor(invert_pose(np.asarray(T_wc, dtype=np.float64)), dtype=torch.float32,
                               device=self.device)
        g = self.gmap
        return rasterize(g.means, g.quats_wxyz, g.log_scales, g.opacity_logits, g.sh_dc, g.sh_rest,
                         T_cw, camera, g.active_sh_degree, background=self._background,
                         near=self.cfg.near_m, backend=self.cfg.raster_backend)

    def step(self) -> StepStats | None:
        """One training iteration; None (and nothing done) until ``ready``."""
        if not self.ready:
            return None
        t0 = time.perf_counter()
        cfg = self.cfg
        with self._lock:
            view = self.keyframes.next_view()
            if view is None or len(self.gmap) == 0:
                return None
            level = view.level
            out = self._rasterize(view.keyframe.T_wc, level.camera)
            loss, terms = mapping_loss(out.color, level.image, self.gmap.log_scales, out.depth,
                                       level.depth_m, ssim_lambda=cfg.ssim_lambda,
                                       iso_weight=cfg.iso_weight, depth_weight=cfg.depth_weight,
                                       mask=level.valid_mask)
            loss.backward()
            grad2d = out.means2d.grad if out.means2d.grad is not None else None
            self.gmap.accumulate_stats(grad2d, out.visible, out.radii, level.camera.width, level.camera.height)
            self.gmap.update_learning_rate(self.iteration)
            self.gmap.optimizer_step()
            self.iteration += 1
            it = self.iteration
            if it % cfg.sh_up_interval == 0:
                self.gmap.raise_sh_degree()
            merged_removed = merged_added = densified = pruned = 0
            merge_due = (self._merge_fn is not None and cfg.merge_enabled
                         and cfg.merge_start_iter <= it <= cfg.merge_stop_iter
                         and it % cfg.merge_interval == 0)
            if merge_due:
                merged_removed, merged_added = self._run_merge()
            elif cfg.densify_start_iter <= it <= cfg.densify_stop_iter and it % cfg.densify_interval == 0:
                if self.budget_gaussians:
                    self._make_room_for_densification()
                densified, pruned = self.densify_and_prune()
            self._enforce_budget_and_record()
            (budget_merged, budget_pruned), self._budget_pending = self._budget_pending, (0, 0)
            return StepStats(it, view.keyframe.kf_id, level.factor, terms, len(self.gmap), densified,
                             pruned, merged_removed, merged_added, time.perf_counter() - t0,
                             budget_merged, budget_pruned)

    def _run_merge(self) -> tuple[int, int]:
        """The single merge hook: memgs_ros.core.merge.merge_pass on the live map.

        Returns (removed, added) Gaussian counts; the full MergeResult is kept in ``last_merge``.
        """
        if self._merge_cfg is None:
            from memgs_ros.core import merge as merge_mod

            cfg_cls = getattr(merge_mod, "MergeConfig", None)
            self._merge_cfg = cfg_cls() if cfg_cls is not None else None
        result = self._merge_fn(self.gmap, self._merge_cfg, self._newest_kf_id, self.iteration)
        # Each pass judges stability on the gradients seen since the previous pass.
        self.gmap.reset_merge_stats()
        self.last_merge = result
        return int(result.removed_ids.numel()), int(result.added_ids.numel())

    # ---------------------------------------------------------- memory budget
    def enforce_budget(self) -> tuple[int, int]:
        """Bring a map over ``budget_gaussians`` down to ``budget_target_fraction`` of it.

        1. When merging is on (``merge_available``) and ``cfg.budget_merge``: up to
           ``_BUDGET_MERGE_PASSES`` relaxed merge passes (``_budget_merge_config``), stopping
           once at the target or when a pass merges nothing. Merging keeps what both Gaussians
           described (one Gaussian, moment-matched), so it goes before pruning. Measured at half
           the unbudgeted size (benchmarks/bench_memory_budget.py, keyframe / all-frames PSNR
           cost): synthetic 1.93 / 1.11 dB with it (voxel x1; x2 2.01 / 1.10, x4 2.02 / 1.24),
           2.03 / 1.24 dB without; TUM fr1/rpy (voxel x2) 0.72 / 0.23 dB with, 0.67 / 0.22
           without: no worse than pruning, not clearly better.
        2. If still above the target: prune the Gaussians with the smallest
           ``budget_contribution`` down to the target.
        Removed ids are recorded by ``GaussianMap.remove`` like any other removal (map delta).
        Returns (merged pairs, pruned Gaussians); (0, 0) when there is no budget or the map is
        within it.
        """
        limit = self.budget_gaussians
        with self._lock:
            if limit == 0 or len(self.gmap) <= limit:
                return 0, 0
            return self._shrink_to(max(int(limit * self.cfg.budget_target_fraction), 1))

    def _shrink_to(self, target: int, keep: torch.Tensor | None = None) -> tuple[int, int]:
        """Relaxed merge passes, then pruning by ``budget_contribution``, down to ``target``
        Gaussians; rows where ``keep`` ([N] bool) is set are never pruned. Returns (merged, pruned)."""
        with self._lock, torch.no_grad():
            g = self.gmap
            merged = 0
            merge_cfg = self._budget_merge_config() if self.cfg.budget_merge else None
            if merge_cfg is not None:
                for _ in range(_BUDGET_MERGE_PASSES):
                    result = self._merge_fn(g, merge_cfg, self._newest_kf_id, self.iteration)
                    self.last_budget_merge = result
                    n = int(result.added_ids.numel())
                    merged += n
                    if n == 0 or len(g) <= target:
                        break
            pruned = max(len(g) - target, 0)
            if pruned:
                score = self.budget_contribution()
                if keep is not None and len(keep) == len(g):
                    score[keep] = math.inf
                weakest = torch.topk(score, pruned, largest=False).indices
                mask = torch.zeros(len(g), dtype=torch.bool, device=self.device)
                mask[weakest] = True
                g.remove(mask)
            logger.debug("budget: merged %d pairs, pruned %d -> %d Gaussians", merged, pruned, len(g))
            return merged, pruned

    def budget_contribution(self) -> torch.Tensor:
        """Budget pruning order, [N]: the smallest go first.

        Gaussians older than ``prune_min_age_iters`` score their opacity (the 3DGS prune
        signal), so the least opaque go first. Younger ones (new seeds, fresh clones) have not
        been trained enough to judge: they score 1 + a uniform draw, i.e. they go only once
        every older Gaussian is kept, and then at random, which thins new seeds evenly. (Not
        world size: seeds are sized by their neighbour spacing, so opacity x area would strip
        whole near-camera surfaces first; on a 3-keyframe 64x48 scene at half the seeds it lost
        2.5 dB against random thinning.)
        """
        g = self.gmap
        score = g.opacities().detach().reshape(-1).clone()
        young = g.created_iter > self.iteration - self.cfg.prune_min_age_iters
        n_young = int(young.sum())
        if n_young:
            draw = torch.rand(n_young, generator=self._generator, dtype=score.dtype).to(score.device)
            score[young] = 1.0 + draw
        return score

    def _budget_merge_config(self) -> Any:
        """The merge configuration for budget passes, or None when there is none to relax.

        Relaxed from the scheduled one (``MergeConfig``): every keyframe in the window (the
        budget binds the whole map, not the newest keyframes), no gradient gate (a Gaussian
        still moving is better merged than pruned) and a voxel ``budget_merge_voxel_scale``
        times larger (default 1: a coarser voxel merged more without lowering the PSNR cost, see
        ``enforce_budget``); the Mahalanobis gate stays, so only overlapping Gaussians merge.
        """
        if self._merge_fn is None:
            return None
        from dataclasses import replace

        from memgs_ros.core import merge as merge_mod

        base = self._merge_cfg if self._merge_cfg is not None else merge_mod.MergeConfig()
        if not isinstance(base, merge_mod.MergeConfig) or not base.enabled:
            return None  # a caller's own merge configuration: nothing known to relax
        return replace(base, window_keyframes=max(self._newest_kf_id + 1, 1), tau=_NO_GRADIENT_GATE,
                       voxel_size_m=base.voxel_size_m * self.cfg.budget_merge_voxel_scale)

    def _enforce_budget_and_record(self) -> None:
        merged, pruned = self.enforce_budget()
        if merged or pruned:
            m0, p0 = self._budget_pending
            self._budget_pending = (m0 + merged, p0 + pruned)

    def train(self, iterations: int, progress: bool = True,
              callback: Callable[[StepStats], None] | None = None) -> StepStats | None:
        """Run ``iterations`` steps (raises ConfigError if the mapper is not ready); returns the last stats."""
        if not self.ready:
            raise ConfigError(f"mapping needs {self.cfg.min_keyframes} keyframes, has {len(self.keyframes)}")
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=iterations, desc="mapping", unit="it")
        last = None
        try:
            for _ in range(iterations):
                last = self.step()
                if callback is not None and last is not None:
                    callback(last)
                if bar is not None:
                    bar.update(1)
                    if last is not None and last.iteration % 10 == 0:
                        bar.set_postfix(loss=f"{last.terms['total']:.4f}", n=last.num_gaussians)
        finally:
            if bar is not None:
                bar.close()
        return last

    # --------------------------------------------------------- densification
    def densify_and_prune(self) -> tuple[int, int]:
        """3DGS clone/split of high-gradient Gaussians, then pruning. Returns (added, removed)."""
        cfg, g = self.cfg, self.gmap
        with self._lock, torch.no_grad():
            n0 = len(g)
            extent = g.spatial_lr_scale
            grads = g.densify_grad_mean()
            max_scale = g.scales().max(dim=1).values
            high = grads >= cfg.densify_grad_threshold
            if self.budget_gaussians:
                high = self._densify_within_budget(high, grads, max_scale)
            clone = high & (max_scale <= cfg.percent_dense * extent)
            split = high & (max_scale > cfg.percent_dense * extent)
            split_idx = torch.nonzero(split).reshape(-1)
            clone_idx = torch.nonzero(clone).reshape(-1)
            added = 0
            # Split children are computed before anything changes the row positions.
            k = cfg.split_children
            if split_idx.numel():
                std = g.scales()[split_idx].repeat(k, 1)
                samples = torch.randn(std.shape, generator=self._generator).to(self.device) * std
                rot = quat_wxyz_to_rotmat_torch(g.quats_wxyz[split_idx]).repeat(k, 1, 1)
                child_means = (rot @ samples[..., None])[..., 0] + g.means[split_idx].repeat(k, 1)
                child = dict(
                    means=child_means,
                    log_scales=torch.log(std / cfg.split_scale_factor),
                    quats_wxyz=g.quats_wxyz[split_idx].repeat(k, 1),
                    opacity_logits=g.opacity_logits[split_idx].repeat(k, 1),
                    sh_dc=g.sh_dc[split_idx].repeat(k, 1, 1),
                    sh_rest=g.sh_rest[split_idx].repeat(k, 1, 1),
                    keyframe_id=g.keyframe_ids[split_idx].repeat(k),
                )
            if clone_idx.numel():
                g.add(g.means[clone_idx], g.log_scales[clone_idx], g.quats_wxyz[clone_idx],
                      g.opacity_logits[clone_idx], g.sh_dc[clone_idx], g.sh_rest[clone_idx],
                      g.keyframe_ids[clone_idx], self.iteration)
                added += clone_idx.numel()
            if split_idx.numel():
                g.add(iteration=self.iteration, **child)
                added += child["means"].shape[0]
                parents = torch.zeros(len(g), dtype=torch.bool, device=self.device)
                parents[split_idx] = True
                g.remove(parents)
            n1 = len(g)
            g.reset_densify_stats()
            prune = self._prunable()
            removed_prune = int(prune.sum())
            if removed_prune:
                g.remove(prune)
            logger.debug("densify: %d -> %d (+%d clone/split) -> %d after pruning", n0, n1, added, len(g))
            return added, removed_prune + int(split_idx.numel())

    def _prunable(self) -> torch.Tensor:
        """Rows the densification prune removes now (opacity, and size when enabled): [N] bool."""
        cfg, g = self.cfg, self.gmap
        old_enough = g.created_iter <= self.iteration - cfg.prune_min_age_iters
        prune = (g.opacities().reshape(-1) < cfg.prune_opacity) & old_enough
        if cfg.max_screen_size_px > 0:
            big = (g.max_radii2d > cfg.max_screen_size_px) | (g.scales().max(dim=1).values > 0.1 * g.spatial_lr_scale)
            prune |= big & old_enough
        return prune

    def _make_room_for_densification(self) -> None:
        """At budget, trade weak Gaussians for densification: when the clone/split candidates
        want more room than the budget leaves, shrink the map (``_shrink_to``: merge, then prune
        the lowest ``budget_contribution``, never a candidate) by up to the hysteresis margin,
        (1 - ``budget_target_fraction``) x budget, per densification interval. Without it a
        map at budget only densifies into what the opacity prune frees; with it the synthetic
        bench at half the unbudgeted size lost 2.01 dB instead of 2.16 dB (keyframe PSNR).
        """
        cfg, g = self.cfg, self.gmap
        limit = self.budget_gaussians
        with torch.no_grad():
            grads = g.densify_grad_mean()
            high = grads >= cfg.densify_grad_threshold
            clone = g.scales().max(dim=1).values <= cfg.percent_dense * g.spatial_lr_scale
            growth = int(torch.where(clone, 1, cfg.split_children - 1)[high].sum())
            room = limit - len(g) + int((self._prunable() & ~high).sum())
            need = min(growth - room, limit - max(int(limit * cfg.budget_target_fraction), 1))
            if need <= 0:
                return
            merged, pruned = self._shrink_to(len(g) - need, keep=high)
            m0, p0 = self._budget_pending
            self._budget_pending = (m0 + merged, p0 + pruned)

    def _densify_within_budget(self, high: torch.Tensor, grads: torch.Tensor,
                               max_scale: torch.Tensor) -> torch.Tensor:
        """The densify candidates ``high`` ([N] bool) cut to the room left under the budget.

        A clone adds one Gaussian, a split ``split_children - 1``; the room is the budget minus
        the map plus what the prune after densification will free among rows not densified.
        Candidates are kept in order of decreasing gradient while their summed growth fits.
        grads, max_scale: [N]. Returns [N] bool.
        """
        cfg, g = self.cfg, self.gmap
        room = self.budget_gaussians - len(g) + int((self._prunable() & ~high).sum())
        idx = torch.nonzero(high).reshape(-1)
        if room <= 0:
            return torch.zeros_like(high)
        clone = max_scale[idx] <= cfg.percent_dense * g.spatial_lr_scale
        growth = torch.where(clone, 1, cfg.split_children - 1)
        order = torch.argsort(grads[idx], descending=True, stable=True)
        fits = torch.cumsum(growth[order], 0) <= room
        kept = torch.zeros_like(high)
        kept[idx[order[fits]]] = True
        return kept

    # -------------------------------------------------------------- outputs
    def render(self, T_wc: np.ndarray, camera: PinholeCamera):  # -> RenderOutput
        """Render the map from camera-to-world ``T_wc`` with undistorted ``camera`` (no grad)."""
        with self._lock, torch.no_grad():
            return self._rasterize(T_wc, camera)

    def render_keyframe(self, kf_id: int):  # -> RenderOutput
        """Render keyframe ``kf_id`` at its training resolution (no grad)."""
        kf = self.keyframes.get(kf_id)
        return self.render(kf.T_wc, kf.camera)

    def pop_changes(self) -> MapChanges:
        """Ids removed and Gaussians added or changed since the last call (then forgotten).

        After optimiser steps "changed" is every Gaussian the steps moved (non-zero Adam first
        moment), which includes every Gaussian that received a non-zero gradient.
        """
        with self._lock:
            removed, changed_idx = self.gmap.pop_changes()
            return MapChanges(removed.cpu().numpy().astype(np.int64), self.gmap.to_records(changed_idx))

    @contextlib.contextmanager
    def exclusive(self) -> Iterator[None]:
        """Hold the map across several calls (e.g. inserting every queued keyframe): no training
        step interleaves, and each call inside re-enters the lock without waiting for one."""
        with self._lock:
            yield

    def discard_changes(self) -> None:
        """Forget the removals and changes ``pop_changes`` would report. For users that diff
        snapshots instead (the mapper node's DeltaOutbox): without this, the ids of every
        Gaussian ever removed pile up (~7 MB per 900k removals, a load run's 5 minutes)."""
        with self._lock:
            self.gmap.pop_changes()

    def snapshot(self) -> GaussianRecords:
        """The whole map as records (consistent: taken under the lock)."""
        with self._lock:
            return self.gmap.to_records()

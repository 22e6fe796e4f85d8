"""Every mapping parameter in one frozen config (reference section 5), apart from the engine that
uses it (core/mapping/mapper.py) so the map policies (core/mapping/strategies.py) can take it without a cycle."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, ClassVar

from memgs_ros.core.gaussians.learning_rates import GaussianLearningRates
from memgs_ros.errors import ConfigError


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
    merge_stop_iter] when ``merge_enabled`` and memgs_ros.core.merge.voxel_merge is importable.
    ``mask_invalid_pixels``: leave the border that undistortion fills with black (no source
    pixel, see ``memgs_ros.core.geometry.view.ViewPreparation.valid_mask``) out of the photometric
    and depth losses, so the map is not taught that the scene is black wherever some view's border
    falls; the whole-image evaluation still compares that border with black. ``seed_opacity``: initial opacity of
    keyframe seeds (3DGS and the paper: 0.1; higher makes short CPU runs converge faster).
    Memory budget (``max_gaussians`` / ``max_model_mbytes``, 0 = none; both set: the tighter
    wins): see ``memgs_ros.core.mapping.strategies.BudgetStrategy``. The MiB budget is converted to a Gaussian
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
    # Gaussians only where the map lacks them (core/mapping/coverage.py): a keyframe's seed becomes a
    # Gaussian only where the settled map (Gaussians of keyframes taken seed_coverage_age_s or more
    # before it) rendered at the keyframe (at seed_coverage_scale of its resolution) is
    # thinner than seed_alpha_max or the seed lies in front of its surface by more than
    # seed_depth_abs_m + seed_depth_rel x depth; a place flown again seeds little
    seed_coverage: bool = True
    seed_coverage_age_s: float = 6.0
    # ... or inserted this many training iterations before it (0: by age only): a flight that turns
    # back over what it saw seconds ago finds that surface trained (acknowledged, 8 iterations a
    # frame, ~1000 iterations), and its age alone had the revisit seed and densify as new (the head
    # twice, forward and back: 38.4k Gaussians, 21.5k with this; one pass 28.4k -> 21.2k, -0.14 dB)
    seed_coverage_trained_iters: int = 300
    seed_coverage_scale: float = 0.5
    seed_alpha_max: float = 0.5
    seed_depth_abs_m: float = 0.05
    seed_depth_rel: float = 0.05
    # Per-keyframe affine colour correction trained with the map (core/mapping/exposure.py); renders
    # for evaluation and the rendered-view topics never use it. Off by default: on the fr1/rpy
    # head it cost 0.40 dB under the paper's protocol (docs/results.md, Map quality)
    exposure_compensation: bool = False
    exposure_lr: float = 0.005
    exposure_reg: float = 0.01  # weight of the pull towards identity (gain 1, bias 0)
    # Spherical harmonics
    max_sh_degree: int = 3
    sh_up_interval: int = 1000
    # Densify / prune
    densify_start_iter: int = 500
    densify_stop_iter: int = 15_000
    densify_interval: int = 100
    densify_grad_threshold: float = 0.001
    # ... and only within this many iterations of the newest keyframe's arrival (0: at any time): a
    # long flight over a room already mapped brings no keyframe, and densification would grow the
    # map with the training time (the fr1/rpy head five times, every frame acknowledged: 2.4x one pass's Gaussians);
    # a keyframe opens it in proportion to the share of its seeds the map lacked (a revisit: ~none)
    densify_window_iters: int = 500
    percent_dense: float = 0.01
    split_children: int = 2
    split_scale_factor: float = 1.6
    prune_opacity: float = 0.1
    prune_min_age_iters: int = 200
    max_screen_size_px: float = 0.0
    # Training views
    min_keyframes: int = 10  # per-frame training starts with this many (the final iterations train on any number)
    # Live (free-running) training starts with this many: the map is for use in flight, and a mapper
    # that waited for min_keyframes trained nothing while the camera moved
    live_min_keyframes: int = 1
    new_keyframe_budget: int = 2  # view selection: draws a new keyframe gets (TUM 2, Replica 8)
    pyramid_uses_per_level: int = 8  # a keyframe's first draws per pyramid level, 1/8 up to full size
    resolution_scale: float = 1.0  # mapping resolution, a fraction of the camera's (0.5: 640x480 -> 320x240)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    raster_backend: str = "auto"  # auto: gsplat on CUDA when importable, numba on the CPU, else torch
    near_m: float = 0.01  # near plane of the renders, m
    # Merge schedule (the merge itself: memgs_ros.core.merge.voxel_merge.merge_pass)
    merge_enabled: bool = True  # merge similar Gaussians while training
    merge_start_iter: int = 1000  # first merge pass at this iteration
    merge_interval: int = 1000  # then every this many iterations
    merge_stop_iter: int = 15_000  # and none after this one
    # ... and in flight, on a schedule a live mapper reaches: a pass once this many keyframes came since
    # the last, at least merge_keyframes_min_iters iterations after it (0: the iteration schedule only)
    merge_every_keyframes: int = 5
    merge_keyframes_min_iters: int = 20
    seed: int = 0  # view selection and densification draws
    # Memory budget (0 = none): when the map exceeds it, relaxed merge passes then pruning of
    # the least contributing Gaussians bring it to budget_target_fraction of it; densification
    # never grows it past the budget
    max_gaussians: int = 0  # budget on the number of Gaussians (0 = none)
    # Keyframes kept for training (0 = all): the newest training_window ones, and a set over the whole
    # flight chosen for coverage. Over it, the most redundant one outside the window (nearest pose to
    # another keyframe) leaves the store: its Gaussians stay in the map. Bounds the mapper's image
    # memory and keeps its per-iteration work flat on long flights that revisit places
    max_keyframes: int = 0
    training_window: int = 10
    max_model_mbytes: float = 0.0  # budget in MiB of parameters + gradients + Adam moments (0 = none)
    # Cap in MiB on the mapper's accounted working memory (0 = none): model (as above) + stored
    # keyframes + the training step's buffers + the delta mirror and one full-map message
    # (core/mapping/strategies.py, MemoryAccount). Over it the
    # mapper first drops redundant keyframes (the max_keyframes rule, down to min_keyframes),
    # then merges/prunes the map like max_model_mbytes. Imports and code are not in it
    max_mapper_mbytes: float = 0.0
    budget_target_fraction: float = 0.95  # enforcement stops at this fraction of the budget (hysteresis)
    budget_merge: bool = True  # merge (all keyframes, no gradient gate) before pruning, when merging is on
    budget_merge_voxel_scale: float = 1.0  # voxel of the budget merge = merge voxel x this

    # Ranges a user can reason about, checked before a run starts (``memgs run --set``, config
    # files) and again by the mapper node: a typo such as resolution_scale=50 (for 0.5) is refused
    # instead of growing a 6 GB map.
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "lr_means": (0.0, 1.0), "lr_means_final": (0.0, 1.0), "lr_means_decay_steps": (1, 10**8),
        "lr_sh_dc": (0.0, 1.0), "lr_sh_rest": (0.0, 1.0), "lr_opacity": (0.0, 1.0), "lr_scaling": (0.0, 1.0),
        "lr_rotation": (0.0, 1.0), "scene_extent": (0.0, 1e4), "min_scene_extent": (1e-3, 1e4),
        "ssim_lambda": (0.0, 1.0), "iso_weight": (0.0, 1e3), "depth_weight": (0.0, 1e3),
        "seed_opacity": (1e-4, 0.9999), "exposure_lr": (0.0, 1.0), "exposure_reg": (0.0, 1e3),
        "seed_coverage_scale": (0.01, 1.0), "seed_alpha_max": (0.0, 1.0), "seed_depth_abs_m": (0.0, 100.0),
        "seed_depth_rel": (0.0, 100.0), "merge_every_keyframes": (0, 10**6), "merge_keyframes_min_iters": (0, 10**8),
        "training_window": (1, 10**5), "seed_coverage_age_s": (0.0, 1e6), "seed_coverage_trained_iters": (0, 10**8),
        "max_sh_degree": (0, 3), "sh_up_interval": (1, 10**8),
        "densify_start_iter": (0, 10**8), "densify_stop_iter": (0, 10**8), "densify_interval": (1, 10**8),
        "densify_window_iters": (0, 10**8),
        "densify_grad_threshold": (0.0, 1.0), "percent_dense": (0.0, 1.0), "split_children": (2, 16),
        "split_scale_factor": (1.0, 100.0), "prune_opacity": (0.0, 1.0), "prune_min_age_iters": (0, 10**8),
        "max_screen_size_px": (0.0, 1e5), "min_keyframes": (1, 10**5),
        "live_min_keyframes": (1, 10**5), "new_keyframe_budget": (1, 10**4),
        "pyramid_uses_per_level": (0, 10**4), "resolution_scale": (0.01, 2.0), "near_m": (1e-4, 100.0),
        "merge_start_iter": (0, 10**8), "merge_interval": (1, 10**8), "merge_stop_iter": (0, 10**8),
        "seed": (0, 2**31 - 1), "max_gaussians": (0, 10**9), "max_keyframes": (0, 10**5),
        "max_model_mbytes": (0.0, 1e6), "max_mapper_mbytes": (0.0, 1e6), "budget_target_fraction": (0.1, 1.0),
        "budget_merge_voxel_scale": (1.0, 1e3),
    }
    CHOICES: ClassVar[dict[str, tuple[str, ...]]] = {
        "raster_backend": ("auto", "torch", "numba", "gsplat", "gsplat_packed")}

    def __post_init__(self) -> None:
        for name in ("lr_means", "lr_means_final", "lr_sh_dc", "lr_sh_rest", "lr_opacity",
                     "lr_scaling", "lr_rotation", "min_scene_extent", "split_scale_factor",
                     "resolution_scale", "exposure_lr", "seed_coverage_scale"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"MappingConfig.{name} must be positive, got {v}")
        for name in ("ssim_lambda",):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"MappingConfig.{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("iso_weight", "depth_weight", "densify_grad_threshold", "percent_dense",
                     "prune_opacity", "max_screen_size_px", "near_m", "max_model_mbytes", "exposure_reg",
                     "max_mapper_mbytes", "seed_alpha_max", "seed_depth_abs_m", "seed_depth_rel",
                     "seed_coverage_age_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"MappingConfig.{name} must be >= 0, got {v}")
        for name in ("sh_up_interval", "densify_interval", "merge_interval", "split_children",
                     "new_keyframe_budget", "lr_means_decay_steps", "training_window"):
            if getattr(self, name) < 1:
                raise ConfigError(f"MappingConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("min_keyframes", "pyramid_uses_per_level", "prune_min_age_iters",
                     "densify_start_iter", "densify_window_iters", "merge_start_iter", "max_gaussians", "max_keyframes",
                     "merge_every_keyframes", "merge_keyframes_min_iters", "seed_coverage_trained_iters"):
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
    def from_dict(values: dict[str, Any]) -> MappingConfig:
        """Build from a flat dict (e.g. ROS parameters), refusing unknown names."""
        known = {f.name for f in fields(MappingConfig)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown mapping parameter(s): {', '.join(unknown)}")
        v = dict(values)
        if "background" in v:
            v["background"] = tuple(float(x) for x in v["background"])
        return MappingConfig(**v)

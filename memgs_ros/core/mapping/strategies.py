"""Map policies as small strategy objects (like gsplat's strategies).

Each policy reads the map and changes it only through ``GaussianMap.add`` / ``GaussianMap.remove``
(both go through ``GaussianMap._resize``, the one helper that moves parameters, Adam moments and
the per-Gaussian side arrays together):

- ``DensifyStrategy``: 3DGS clone/split of high-gradient Gaussians, then the opacity/size prune;
- ``MergeSchedule``: when the MemGS voxel merge runs (``memgs_ros.core.merge.voxel_merge.merge_pass``) and the
  relaxed merge configuration the memory budget uses;
- ``BudgetStrategy``: the memory budget (a Gaussian count), enforced by relaxed merge passes and
  then pruning of the least contributing Gaussians; it also cuts densification to the room left;
- ``TrainingSetStrategy``: which training keyframes go when the store is over ``max_keyframes``
  or the accounted memory over ``max_mapper_mbytes``.

A policy holds its configuration and its own random generator, never the map: the mapping engine
(``memgs_ros.core.mapping.mapper.GaussianMapper``) passes the map and the iteration to every call.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from memgs_ros.core.geometry.poses import nearest_pose_distance, quat_wxyz_to_rotmat_torch

if TYPE_CHECKING:
    from memgs_ros.core.gaussians.gaussian_map import GaussianMap
    from memgs_ros.core.mapping.config import MappingConfig
    from memgs_ros.core.mapping.keyframes import KeyframeStore

logger = logging.getLogger(__name__)

# Budget merge passes per enforcement: each pass merges at most one pair per voxel, so a map far
# over budget may need several; the rest is pruned.
BUDGET_MERGE_PASSES = 3
# Training-step buffers beyond the model, per Gaussian (projection outputs, their gradients,
# tile lists) and per training pixel (render, depth, transmittance, loss and SSIM maps, their
# gradients): the peak RSS growth of one forward + backward over the model's own bytes in
# benchmarks/bench_raster.py (numba, 320x240): 26 MB at 20k, 81 MB at 100k Gaussians
STEP_BYTES_PER_GAUSSIAN = 512
STEP_BYTES_PER_PIXEL = 192
# The map's way out, per Gaussian: the session's delta mirror keeps every row as GaussianRecords
# (236 B: PLY fields with 45 SH-rest floats at any degree), and a delta or snapshot that carries
# every row is built once more as message rows and again as the message's bytes
DELTA_BYTES_PER_GAUSSIAN = 3 * 236
# MergeConfig.tau must be finite: a bound no mean positional gradient reaches turns the gate off.
_NO_GRADIENT_GATE = 1e30

MergeFn = Callable[..., Any]  # merge_pass(gmap, merge_cfg, newest_keyframe_id, iteration) -> MergeResult


def load_merge() -> MergeFn | None:
    """memgs_ros.core.merge.voxel_merge.merge_pass, when that module is importable."""
    try:
        from memgs_ros.core.merge import voxel_merge as merge_mod
    except ImportError:
        return None
    return getattr(merge_mod, "merge_pass", None)


class MergeSchedule:
    """When the scheduled merge runs, and the merge itself (reference section 4).

    ``merge_fn``: the merge pass (default ``merge_pass`` when ``cfg.merge_enabled``); ``merge_cfg``:
    its ``MergeConfig`` (default ``MergeConfig()``). ``last`` / ``last_budget``: the latest
    ``MergeResult`` of a scheduled and of a budget pass.
    """

    def __init__(self, cfg: MappingConfig, merge_fn: MergeFn | None = None, merge_cfg: Any = None) -> None:
        self.cfg = cfg
        self.merge_fn = merge_fn if merge_fn is not None else (load_merge() if cfg.merge_enabled else None)
        self.merge_cfg = merge_cfg
        self.last: Any = None
        self.last_budget: Any = None
        self.passes = 0  # scheduled passes run
        self._keyframes_since = 0  # keyframes inserted since the last pass
        self._last_iteration = 0  # of the last pass

    @property
    def available(self) -> bool:
        return self.merge_fn is not None

    def keyframe_added(self) -> None:
        """Count a keyframe towards the in-flight schedule (``merge_every_keyframes``)."""
        self._keyframes_since += 1

    def due(self, iteration: int) -> bool:
        """On the iteration schedule (``merge_start_iter`` + k ``merge_interval``), or in flight once
        ``merge_every_keyframes`` keyframes came since the last pass and it is at least
        ``merge_keyframes_min_iters`` iterations old (their seeds have been trained on a little): a
        live mapper, which trains a few hundred iterations while the camera moves, merges then too."""
        cfg = self.cfg
        if self.merge_fn is None or not cfg.merge_enabled or iteration > cfg.merge_stop_iter:
            return False
        if cfg.merge_start_iter <= iteration and iteration % cfg.merge_interval == 0:
            return True
        return (0 < cfg.merge_every_keyframes <= self._keyframes_since
                and iteration - self._last_iteration >= cfg.merge_keyframes_min_iters)

    def run(self, gmap: GaussianMap, newest_kf_id: int, iteration: int) -> tuple[int, int]:
        """One scheduled merge pass on the live map. Returns (removed, added) Gaussian counts."""
        if self.merge_fn is None:
            return 0, 0
        if self.merge_cfg is None:
            from memgs_ros.core.merge import voxel_merge as merge_mod

            self.merge_cfg = merge_mod.MergeConfig()
        result = self.merge_fn(gmap, self.merge_cfg, newest_kf_id, iteration)
        gmap.reset_merge_stats()  # each pass judges stability on the gradients seen since the last
        self.last = result
        self.passes += 1
        self._keyframes_since, self._last_iteration = 0, iteration
        return int(result.removed_ids.numel()), int(result.added_ids.numel())

    def budget_config(self, newest_kf_id: int) -> Any:
        """The merge configuration for budget passes, or None when there is none to relax.

        Relaxed from the scheduled one (``MergeConfig``): every keyframe in the window (the budget
        binds the whole map, not the newest keyframes), no gradient gate nor age (a Gaussian still
        moving is better merged than pruned) and a voxel ``budget_merge_voxel_scale`` times larger (default
        1: a coarser voxel merged more without lowering the PSNR cost, see ``BudgetStrategy``); the
        Mahalanobis gate stays, so only overlapping Gaussians merge.
        """
        if self.merge_fn is None or not self.cfg.budget_merge:
            return None
        from memgs_ros.core.merge import voxel_merge as merge_mod

        base = self.merge_cfg if self.merge_cfg is not None else merge_mod.MergeConfig()
        if not isinstance(base, merge_mod.MergeConfig) or not base.enabled:
            return None  # a caller's own merge configuration: nothing known to relax
        return replace(base, window_keyframes=max(newest_kf_id + 1, 1), tau=_NO_GRADIENT_GATE, min_age_iters=0,
                       voxel_size_m=base.voxel_size_m * self.cfg.budget_merge_voxel_scale)


@dataclass(frozen=True)
class MemoryAccount:
    """The mapper's accounted working memory in bytes (``mapping.max_mapper_mbytes`` bounds
    ``total``): the model (parameters, gradients, Adam moments), the stored keyframes, the
    training step's buffers (estimated from the Gaussian count and the full-resolution pixels)
    and the map's delta mirror with one full-map message in flight (``DELTA_BYTES_PER_GAUSSIAN``)."""

    model: int
    keyframes: int
    step_buffers: int
    delta: int = 0

    @property
    def total(self) -> int:
        return self.model + self.keyframes + self.step_buffers + self.delta


def step_buffer_bytes(n_gaussians: int, n_pixels: int) -> int:
    """Estimated bytes of one training step's buffers beyond the model (see the constants)."""
    return STEP_BYTES_PER_GAUSSIAN * int(n_gaussians) + STEP_BYTES_PER_PIXEL * int(n_pixels)


class BudgetStrategy:
    """The memory budget (``max_gaussians`` / ``max_model_mbytes``, 0 = none; both set: the tighter).

    Enforcement (``enforce``), measured at half the unbudgeted size
    (benchmarks/bench_memory_budget.py, keyframe / all-frames PSNR cost): synthetic 1.93 / 1.11 dB
    with the budget merge (voxel x1; x2 2.01 / 1.10, x4 2.02 / 1.24), 2.03 / 1.24 dB without; TUM
    fr1/rpy (voxel x2) 0.72 / 0.23 dB with, 0.67 / 0.22 without: no worse than pruning.
    """

    def __init__(self, cfg: MappingConfig, merge: MergeSchedule, generator: torch.Generator) -> None:
        self.cfg = cfg
        self.merge = merge
        self._generator = generator

    @staticmethod
    def trained_bytes_per_gaussian(gmap: GaussianMap) -> int:
        """Bytes ``GaussianMap.memory_bytes().total`` counts per Gaussian once the map trains:
        every parameter row four times (value, gradient, Adam exp_avg and exp_avg_sq)."""
        return 4 * sum(math.prod(p.shape[1:]) * p.element_size() for p in gmap.params().values())

    @staticmethod
    def training_pixels(keyframes: KeyframeStore) -> int:
        """Pixels of the largest full-resolution training view (0 without keyframes)."""
        return max((kf.camera.width * kf.camera.height for kf in keyframes.all()), default=0)

    def fixed_bytes(self, keyframes: KeyframeStore) -> int:
        """The accounted memory that does not scale with the Gaussians: keyframes and the
        per-pixel step buffers (only needed when ``max_mapper_mbytes`` is set)."""
        if self.cfg.max_mapper_mbytes <= 0:
            return 0
        return keyframes.nbytes() + step_buffer_bytes(0, self.training_pixels(keyframes))

    def account(self, gmap: GaussianMap, keyframes: KeyframeStore) -> MemoryAccount:
        """The accounted working memory now (``mapping.max_mapper_mbytes`` bounds its total): the
        model at its trained cost (gradients and Adam moments counted before they exist, as the
        budget does), the stored keyframes, the step buffers and the delta bytes."""
        n = len(gmap)
        return MemoryAccount(model=n * self.trained_bytes_per_gaussian(gmap), keyframes=keyframes.nbytes(),
                             step_buffers=step_buffer_bytes(n, self.training_pixels(keyframes)),
                             delta=n * DELTA_BYTES_PER_GAUSSIAN)

    def limit(self, gmap: GaussianMap, fixed_bytes: int = 0) -> int:
        """The budget as a Gaussian count (0 = none): the tightest of ``max_gaussians``,
        ``max_model_mbytes`` at a trained map's bytes per Gaussian, and ``max_mapper_mbytes``
        less ``fixed_bytes`` (the keyframes and the per-pixel step buffers) at a trained
        Gaussian's bytes plus its step buffers and delta bytes; at least 1 when set. The MiB budgets are
        converted at the trained cost, so seeds inserted before training respect them."""
        cfg = self.cfg
        limits = [cfg.max_gaussians] if cfg.max_gaussians > 0 else []
        per_gaussian = self.trained_bytes_per_gaussian(gmap)
        if cfg.max_model_mbytes > 0:
            limits.append(max(int(cfg.max_model_mbytes * 2**20 // per_gaussian), 1))
        if cfg.max_mapper_mbytes > 0:
            free = cfg.max_mapper_mbytes * 2**20 - fixed_bytes
            limits.append(max(int(free // (per_gaussian + STEP_BYTES_PER_GAUSSIAN + DELTA_BYTES_PER_GAUSSIAN)), 1))
        return min(limits) if limits else 0

    def enforce(self, gmap: GaussianMap, iteration: int, newest_kf_id: int, fixed_bytes: int = 0) -> tuple[int, int]:
        """Bring a map over the limit down to ``budget_target_fraction`` of it (hysteresis).

        1. Relaxed merge passes (``MergeSchedule.budget_config``), when merging is on: merging
           keeps what both Gaussians described, so it goes before pruning.
        2. If still above the target: prune the smallest ``contribution`` down to the target.
        Returns (merged pairs, pruned Gaussians); (0, 0) without a budget or within it.
        """
        limit = self.limit(gmap, fixed_bytes)
        if limit == 0 or len(gmap) <= limit:
            return 0, 0
        return self.shrink_to(gmap, max(int(limit * self.cfg.budget_target_fraction), 1), iteration,
                              newest_kf_id)

    def shrink_to(self, gmap: GaussianMap, target: int, iteration: int, newest_kf_id: int,
                  keep: torch.Tensor | None = None) -> tuple[int, int]:
        """Relaxed merge passes, then pruning by ``contribution``, down to ``target`` Gaussians;
        rows where ``keep`` ([N] bool) is set are never pruned. Returns (merged, pruned)."""
        with torch.no_grad():
            merged = 0
            merge_cfg = self.merge.budget_config(newest_kf_id)
            if merge_cfg is not None and self.merge.merge_fn is not None:
                for _ in range(BUDGET_MERGE_PASSES):
                    result = self.merge.merge_fn(gmap, merge_cfg, newest_kf_id, iteration)
                    self.merge.last_budget = result
                    n = int(result.added_ids.numel())
                    merged += n
                    if n == 0 or len(gmap) <= target:
                        break
            pruned = max(len(gmap) - target, 0)
            if pruned:
                score = self.contribution(gmap, iteration)
                if keep is not None and len(keep) == len(gmap):
                    score[keep] = math.inf
                weakest = torch.topk(score, pruned, largest=False).indices
                mask = torch.zeros(len(gmap), dtype=torch.bool, device=gmap.device)
                mask[weakest] = True
                gmap.remove(mask)
            logger.debug("budget: merged %d pairs, pruned %d -> %d Gaussians", merged, pruned, len(gmap))
            return merged, pruned

    def contribution(self, gmap: GaussianMap, iteration: int) -> torch.Tensor:
        """Budget pruning order, [N]: the smallest go first.

        Gaussians older than ``prune_min_age_iters`` score their opacity (the 3DGS prune signal).
        Younger ones (new seeds, fresh clones) have not been trained enough to judge: they score
        1 + a uniform draw, i.e. they go only once every older Gaussian is kept, and then at
        random, which thins new seeds evenly. (Not world size: seeds are sized by their neighbour
        spacing, so opacity x area would strip whole near-camera surfaces first; on a 3-keyframe
        64x48 scene at half the seeds it lost 2.5 dB against random thinning.)
        """
        score = gmap.opacities().detach().reshape(-1).clone()
        young = gmap.created_iter > iteration - self.cfg.prune_min_age_iters
        n_young = int(young.sum())
        if n_young:
            draw = torch.rand(n_young, generator=self._generator, dtype=score.dtype).to(score.device)
            score[young] = 1.0 + draw
        return score

    def make_room_for_densification(self, gmap: GaussianMap, densify: DensifyStrategy, iteration: int,
                                    newest_kf_id: int, fixed_bytes: int = 0) -> tuple[int, int]:
        """At budget, trade weak Gaussians for densification: when the clone/split candidates want
        more room than the budget leaves, shrink the map (merge, then prune the lowest
        ``contribution``, never a candidate) by up to the hysteresis margin,
        (1 - ``budget_target_fraction``) x budget, per densification interval. Without it a map at
        budget only densifies into what the opacity prune frees; with it the synthetic bench at
        half the unbudgeted size lost 2.01 dB instead of 2.16 dB (keyframe PSNR).
        Returns (merged, pruned).
        """
        cfg = self.cfg
        limit = self.limit(gmap, fixed_bytes)
        if limit == 0:
            return 0, 0
        with torch.no_grad():
            high = gmap.densify_grad_mean() >= cfg.densify_grad_threshold
            clone = gmap.scales().max(dim=1).values <= cfg.percent_dense * gmap.spatial_lr_scale
            growth = int(torch.where(clone, 1, cfg.split_children - 1)[high].sum())
            room = limit - len(gmap) + int((densify.prunable(gmap, iteration) & ~high).sum())
            need = min(growth - room, limit - max(int(limit * cfg.budget_target_fraction), 1))
            if need <= 0:
                return 0, 0
            return self.shrink_to(gmap, len(gmap) - need, iteration, newest_kf_id, keep=high)


class DensifyStrategy:
    """3DGS adaptive density control without opacity reset (reference section 5).

    Every ``densify_interval`` iterations in [densify_start_iter, densify_stop_iter], Gaussians
    whose mean NDC 2D gradient exceeds ``densify_grad_threshold`` are cloned (max scale <=
    percent_dense x extent) or split into ``split_children`` scaled by 1/``split_scale_factor``;
    then Gaussians with opacity < ``prune_opacity`` (and, when ``max_screen_size_px`` > 0, larger
    on screen than that or wider than 0.1 x extent) are pruned. A Gaussian younger than
    ``prune_min_age_iters`` is never pruned: seeds start at opacity 0.1, at the prune threshold,
    and a new keyframe's seeds may not have been rendered yet.
    """

    def __init__(self, cfg: MappingConfig, generator: torch.Generator) -> None:
        self.cfg = cfg
        self._generator = generator
        self._window_from = 0  # the iteration the densification window counts from

    def keyframe_came(self, iteration: int, novel: float = 1.0) -> None:
        """A keyframe came at ``iteration``; ``novel``: the share of its seeds the settled map lacked.
        It opens the window in that proportion: a new view all of it, a revisit whose seeds the map
        already explains almost none (it counts as having come that much earlier). Without this a
        flight over one room densified after every revisit's keyframe and grew the map with the
        flight (acknowledged ping-pong: 1.35x one pass's Gaussians, 1.24x with it)."""
        unseen = self.cfg.densify_window_iters * (1.0 - min(max(novel, 0.0), 1.0))
        self._window_from = max(self._window_from, iteration - round(unseen))

    def due(self, iteration: int, in_flight: bool = False) -> bool:
        """Densify at ``iteration``? In flight only within ``densify_window_iters`` of the newest
        keyframe (``keyframe_came``): over a room already mapped no keyframe comes, and
        densification would grow the map with the training time."""
        cfg = self.cfg
        if in_flight and cfg.densify_window_iters and iteration - self._window_from > cfg.densify_window_iters:
            return False
        return cfg.densify_start_iter <= iteration <= cfg.densify_stop_iter and iteration % cfg.densify_interval == 0

    def prunable(self, gmap: GaussianMap, iteration: int) -> torch.Tensor:
        """Rows the densification prune removes now (opacity, and size when enabled): [N] bool."""
        cfg = self.cfg
        old_enough = gmap.created_iter <= iteration - cfg.prune_min_age_iters
        prune = (gmap.opacities().reshape(-1) < cfg.prune_opacity) & old_enough
        if cfg.max_screen_size_px > 0:
            big = ((gmap.max_radii2d > cfg.max_screen_size_px)
                   | (gmap.scales().max(dim=1).values > 0.1 * gmap.spatial_lr_scale))
            prune |= big & old_enough
        return prune

    def within_budget(self, gmap: GaussianMap, high: torch.Tensor, grads: torch.Tensor,  # [N] bool, [N]
                      max_scale: torch.Tensor, limit: int, iteration: int) -> torch.Tensor:  # [N]
        """The densify candidates ``high`` ([N] bool) cut to the room left under ``limit``.

        A clone adds one Gaussian, a split ``split_children - 1``; the room is the limit minus the
        map plus what the prune after densification will free among rows not densified.
        Candidates are kept in order of decreasing gradient while their summed growth fits.
        Returns [N] bool.
        """
        cfg = self.cfg
        room = limit - len(gmap) + int((self.prunable(gmap, iteration) & ~high).sum())
        idx = torch.nonzero(high).reshape(-1)
        if room <= 0:
            return torch.zeros_like(high)
        clone = max_scale[idx] <= cfg.percent_dense * gmap.spatial_lr_scale
        growth = torch.where(clone, 1, cfg.split_children - 1)
        order = torch.argsort(grads[idx], descending=True, stable=True)
        fits = torch.cumsum(growth[order], 0) <= room
        kept = torch.zeros_like(high)
        kept[idx[order[fits]]] = True
        return kept

    def densify_and_prune(self, gmap: GaussianMap, iteration: int, limit: int = 0) -> tuple[int, int]:
        """Clone/split, then prune; ``limit`` > 0 caps the growth (budget). Returns (added, removed)."""
        cfg = self.cfg
        with torch.no_grad():
            n0 = len(gmap)
            extent = gmap.spatial_lr_scale
            grads = gmap.densify_grad_mean()
            max_scale = gmap.scales().max(dim=1).values
            high = grads >= cfg.densify_grad_threshold
            if limit:
                high = self.within_budget(gmap, high, grads, max_scale, limit, iteration)
            clone_idx = torch.nonzero(high & (max_scale <= cfg.percent_dense * extent)).reshape(-1)
            split_idx = torch.nonzero(high & (max_scale > cfg.percent_dense * extent)).reshape(-1)
            added = 0
            k = cfg.split_children
            child: dict[str, torch.Tensor] = {}
            if split_idx.numel():  # children computed before anything changes the row positions
                std = gmap.scales()[split_idx].repeat(k, 1)
                samples = torch.randn(std.shape, generator=self._generator).to(gmap.device) * std
                rot = quat_wxyz_to_rotmat_torch(gmap.quats_wxyz[split_idx]).repeat(k, 1, 1)
                child = {
                    "means": (rot @ samples[..., None])[..., 0] + gmap.means[split_idx].repeat(k, 1),
                    "log_scales": torch.log(std / cfg.split_scale_factor),
                    "quats_wxyz": gmap.quats_wxyz[split_idx].repeat(k, 1),
                    "opacity_logits": gmap.opacity_logits[split_idx].repeat(k, 1),
                    "sh_dc": gmap.sh_dc[split_idx].repeat(k, 1, 1),
                    "sh_rest": gmap.sh_rest[split_idx].repeat(k, 1, 1),
                    "keyframe_id": gmap.keyframe_ids[split_idx].repeat(k),
                }
            if clone_idx.numel():
                gmap.add(gmap.means[clone_idx], gmap.log_scales[clone_idx], gmap.quats_wxyz[clone_idx],
                         gmap.opacity_logits[clone_idx], gmap.sh_dc[clone_idx], gmap.sh_rest[clone_idx],
                         gmap.keyframe_ids[clone_idx], iteration)
                added += clone_idx.numel()
            if split_idx.numel():
                gmap.add(iteration=iteration, **child)
                added += child["means"].shape[0]
                parents = torch.zeros(len(gmap), dtype=torch.bool, device=gmap.device)
                parents[split_idx] = True
                gmap.remove(parents)
            n1 = len(gmap)
            gmap.reset_densify_stats()
            prune = self.prunable(gmap, iteration)
            removed_prune = int(prune.sum())
            if removed_prune:
                gmap.remove(prune)
            logger.debug("densify: %d -> %d (+%d clone/split) -> %d after pruning", n0, n1, added, len(gmap))
            return added, removed_prune + int(split_idx.numel())


class TrainingSetStrategy:
    """The mapper's training keyframes, bounded: the newest ``training_window`` and, beside them,
    the flight's most spread-out views (``max_keyframes``, 0 = all), so that a long flight's image
    memory and per-iteration work stay flat."""

    def __init__(self, cfg: MappingConfig) -> None:
        self.cfg = cfg

    def drop(self, store: KeyframeStore, over_memory_cap: Callable[[], bool]) -> list[int]:
        """Remove keyframes from ``store`` while it holds more than ``max_keyframes`` or
        ``over_memory_cap()``: each time the one whose pose is closest to another (translation in
        metres + 0.5 m per radian of rotation), never one of the newest ``training_window``
        (at most ``max_keyframes - 1`` of them). Returns the removed ids, in order."""
        cap, out = self.cfg.max_keyframes, []
        while (cap > 0 and len(store) > cap) or over_memory_cap():
            kfs = store.all()
            nearest = nearest_pose_distance(np.stack([k.T_wc for k in kfs]))
            window = min(self.cfg.training_window, cap - 1 if cap > 0 else len(kfs) - 1, len(kfs) - 1)
            if window > 0:
                nearest[-window:] = np.inf  # id order: the newest last
            if not np.isfinite(nearest).any():
                break
            out.append(kfs[int(np.argmin(nearest))].kf_id)
            store.remove(out[-1])
        return out

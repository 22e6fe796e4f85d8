"""The mapping back-end: keyframes in, an optimised Gaussian map out (reference section 5).

``GaussianMapper`` owns a ``GaussianMap`` and a ``KeyframeStore``. Each ``step()`` draws one
training view (Photo-SLAM schedule, coarse-to-fine pyramid), renders it, applies the loss
(photometric + isotropic + optional depth L1), back-propagates, accumulates densification and
merge statistics, takes an Adam step and, on schedule, densifies/prunes (3DGS clone/split),
merges (MemGS voxel merge, ``memgs_ros.core.merge.voxel_merge.merge_pass``) and raises the SH degree.

The policies that change the map's size live in ``memgs_ros.core.mapping.strategies`` (densify/prune,
merge schedule, memory budget). ``GaussianMapper`` is single-threaded: it has no lock. A program
that trains while other threads insert, render or read the map uses
``memgs_ros.core.mapper_service.session.MappingSession``, the one owner of a mapper, whose worker thread runs
every call.

Densification choices (documented differences from plain 3DGS): no opacity reset (reference
section 5); a Gaussian younger than ``prune_min_age_iters`` is never pruned, because seeds start
at opacity 0.1, at the prune threshold, and a new keyframe's seeds may not have been rendered yet;
in an iteration where a merge is scheduled, densification waits for the next interval (merge and
densification alternate, reference section 4).
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from memgs_ros.core.gaussians.gaussian_map import GaussianMap, GaussianRecords
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.geometry.view import view_preparation
from memgs_ros.core.mapping.anchors import KeyframeAnchors
from memgs_ros.core.mapping.config import MappingConfig
from memgs_ros.core.mapping.coverage import settled_uncovered
from memgs_ros.core.mapping.device_peaks import PeakAttribution
from memgs_ros.core.mapping.device_view import device_view
from memgs_ros.core.mapping.exposure import ExposureCompensation
from memgs_ros.core.mapping.keyframes import KeyframeStore, TrainingKeyframe, make_keyframe
from memgs_ros.core.mapping.losses import mapping_loss
from memgs_ros.core.mapping.mapper_state import MapperState
from memgs_ros.core.mapping.rigid import move_with_keyframes
from memgs_ros.core.mapping.strategies import (
    BudgetStrategy,
    DensifyStrategy,
    MemoryAccount,
    MergeFn,
    MergeSchedule,
    TrainingSetStrategy,
)
from memgs_ros.errors import ConfigError, DataError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class StepStats:
    """What one ``step()`` did. ``terms`` are the loss terms (see ``losses.mapping_loss``).

    ``budget_merged`` / ``budget_pruned``: Gaussians the memory budget removed since the previous
    step (``enforce_budget``, including its runs after ``add_keyframe``):
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


def prepare_keyframe(cfg: MappingConfig, device: torch.device, kf_id: int, stamp_ns: int, T_wc: np.ndarray,
                     rgb: np.ndarray, depth: np.ndarray | None, camera: PinholeCamera,
                     depth_scale: float = 1.0, on_device: bool | None = None) -> TrainingKeyframe:
    """The keyframe as it is trained on: undistorted, resized to ``cfg.resolution_scale``, with its
    valid-pixel mask, on ``device`` (``core/geometry/view.py``, ``make_keyframe``). A pure function
    of the config: any thread may call it while a mapper trains.

    T_wc: [4, 4] camera-to-world; rgb: [H, W, 3] uint8; depth: [H, W] float32 metres (NaN/0
    invalid) or uint16 raw units (``depth_scale`` per metre), or None; camera: intrinsics of rgb
    (with its distortion). ``on_device`` (default: on any device but the CPU) uploads the images as
    they are and prepares them there (``DeviceView``); otherwise OpenCV prepares them on the host.
    """
    if rgb.dtype != np.uint8 or rgb.shape != (camera.height, camera.width, 3):
        raise DataError(f"keyframe {kf_id}: rgb must be uint8 [{camera.height}, {camera.width}, 3], "
                        f"got {rgb.dtype} {rgb.shape}")
    if depth is not None and depth.shape != (camera.height, camera.width):
        raise DataError(f"keyframe {kf_id}: depth must be [{camera.height}, {camera.width}], got {depth.shape}")
    device = torch.device(device)
    prep = view_preparation(camera, cfg.resolution_scale)
    mask_t = None
    if on_device if on_device is not None else device.type != "cpu":
        view = device_view(prep, device)
        raw = None if depth is None else torch.from_numpy(_torch_compatible(depth)).to(device)
        image, depth_t = view(torch.from_numpy(_torch_compatible(rgb)).to(device), raw, depth_scale)
        if cfg.mask_invalid_pixels:
            mask_t = view.valid_mask
    else:
        rgb_p, depth_p = prep(rgb, depth, depth_scale)
        image = torch.from_numpy(_torch_compatible(rgb_p)).to(device).permute(2, 0, 1)  # uint8, stored as is
        depth_t = None
        if depth_p is not None:
            d = np.where(np.isfinite(depth_p) & (depth_p > 0), depth_p, 0.0).astype(np.float32)
            depth_t = torch.from_numpy(d).to(device)
        if cfg.mask_invalid_pixels and prep.valid_mask is not None:
            mask_t = torch.from_numpy(prep.valid_mask).to(device)
    return make_keyframe(kf_id, stamp_ns, T_wc, image.contiguous(), depth_t, prep.camera, valid_mask=mask_t)


def _torch_compatible(a: np.ndarray) -> np.ndarray:
    """An image array torch.from_numpy takes: C-contiguous, native byte order, writeable (a view
    on a received message is read-only: copied then, in its compact type)."""
    if a.flags.c_contiguous and a.flags.writeable and a.dtype.isnative:
        return a
    return np.array(a, dtype=a.dtype.newbyteorder("="), order="C")


class GaussianMapper(MapperState):
    """Trains a Gaussian map on keyframes (see module docstring). ``device``: torch device.

    Not thread-safe: one thread calls it (``MappingSession``'s worker, or a script). Its state
    leaves and enters only through ``state_dict`` / ``load_state_dict``.
    """

    def __init__(self, cfg: MappingConfig | None = None, device: torch.device | str = "cpu",
                 merge_fn: MergeFn | None = None, merge_cfg: Any = None) -> None:
        self.cfg = cfg if cfg is not None else MappingConfig()
        self.device = torch.device(device)
        extent = self.cfg.scene_extent if self.cfg.scene_extent > 0 else self.cfg.min_scene_extent
        self.gmap = GaussianMap(self.cfg.max_sh_degree, self.device, self.cfg.learning_rates(), extent)
        self.keyframes = KeyframeStore(self.cfg.new_keyframe_budget, self.cfg.pyramid_uses_per_level,
                                       seed=self.cfg.seed)
        self.iteration = 0
        self.keyframes_dropped = 0  # by max_keyframes
        self.keyframes_retired = 0  # culled by the tracker
        self.seeds_covered = 0  # seeds not made Gaussians: the map already explained them
        self._newest_kf_id = -1
        self._anchors = KeyframeAnchors()  # every keyframe inserted, also those dropped from training
        self.exposure = ExposureCompensation(self.cfg.exposure_lr, self.cfg.exposure_reg, self.device) \
            if self.cfg.exposure_compensation else None
        self._background = torch.tensor(self.cfg.background, dtype=torch.float32, device=self.device)
        generator = torch.Generator(device="cpu").manual_seed(self.cfg.seed)
        self.merge = MergeSchedule(self.cfg, merge_fn, merge_cfg)
        self.densify = DensifyStrategy(self.cfg, generator)
        self.budget = BudgetStrategy(self.cfg, self.merge, generator)
        self.training_set = TrainingSetStrategy(self.cfg)
        self._budget_pending = (0, 0)  # (merged, pruned) by the budget since the last StepStats
        self.peaks = PeakAttribution(self.device)  # which work set the GPU's allocation peak

    # ----------------------------------------------------------- properties
    @property
    def scene_extent(self) -> float:
        return self.gmap.spatial_lr_scale

    @property
    def ready(self) -> bool:
        """True once ``min_keyframes`` keyframes exist (training starts then)."""
        return len(self.keyframes) >= max(self.cfg.min_keyframes, 1)

    @property
    def budget_gaussians(self) -> int:
        """The memory budget as a Gaussian count (0 = none), see ``BudgetStrategy.limit``."""
        return self.budget.limit(self.gmap, self._fixed_bytes())

    def _fixed_bytes(self) -> int:
        return self.budget.fixed_bytes(self.keyframes)

    def memory_account(self) -> MemoryAccount:
        """The accounted working memory now (``BudgetStrategy.account``)."""
        return self.budget.account(self.gmap, self.keyframes)

    def trained_bytes_per_gaussian(self) -> int:
        return self.budget.trained_bytes_per_gaussian(self.gmap)

    # ------------------------------------------------------------ keyframes
    def add_keyframe(self, kf_id: int, stamp_ns: int, T_wc: np.ndarray, rgb: np.ndarray,
                     depth_m: np.ndarray | None, camera: PinholeCamera,
                     points_w: np.ndarray | None = None, colors: np.ndarray | None = None,
                     enforce_budget: bool = True) -> int:
        """Insert a keyframe and seed Gaussians at its points: ``prepare_keyframe`` then
        ``add_prepared_keyframe`` (see both). Returns the number of Gaussians added."""
        kf = self.prepare_keyframe(kf_id, stamp_ns, T_wc, rgb, depth_m, camera)
        return self.add_prepared_keyframe(kf, points_w, colors, enforce_budget)

    def prepare_keyframe(self, kf_id: int, stamp_ns: int, T_wc: np.ndarray, rgb: np.ndarray,
                         depth: np.ndarray | None, camera: PinholeCamera,
                         depth_scale: float = 1.0) -> TrainingKeyframe:
        """:func:`prepare_keyframe` with this mapper's config and device."""
        return prepare_keyframe(self.cfg, self.device, kf_id, stamp_ns, T_wc, rgb, depth, camera, depth_scale)

    def add_prepared_keyframe(self, kf: TrainingKeyframe, points_w: np.ndarray | None = None,
                              colors: np.ndarray | None = None, enforce_budget: bool = True) -> int:
        """Insert a prepared keyframe (``prepare_keyframe``, or a restored checkpoint's) and seed
        Gaussians at its points.

        points_w: [M, 3] world seeds (from undistorted pixels); colors: [M, 3] in [0, 1].
        enforce_budget: False leaves the memory budget to the next ``step`` (the map may exceed
        it by this keyframe's seeds until then): a worker that must keep up with the tracker
        then pays ~35 ms instead of ~180 ms on a 60k map at 320x240 (CPU).
        Returns the number of Gaussians added.
        """
        if points_w is not None and len(points_w) and colors is None:
            raise DataError(f"keyframe {kf.kf_id}: points_w given without colors")
        with self.peaks.work("keyframe insertion"):
            return self._add_prepared(kf, points_w, colors, enforce_budget)

    def _add_prepared(self, kf: TrainingKeyframe, points_w: np.ndarray | None, colors: np.ndarray | None,
                      enforce_budget: bool) -> int:
        self._insert(kf)
        self._drop_redundant_keyframes()
        self._update_extent()
        self.merge.keyframe_added()
        novel = 1.0  # the share of the keyframe's seeds the settled map lacked
        if points_w is not None and len(points_w) and colors is not None:  # colors checked above
            keep = self._uncovered(kf, points_w)
            if keep is not None:
                self.seeds_covered += int(np.count_nonzero(~keep))
                novel = float(np.count_nonzero(keep)) / len(keep)
                points_w, colors = np.asarray(points_w)[keep], np.asarray(colors)[keep]
        self.densify.keyframe_came(self.iteration, novel)
        if points_w is None or colors is None or not len(points_w):
            return 0
        ids = self.gmap.add_from_points(points_w, colors, kf.kf_id, self.iteration, opacity=self.cfg.seed_opacity)
        # A memory cap is a promise about every moment, not about the next step: keep it here
        # even when the caller leaves the Gaussian budget to the step (free-running inserts).
        if enforce_budget or self.cfg.max_mapper_mbytes > 0:
            self._enforce_budget()
        return int(ids.numel())

    def _uncovered(self, kf: TrainingKeyframe, points_w: np.ndarray) -> np.ndarray | None:
        """[M] bool: the seeds the settled map lacks (``coverage.settled_uncovered``); None: keep all."""
        if not self.cfg.seed_coverage:
            return None
        age_ns, trained = int(self.cfg.seed_coverage_age_s * 1e9), self.cfg.seed_coverage_trained_iters  # 0: age only
        settled = self._anchors.settled(kf.stamp_ns - age_ns, (self.iteration - trained) if trained else None)
        with self.peaks.work("coverage"):
            return settled_uncovered(self.gmap, settled, np.asarray(points_w), kf.T_wc, kf.camera, self.cfg,
                                     self._background)

    def _insert(self, kf: TrainingKeyframe) -> None:
        self.keyframes.add(kf)
        self._anchors.add(kf.kf_id, kf.stamp_ns, kf.T_wc, self.iteration)
        self._newest_kf_id = max(self._newest_kf_id, int(kf.kf_id))

    def _over_memory_cap(self) -> bool:
        """The accounted memory is over ``max_mapper_mbytes`` and keyframes may still go (more
        than ``min_keyframes``, at least 2: training needs views)."""
        cap = self.cfg.max_mapper_mbytes
        return (cap > 0 and len(self.keyframes) > max(self.cfg.min_keyframes, 2)
                and self.memory_account().total > cap * 2**20)

    def _drop_redundant_keyframes(self) -> None:
        """Keep at most ``max_keyframes``, and drop keyframes while the accounted memory is over
        ``max_mapper_mbytes`` (before the map is merged or pruned for it): ``TrainingSetStrategy``."""
        for dropped in self.training_set.drop(self.keyframes, self._over_memory_cap):
            if self.exposure is not None:
                self.exposure.remove(dropped)
            self.keyframes_dropped += 1

    def retire_keyframes(self, kf_ids: list[int]) -> tuple[int, int]:
        """Keyframes the tracker culled as redundant: their views leave training, and the Gaussians
        they created follow the nearest kept keyframe (by pose, its heir) from now on, so a loop
        correction still moves them. Unknown ids are ignored. Returns (retired, Gaussians handed on)."""
        known = [k for k in kf_ids if k in self._anchors]
        handed = 0
        for kf_id, heir in ((k, self._anchors.retire(k)) for k in known):
            if kf_id in self.keyframes:
                self.keyframes.remove(kf_id)
                if self.exposure is not None:
                    self.exposure.remove(kf_id)
            rows = self.gmap.keyframe_ids == int(kf_id)
            handed += int(rows.sum()) if heir is not None else 0
            self.gmap.keyframe_ids[rows] = heir if heir is not None else kf_id
        self.keyframes_retired += len(known)
        return len(known), handed

    def update_keyframe_pose(self, kf_id: int, T_wc: np.ndarray) -> bool:
        """Replace a keyframe's pose (e.g. after bundle adjustment). Returns False (and changes
        nothing) for a keyframe no longer trained on (dropped by max_keyframes)."""
        return self.update_keyframe_poses({kf_id: T_wc}) == 1

    def update_keyframe_poses(self, poses: Mapping[int, np.ndarray]) -> int:
        """``update_keyframe_pose`` for many keyframes ({kf_id: T_wc [4, 4]}); returns how many
        were updated (the rest are no longer trained on). The Gaussians stay where they are."""
        updated = 0
        for kf_id, T_wc in poses.items():
            if kf_id in self.keyframes:
                self.keyframes.update_pose(kf_id, T_wc)
                self._anchors.move(kf_id, T_wc)
                updated += 1
        if updated:
            self._update_extent()
        return updated

    def correct_keyframes(self, poses: Mapping[int, np.ndarray], retrain: bool = True) -> tuple[int, int]:
        """Rigidly move keyframes and the Gaussians anchored to them (a loop closure). poses:
        {kf_id: corrected T_wc [4, 4]}; each keyframe's correction D = T_new inv(T_old) moves the
        Gaussians it created (``rigid.move_with_keyframes``), also those of keyframes no longer
        trained on. ``retrain``: corrected keyframes still trained on get a fresh new-keyframe budget
        of training views (priority). Returns (keyframes corrected, Gaussians moved)."""
        todo: list[tuple[int, np.ndarray, np.ndarray]] = []  # (kf_id, T_new, D), validated before any change
        for kf_id, T_new in poses.items():
            T_new = np.asarray(T_new, dtype=np.float64)
            if T_new.shape != (4, 4) or not np.all(np.isfinite(T_new)):
                raise DataError(f"keyframe {kf_id}: corrected T_wc must be a finite 4x4 matrix")
            T_old = self._anchors.pose(kf_id)
            if T_old is not None:
                todo.append((int(kf_id), T_new, T_new @ invert_pose(T_old)))
        if not todo:
            return 0, 0
        todo.sort(key=lambda c: c[0])
        moved = move_with_keyframes(self.gmap, [c[0] for c in todo], np.stack([c[2] for c in todo]))
        for kf_id, T_new, _ in todo:
            self._anchors.move(kf_id, T_new)
            if kf_id in self.keyframes:
                self.keyframes.update_pose(kf_id, T_new)
                if retrain:
                    self.keyframes.prioritise(kf_id)
        self._update_extent()
        return len(todo), moved

    def _update_extent(self) -> None:
        if self.cfg.scene_extent > 0 or len(self.keyframes) == 0:
            return
        centres = np.stack([kf.T_wc[:3, 3] for kf in self.keyframes.all()])
        radius = float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
        extent = max(1.1 * radius, self.cfg.min_scene_extent)
        if abs(extent - self.gmap.spatial_lr_scale) > 1e-9:
            self.gmap.set_spatial_lr_scale(extent)
            self.gmap.update_learning_rate(self.iteration)

    # ------------------------------------------------------------- training
    def _rasterize(self, T_wc: np.ndarray, camera: PinholeCamera):  # -> RenderOutput
        from memgs_ros.core.raster import rasterize

        T_cw = torch.as_tensor(invert_pose(np.asarray(T_wc, dtype=np.float64)), dtype=torch.float32,
                               device=self.device)
        g = self.gmap
        return rasterize(g.gaussians(), T_cw, camera, g.active_sh_degree, background=self._background,
                         near=self.cfg.near_m, backend=self.cfg.raster_backend)

    def step(self, densify: bool = True, final: bool = False, min_keyframes: int | None = None) -> StepStats | None:
        """One training iteration; None (and nothing done) until ``ready``, or with ``final``
        (the run has ended and no keyframe is coming) until there is one keyframe: a run that
        ended with fewer than ``min_keyframes`` must not leave its map untrained.
        ``min_keyframes`` replaces the config's start gate (a live mapper starts at 1).

        In an iteration where a merge is scheduled, densification waits for the next interval
        (merge and densification alternate, reference section 4). ``densify=False`` skips
        densification (a final polish that should not grow the map; in flight: DensifyStrategy.due).
        """
        gate = 1 if final else (self.cfg.min_keyframes if min_keyframes is None else min_keyframes)
        if len(self.keyframes) < max(gate, 1):
            return None
        t0 = time.perf_counter()
        cfg = self.cfg
        view = self.keyframes.next_view()
        if view is None or len(self.gmap) == 0:
            return None
        level = view.level
        peaks = self.peaks
        with peaks.work("forward"):
            out = self._rasterize(view.keyframe.T_wc, level.camera)
        color, exposure_reg = out.color, None
        if self.exposure is not None:
            color, exposure_reg = self.exposure.apply(view.keyframe.kf_id, color, train=level.factor == 1.0)
        with peaks.work("loss"):
            loss, terms = mapping_loss(color, level.image, self.gmap.log_scales, out.depth,
                                       level.depth_m, ssim_lambda=cfg.ssim_lambda,
                                       iso_weight=cfg.iso_weight, depth_weight=cfg.depth_weight,
                                       mask=level.valid_mask)
            if exposure_reg is not None:
                loss = loss + exposure_reg
        with peaks.work("backward"):
            loss.backward()
        grad2d = out.means2d.grad if out.means2d.grad is not None else None
        self.gmap.accumulate_stats(grad2d, out.visible, out.radii, level.camera.width, level.camera.height)
        self.gmap.update_learning_rate(self.iteration)
        with peaks.work("optimizer"):
            self.gmap.optimizer_step()
        if self.exposure is not None:
            self.exposure.step()
        self.iteration += 1
        it = self.iteration
        if it % cfg.sh_up_interval == 0:
            self.gmap.raise_sh_degree()
        merged_removed = merged_added = densified = pruned = 0
        if self.merge.due(it):
            with peaks.work("merge"):
                merged_removed, merged_added = self.merge.run(self.gmap, self._newest_kf_id, it)
        elif densify and self.densify.due(it, in_flight=not final):
            with peaks.work("densify"):
                self._record_budget(*self.budget.make_room_for_densification(
                    self.gmap, self.densify, it, self._newest_kf_id, self._fixed_bytes()))
                densified, pruned = self.densify.densify_and_prune(self.gmap, it, self.budget_gaussians)
        with peaks.work("budget"):
            self._enforce_budget()
        (budget_merged, budget_pruned), self._budget_pending = self._budget_pending, (0, 0)
        return StepStats(it, view.keyframe.kf_id, level.factor, terms, len(self.gmap), densified,
                         pruned, merged_removed, merged_added, time.perf_counter() - t0,
                         budget_merged, budget_pruned)

    def densify_and_prune(self) -> tuple[int, int]:
        """Densify/prune now (``DensifyStrategy``) within the budget. Returns (added, removed)."""
        return self.densify.densify_and_prune(self.gmap, self.iteration, self.budget_gaussians)

    def enforce_budget(self) -> tuple[int, int]:
        """Apply the memory budget now (``BudgetStrategy.enforce``). Returns (merged, pruned)."""
        return self.budget.enforce(self.gmap, self.iteration, self._newest_kf_id, self._fixed_bytes())

    def _enforce_budget(self) -> None:
        if self.cfg.max_mapper_mbytes > 0:
            self._drop_redundant_keyframes()  # over the memory cap keyframes go first, then Gaussians
        self._record_budget(*self.enforce_budget())

    def _record_budget(self, merged: int, pruned: int) -> None:
        if merged or pruned:
            m0, p0 = self._budget_pending
            self._budget_pending = (m0 + merged, p0 + pruned)

    def train(self, iterations: int, progress: bool = True,
              callback: Callable[[StepStats], None] | None = None) -> StepStats | None:
        """Run ``iterations`` steps (raises ConfigError if the mapper is not ready); returns the last stats."""
        if not self.ready:
            raise ConfigError(f"mapping needs {self.cfg.min_keyframes} keyframes, has {len(self.keyframes)}")
        from tqdm import tqdm

        last = None
        for _ in tqdm(range(iterations), desc="mapping", unit="it", disable=not progress):
            last = self.step()
            if callback is not None and last is not None:
                callback(last)
        return last

    # -------------------------------------------------------------- outputs
    def render(self, T_wc: np.ndarray, camera: PinholeCamera):  # -> RenderOutput
        """Render the map from camera-to-world ``T_wc`` with undistorted ``camera`` (no grad)."""
        with torch.no_grad(), self.peaks.work("render"):
            return self._rasterize(T_wc, camera)

    def render_keyframe(self, kf_id: int):  # -> RenderOutput
        """Render keyframe ``kf_id`` at its training resolution (no grad)."""
        kf = self.keyframes.get(kf_id)
        return self.render(kf.T_wc, kf.camera)

    def snapshot(self) -> GaussianRecords:
        """The whole map as records (host copies)."""
        with self.peaks.work("snapshot"):
            return self.gmap.to_records()

    # ----------------------------------------------------------- state

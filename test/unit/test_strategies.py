"""The map policies (core/mapping/strategies.py) on hand-made maps, without a mapper around them."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from memgs_ros.core.gaussians.gaussian_map import GaussianMap
from memgs_ros.core.mapping.mapper import MappingConfig
from memgs_ros.core.mapping.strategies import BudgetStrategy, DensifyStrategy, MergeSchedule
from memgs_ros.core.merge.voxel_merge import MergeConfig


def _map(n: int, log_scale: float = math.log(0.001), opacity: float = 0.5) -> GaussianMap:
    g = GaussianMap(0)
    rng = np.random.default_rng(0)
    t = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    g.add(t(rng.uniform(-1, 1, (n, 3))), t(np.full((n, 3), log_scale)), t(quats),
          t(np.full((n, 1), math.log(opacity / (1 - opacity)))), t(np.full((n, 1, 3), 0.5)), None, 0, 0)
    return g


def test_merge_schedule_runs_on_its_interval_and_relaxes_for_the_budget() -> None:
    calls: list[tuple[int, int]] = []

    class Result:
        removed_ids = torch.zeros(2, dtype=torch.int64)
        added_ids = torch.zeros(1, dtype=torch.int64)

    def merge_fn(gmap, cfg, newest, it):  # noqa: ANN001, ANN202
        calls.append((newest, it))
        return Result()

    cfg = MappingConfig(merge_start_iter=100, merge_interval=50, merge_stop_iter=300)
    m = MergeSchedule(cfg, merge_fn, MergeConfig(voxel_size_m=0.02))
    assert [it for it in range(0, 400, 25) if m.due(it)] == [100, 150, 200, 250, 300]
    g = _map(4)
    g.merge_grad_sum += 1.0
    g.merge_count += 1
    assert m.run(g, 7, 150) == (2, 1) and calls == [(7, 150)] and m.last is not None
    assert float(g.merge_grad_sum.sum()) == 0.0  # each pass judges the gradients since the last
    relaxed = m.budget_config(7)
    assert relaxed.window_keyframes == 8 and relaxed.tau > 1e20 and relaxed.voxel_size_m == 0.02
    assert MergeSchedule(replace(cfg, budget_merge=False), merge_fn).budget_config(7) is None
    assert not MergeSchedule(replace(cfg, merge_enabled=False)).available


def test_budget_limit_is_the_tighter_of_count_and_mbytes() -> None:
    g = _map(10)
    merge = MergeSchedule(MappingConfig(merge_enabled=False))
    gen = torch.Generator().manual_seed(0)
    assert BudgetStrategy(MappingConfig(), merge, gen).limit(g) == 0
    per = BudgetStrategy.trained_bytes_per_gaussian(g)
    cfg = MappingConfig(max_gaussians=1000, max_model_mbytes=100 * per / 2**20)
    assert BudgetStrategy(cfg, merge, gen).limit(g) == 100
    assert BudgetStrategy(replace(cfg, max_gaussians=50), merge, gen).limit(g) == 50


def test_budget_enforcement_prunes_least_opaque_old_gaussians_to_target_and_keeps_kept_rows() -> None:
    g = _map(40)
    with torch.no_grad():
        g.opacity_logits[:, 0] = torch.linspace(-4, 4, 40)
    g.created_iter[30:] = 1000  # young: judged last
    cfg = MappingConfig(max_gaussians=20, merge_enabled=False, prune_min_age_iters=200)
    b = BudgetStrategy(cfg, MergeSchedule(cfg), torch.Generator().manual_seed(0))
    ids = g.ids.clone()
    assert b.enforce(g, iteration=1000, newest_kf_id=0) == (0, 21)  # to 0.95 x 20 = 19
    assert len(g) == 19 and torch.equal(g.ids, torch.cat([ids[21:30], ids[30:]]))
    keep = torch.zeros(len(g), dtype=torch.bool)
    keep[:3] = True  # the three least opaque old ones are protected
    kept_ids = g.ids[:3].clone()
    assert b.shrink_to(g, 15, 1000, 0, keep=keep) == (0, 4)
    assert torch.isin(kept_ids, g.ids).all()
    assert b.enforce(g, 1000, 0) == (0, 0)  # within budget: nothing


def test_densify_clones_small_splits_large_and_prunes_transparent_old() -> None:
    cfg = MappingConfig(densify_grad_threshold=0.01, percent_dense=0.01, split_children=2,
                        prune_opacity=0.1, prune_min_age_iters=100, densify_start_iter=500,
                        densify_interval=100, densify_stop_iter=1000)
    d = DensifyStrategy(cfg, torch.Generator().manual_seed(0))
    assert [it for it in range(0, 1300, 100) if d.due(it)] == [500, 600, 700, 800, 900, 1000]
    g = _map(6)  # extent 1: clone at max scale <= 0.01 m
    with torch.no_grad():
        g.log_scales[3:] = math.log(0.05)  # rows 3..5 are large: split
        g.opacity_logits[5] = math.log(0.05 / 0.95)  # row 5 transparent: pruned (old enough)
    g.densify_grad_sum[:] = torch.tensor([1.0, 1.0, 0.0, 1.0, 0.0, 0.0])
    g.densify_count[:] = 1
    added, removed = d.densify_and_prune(g, iteration=500)
    # rows 0 and 1 clone (+2), row 3 splits into two children (+2, its parent removed), row 5 is
    # pruned: 6 + 2 + 2 - 1 - 1 = 8
    assert (added, removed) == (4, 2) and len(g) == 8
    assert float(g.densify_grad_sum.abs().sum()) == 0.0  # statistics restart after densification


def test_densify_within_a_budget_keeps_the_highest_gradients() -> None:
    cfg = MappingConfig(densify_grad_threshold=0.01, prune_opacity=0.0)
    d = DensifyStrategy(cfg, torch.Generator().manual_seed(0))
    g = _map(10)
    grads = torch.tensor([0.5, 0.2, 0.9, 0.0, 0.3, 0.0, 0.0, 0.0, 0.0, 0.0])
    high = grads >= 0.01
    kept = d.within_budget(g, high, grads, g.scales().max(dim=1).values, limit=12, iteration=0)
    assert torch.nonzero(kept).reshape(-1).tolist() == [0, 2]  # room for two clones: 0.9 and 0.5

"""The mapper's memory budget: hard cap on Gaussians / MiB, merge then prune, ids reported."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from frame_seeds import grid_seeds

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.mapping.mapper import GaussianMapper, MappingConfig
from memgs_ros.core.metrics.image import psnr
from memgs_ros.errors import ConfigError
from memgs_ros.io.synthetic import generate_frames, parse_spec


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(generate_frames(parse_spec("synthetic:w=64,h=48,n=30,seed=1")))[::10]  # 3 keyframes


# Densification from step 10 every 10 steps with a low gradient threshold: an unbudgeted map
# grows, so the budget's cap on densification is exercised.
GROWING = {"min_keyframes": 3, "pyramid_uses_per_level": 2, "densify_start_iter": 10, "densify_interval": 10,
           "densify_grad_threshold": 2e-5, "prune_min_age_iters": 5, "merge_enabled": True,
           "merge_start_iter": 15, "merge_interval": 15, "seed_opacity": 0.5}


def _mapper(frames: list[Frame], adds: list[int] | None = None, **overrides: object) -> GaussianMapper:
    m = GaussianMapper(MappingConfig(**{**GROWING, **overrides}))
    for i, f in enumerate(frames):
        p, c = grid_seeds(f)
        n = m.add_keyframe(i, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)
        if adds is not None:
            adds.append(n)
        limit = m.budget_gaussians
        assert limit == 0 or len(m.gmap) <= limit, (i, len(m.gmap), limit)
    return m


def _psnr(m: GaussianMapper, frames: list[Frame]) -> float:
    vals = []
    for f in frames:
        gt = torch.from_numpy(f.rgb).permute(2, 0, 1).float() / 255.0
        vals.append(psnr(m.render(f.T_wc_gt, f.camera).color.clamp(0, 1), gt))
    return float(np.mean(vals))


def _ids_never_come_back(m: GaussianMapper, gone: set[int], before: set[int]) -> set[int]:
    """Ids are issued once: every live id was issued, and no id that left the map returns.
    Adds the ids that left since ``before`` to ``gone``; returns the live ids."""
    live = set(m.gmap.ids.tolist())
    gone |= before - live
    assert not (live & gone)
    assert live <= set(range(m.gmap.next_id))
    return live


def test_config_validates_budget_fields() -> None:
    for bad in ({"max_gaussians": -1}, {"max_model_mbytes": -0.5}, {"max_model_mbytes": float("nan")},
                {"budget_target_fraction": 0.0}, {"budget_target_fraction": 1.5},
                {"budget_merge_voxel_scale": 0.5}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            MappingConfig(**bad)
    m = GaussianMapper(MappingConfig(max_gaussians=500, max_model_mbytes=1.0))
    assert m.trained_bytes_per_gaussian() == 944  # SH degree 3: 59 floats x 4 copies
    assert m.budget_gaussians == 500  # 1 MiB = 1110 Gaussians: the count is tighter
    assert GaussianMapper(MappingConfig(max_model_mbytes=0.1)).budget_gaussians == int(0.1 * 2**20 // 944)
    assert GaussianMapper(MappingConfig(max_model_mbytes=1e-9)).budget_gaussians == 1  # never "no budget"
    assert GaussianMapper(MappingConfig()).budget_gaussians == 0


def test_count_budget_holds_through_seeding_and_training(frames: list[Frame]) -> None:
    free = _mapper(frames)
    n_seeds = len(free.gmap)
    for _ in range(40):
        free.step()
    assert len(free.gmap) > n_seeds  # unbudgeted, this schedule grows the map
    budget = n_seeds // 2
    adds: list[int] = []
    m = _mapper(frames, adds, max_gaussians=budget)
    assert sum(adds) == n_seeds and len(m.gmap) <= budget
    gone: set[int] = set(range(m.gmap.next_id)) - set(m.gmap.ids.tolist())  # seeds over the budget
    live = _ids_never_come_back(m, gone, set())
    stats = []
    for _ in range(40):
        st = m.step()
        stats.append(st)
        assert st.num_gaussians == len(m.gmap) <= budget, st
        live = _ids_never_come_back(m, gone, live)
    # What seeding overflowed is reported by the first step: merged pairs and pruned Gaussians.
    assert stats[0].budget_merged + stats[0].budget_pruned >= n_seeds - budget
    assert sum(s.densified for s in stats) > 0  # densification still ran, within the room left


def test_overflow_merges_duplicates_first_and_is_reported_exactly(frames: list[Frame]) -> None:
    # The first view seeded a second time: every seed has an exact twin, which the budget's
    # merge pass fuses (the scene's own seeds are too sparse for the 2 cm voxel to pair them).
    adds: list[int] = []
    m = _mapper([*frames, frames[0]], adds, max_gaussians=600, densify_start_iter=10_000)
    n_after_seeding = len(m.gmap)
    assert n_after_seeding <= 600 and sum(adds) > 600
    first = m.step()
    # Each merged pair shrank the map by one, each pruned Gaussian by one.
    assert first.budget_merged + first.budget_pruned == sum(adds) - n_after_seeding
    assert first.budget_merged == adds[-1] and first.budget_pruned == sum(adds) - adds[-1] - int(0.95 * 600)
    assert m.step().budget_merged == 0  # reported once


def test_deferred_budget_is_enforced_by_the_next_step(frames: list[Frame]) -> None:
    """An insert thread that must keep up can leave the budget to training: the map overshoots
    by the new keyframe's seeds until the next step, which reports what it removed."""
    m = GaussianMapper(MappingConfig(**{**GROWING, "max_gaussians": 300, "densify_start_iter": 10_000}))
    added = 0
    for i, f in enumerate(frames):
        p, c = grid_seeds(f)
        added += m.add_keyframe(i, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c, enforce_budget=False)
    assert added > 300 and len(m.gmap) == added  # nothing enforced yet
    st = m.step()
    assert st is not None and len(m.gmap) == st.num_gaussians <= 300
    assert st.budget_merged + st.budget_pruned == added - len(m.gmap)


def test_mbyte_budget_bounds_model_memory(frames: list[Frame]) -> None:
    mib = 250 * 944 / 2**20
    m = _mapper(frames, max_model_mbytes=mib)
    assert m.budget_gaussians == 250
    for _ in range(30):
        m.step()
        # Bounded even if every parameter had its gradient and Adam moments (944 B each).
        assert m.gmap.memory_bytes().total <= len(m.gmap) * 944 <= mib * 2**20
    assert len(m.gmap) > 0.9 * 250  # the budget binds (seeds and densification exceed it)


def test_prune_order_old_by_opacity_then_young_and_optimiser_rows_aligned() -> None:
    cam = PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0)
    m = GaussianMapper(MappingConfig(min_keyframes=1, merge_enabled=False, scene_extent=1.0, max_gaussians=10,
                                     budget_target_fraction=0.6, prune_min_age_iters=100))
    g = m.gmap
    m.add_keyframe(0, 0, np.eye(4), np.zeros((24, 32, 3), np.uint8), None, cam)
    n = 12
    means = torch.stack([torch.linspace(-1, 1, n), torch.zeros(n), torch.full((n,), 3.0)], 1)
    opac = torch.linspace(0.05, 0.95, n)
    g.add(means, torch.log(torch.full((n, 3), 0.02)), torch.tensor([[1.0, 0, 0, 0]] * n),
          torch.logit(opac)[:, None], torch.zeros(n, 1, 3), None, 0, 0)
    m.iteration = 150
    g.created_iter[[1, 2]] = 100  # young: too new to judge by opacity, kept while older rows can go
    # Distinct Adam moments per row, to check they stay with their rows.
    g.optimizer.state[g.opacity_logits] = {"step": torch.tensor(1.0), "exp_avg": opac[:, None].clone(),
                                           "exp_avg_sq": opac[:, None].clone()}
    merged, pruned = m.enforce_budget()
    assert (merged, pruned) == (0, 6)  # down to 0.6 x 10
    kept = [1, 2, 8, 9, 10, 11]  # old rows 0, 3..7 had the lowest opacities
    assert g.ids.tolist() == kept
    assert torch.equal(g.optimizer.state[g.opacity_logits]["exp_avg"].reshape(-1), opac[kept])
    assert m.enforce_budget() == (0, 0)  # within budget: nothing
    # Past every old row, young ones go at random, not by opacity.
    m2 = GaussianMapper(MappingConfig(min_keyframes=1, merge_enabled=False, max_gaussians=400))
    m2.gmap.add(torch.randn(1000, 3), torch.full((1000, 3), -3.0), torch.tensor([[1.0, 0, 0, 0]] * 1000),
                torch.linspace(-3, 3, 1000)[:, None], torch.zeros(1000, 1, 3), None, 0, 0)
    m2.enforce_budget()
    survivors = m2.gmap.ids
    assert len(survivors) == 380 and 300 < int((survivors < 500).sum()) * 2 < 460  # both halves thinned alike


def test_densification_capped_to_room_highest_gradient_first() -> None:
    cam = PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0)
    m = GaussianMapper(MappingConfig(min_keyframes=1, merge_enabled=False, scene_extent=1.0,
                                     prune_min_age_iters=0, prune_opacity=0.01, max_gaussians=6))
    g = m.gmap
    m.add_keyframe(0, 0, np.eye(4), np.zeros((24, 32, 3), np.uint8), None, cam)
    means = torch.tensor([[0.0, 0, 2], [0.5, 0, 2], [0.0, 0.5, 2], [0.5, 0.5, 2]])
    log_s = torch.log(torch.tensor([[0.005] * 3, [0.1, 0.05, 0.02], [0.005] * 3, [0.005] * 3]))
    g.add(means, log_s, torch.tensor([[1.0, 0, 0, 0]] * 4), torch.zeros(4, 1), torch.zeros(4, 1, 3), None, 0, 0)
    # Room 2: the split (grad 3, +1) and the strongest clone (grad 2, +1) fit; the clone at 1 does not.
    g.densify_grad_sum[:] = torch.tensor([1.0, 3.0, 2.0, 1e-6])
    g.densify_count[:] = 1
    added, removed = m.densify_and_prune()
    assert (added, removed) == (3, 1) and len(g) == 6
    assert g.ids.tolist() == [0, 2, 3, 4, 5, 6]  # row 1 split into 5, 6; row 2 cloned as 4
    assert torch.equal(g.means[3], means[2])
    assert m.densify_and_prune() == (0, 0)  # full: nothing grows (gradients were reset anyway)


def test_budget_costs_little_quality(frames: list[Frame]) -> None:
    # No densification: the budget has to thin the seeds to half, and training cannot make up
    # for a badly chosen half (removing the smallest seeds first, i.e. whole near surfaces,
    # scored 17.1 dB here against 20.5 unbudgeted).
    free = _mapper(frames, densify_start_iter=10_000)
    budget = len(free.gmap) // 2
    m = _mapper(frames, max_gaussians=budget, densify_start_iter=10_000)
    p0 = _psnr(m, frames)
    for mapper in (free, m):
        for _ in range(50):
            mapper.step()
    p_free, p_budget = _psnr(free, frames), _psnr(m, frames)
    assert len(m.gmap) <= budget
    assert p_budget > p0 + 1.5, (p0, p_budget)
    assert p_budget > p_free - 1.2, (p_free, p_budget)


def test_zero_budget_and_unbinding_budget_change_nothing(frames: list[Frame]) -> None:
    a = _mapper(frames)
    b = _mapper(frames, max_gaussians=10**9)
    for _ in range(35):  # spans densify, prune and merge iterations
        sa, sb = a.step(), b.step()
        assert (sa.num_gaussians, sa.densified, sa.pruned, sa.merged_removed) == \
            (sb.num_gaussians, sb.densified, sb.pruned, sb.merged_removed)
        assert sa.budget_merged == sa.budget_pruned == sb.budget_merged == sb.budget_pruned == 0
    for name, p in a.gmap.params().items():
        assert torch.equal(p, b.gmap.params()[name]), name
    assert torch.equal(a.gmap.ids, b.gmap.ids)


def test_mapper_memory_cap_drops_keyframes_then_shrinks_the_map() -> None:
    # 8 keyframes at 64x48 (9.2 KB each as uint8 colour + float16 depth) and their seeds. The cap
    # is set between "every keyframe and a smaller map" and the unbounded account, so the
    # mapper drops redundant keyframes first (down to min_keyframes) and then holds the map
    # below what is left; the accounted total stays under the cap after every insert and step.
    many = list(generate_frames(parse_spec("synthetic:w=64,h=48,n=40,seed=1")))[::5]
    base = {**GROWING, "min_keyframes": 3}
    free = _mapper(many, **base)
    acc = free.memory_account()
    assert acc.keyframes == 8 * (3 + 2) * 64 * 48 and acc.total == acc.model + acc.keyframes + acc.step_buffers + acc.delta
    assert acc.delta == len(free.gmap) * 3 * 236  # the delta mirror and one full-map message
    per_g = free.trained_bytes_per_gaussian()
    cap_bytes = acc.total - acc.keyframes // 2 - 100 * per_g  # needs both levers
    # Free-running inserts defer the Gaussian budget to the next step, but not the memory cap.
    cfg = {**base, "max_mapper_mbytes": cap_bytes / 2**20}
    m = GaussianMapper(MappingConfig(**cfg))
    for i, f in enumerate(many):
        p, c = grid_seeds(f)
        m.add_prepared_keyframe(m.prepare_keyframe(i, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera), p, c,
                                enforce_budget=False)
        assert m.memory_account().total <= cap_bytes, i
    assert 3 <= len(m.keyframes) < 8 and m.keyframes_dropped == 8 - len(m.keyframes)
    assert len(m.gmap) < len(free.gmap)
    for _ in range(40):
        m.step()
        assert m.memory_account().total <= cap_bytes
    assert m.budget_gaussians > 0
    with pytest.raises(ConfigError, match="max_mapper_mbytes"):
        MappingConfig(max_mapper_mbytes=-1.0)

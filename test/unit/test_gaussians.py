"""GaussianMap: parameters, Adam state and side arrays stay in step; ids; memory; records."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from memgs_ros.core.gaussians.gaussian_map import (
    PARAM_NAMES,
    SH_C0,
    SIDE_NAMES,
    GaussianMap,
    GaussianRecords,
    num_sh_rest,
    render_tensors,
)
from memgs_ros.errors import DataError


def _map_with_points(n: int, seed: int = 0, sh: int = 3) -> GaussianMap:
    rng = np.random.default_rng(seed)
    g = GaussianMap(sh)
    g.add_from_points(rng.uniform(-1, 1, (n, 3)), rng.uniform(0, 1, (n, 3)), keyframe_id=0, iteration=0)
    return g


def _train_step(g: GaussianMap, seed: int = 0) -> None:
    """A loss touching every parameter with row-dependent gradients, then one Adam step."""
    torch.manual_seed(seed)
    loss = sum((p * torch.randn_like(p)).sum() for p in g.params().values())
    loss.backward()
    g.optimizer_step()


def test_add_from_points_initialisation_matches_3dgs() -> None:
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [10, 10, 10]], dtype=np.float64)
    cols = np.array([[0.5, 0.0, 1.0]] * 5)
    g = GaussianMap(3)
    ids = g.add_from_points(pts, cols, keyframe_id=7, iteration=3)
    assert ids.tolist() == [0, 1, 2, 3, 4]
    # Point 0: neighbours at distances 1, 2, 3 -> mean sq = 14/3.
    assert g.log_scales[0].tolist() == pytest.approx([math.log(math.sqrt(14 / 3))] * 3, rel=1e-6)
    assert torch.equal(g.quats_wxyz[0], torch.tensor([1.0, 0, 0, 0]))
    assert float(torch.sigmoid(g.opacity_logits[0].detach())) == pytest.approx(0.1, rel=1e-6)
    assert g.sh_dc[0, 0].tolist() == pytest.approx([0.0, -0.5 / SH_C0, 0.5 / SH_C0], rel=1e-6)
    assert g.sh_rest.shape == (5, 15, 3) and float(g.sh_rest.detach().abs().sum()) == 0.0
    assert g.keyframe_ids.tolist() == [7] * 5 and g.created_iter.tolist() == [3] * 5


def test_add_from_points_uses_existing_map_for_scale_and_clamps_duplicates() -> None:
    g = GaussianMap(0)
    g.add_from_points(np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]]), np.zeros((3, 3)), 0, 0)
    ids = g.add_from_points(np.array([[0.0, 0, 0.1]]), np.zeros((1, 3)), 1, 0)
    # The lone new point is sized by its 3 neighbours in the existing map, not by a default.
    d2 = np.mean([0.01, 0.02, 0.02])
    assert float(g.log_scales[3, 0].detach()) == pytest.approx(math.log(math.sqrt(d2)), rel=1e-5)
    g.add_from_points(np.zeros((4, 3)) + 5.0, np.zeros((4, 3)), 2, 0)  # identical points
    assert float(g.log_scales[-1, 0].detach()) == pytest.approx(math.log(math.sqrt(1e-7)), rel=1e-5)
    assert ids.tolist() == [3]


def test_remove_keeps_params_adam_state_and_side_arrays_in_step() -> None:
    g = _map_with_points(20)
    _train_step(g)
    g.densify_grad_sum += torch.arange(20, dtype=torch.float32)
    g.merge_count += torch.arange(20)
    before = {n: getattr(g, n).detach().clone() for n in PARAM_NAMES}
    moments = {n: {k: g.optimizer.state[getattr(g, n)][k].clone() for k in ("exp_avg", "exp_avg_sq")}
               for n in PARAM_NAMES}
    side = {n: getattr(g, n).clone() for n in SIDE_NAMES}
    param_objects = [id(p) for p in g.params().values()]
    mask = torch.zeros(20, dtype=torch.bool)
    mask[[0, 5, 6, 19]] = True
    removed = g.remove(mask)
    assert removed.tolist() == [0, 5, 6, 19]
    assert len(g) == 16
    for n in PARAM_NAMES:
        assert torch.equal(getattr(g, n).detach(), before[n][~mask])
        for k in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(g.optimizer.state[getattr(g, n)][k], moments[n][k][~mask])
    for n in SIDE_NAMES:
        assert torch.equal(getattr(g, n), side[n][~mask]), n
    # Same Parameter objects: the optimiser was edited, not rebuilt.
    assert [id(p) for p in g.params().values()] == param_objects
    assert all(group["params"][0] is getattr(g, group["name"]) for group in g.optimizer.param_groups)


def test_add_appends_zero_moments_and_training_continues() -> None:
    g = _map_with_points(10)
    _train_step(g)
    old = g.optimizer.state[g.means]["exp_avg"].clone()
    assert float(old.abs().sum()) > 0
    ids = g.add_from_points(np.random.default_rng(1).uniform(size=(5, 3)), np.ones((5, 3)) * 0.2, 3, 9)
    assert ids.tolist() == list(range(10, 15))
    for n in PARAM_NAMES:
        st = g.optimizer.state[getattr(g, n)]
        assert st["exp_avg"].shape[0] == 15 and st["exp_avg_sq"].shape[0] == 15
        assert float(st["exp_avg"][10:].abs().sum()) == 0.0 and float(st["exp_avg_sq"][10:].abs().sum()) == 0.0
    assert torch.equal(g.optimizer.state[g.means]["exp_avg"][:10], old)
    assert g.keyframe_ids[10:].tolist() == [3] * 5 and g.created_iter[10:].tolist() == [9] * 5
    _train_step(g, seed=1)  # shapes consistent for Adam
    assert float(g.optimizer.state[g.means]["exp_avg"][10:].abs().sum()) > 0


def test_ids_are_never_reused_and_index_of() -> None:
    g = _map_with_points(6)
    g.remove(torch.tensor([False, False, False, False, True, True]))  # drop the newest ids 4, 5
    new = g.add_from_points(np.random.default_rng(2).uniform(size=(2, 3)), np.zeros((2, 3)), 1, 0)
    assert new.tolist() == [6, 7]
    assert len(set(g.ids.tolist())) == len(g)
    assert g.index_of(torch.tensor([7, 4, 0, 3, 100])).tolist() == [5, -1, 0, 3, -1]
    assert GaussianMap(0).index_of(torch.tensor([1])).tolist() == [-1]


def test_reset_rows_zeroes_moments_and_accumulators() -> None:
    g = _map_with_points(5)
    _train_step(g)
    g.merge_grad_sum += 1.0
    g.merge_count += 2
    g.reset_rows(torch.tensor([1, 3]))
    st = g.optimizer.state[g.log_scales]
    assert float(st["exp_avg"][[1, 3]].abs().sum()) == 0.0 and float(st["exp_avg"][[0, 2, 4]].abs().sum()) > 0
    assert g.merge_count.tolist() == [2, 0, 2, 0, 2]
    assert g.merge_grad_mean().tolist() == pytest.approx([0.5, 0.0, 0.5, 0.0, 0.5])


@pytest.mark.parametrize("sh,per_param,per_train", [(3, 236, 944), (0, 56, 224)])
def test_memory_bytes_match_reference(sh: int, per_param: int, per_train: int) -> None:
    g = _map_with_points(100, sh=sh)
    rep = g.memory_bytes()
    assert (rep.params, rep.grads, rep.optimizer) == (100 * per_param, 0, 0)
    _train_step(g)
    loss = sum(p.sum() for p in g.params().values())
    loss.backward()
    rep = g.memory_bytes()
    assert rep.params == 100 * per_param and rep.grads == 100 * per_param
    assert rep.optimizer == 100 * 2 * per_param and rep.total == 100 * per_train


def test_accumulate_stats_scales_2d_gradient_to_ndc_and_counts_visible() -> None:
    g = _map_with_points(3)
    g.means.grad = torch.tensor([[3.0, 4.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    vis = torch.tensor([True, False, True])
    g.accumulate_stats(torch.tensor([[1.0, 0.0], [1.0, 1.0], [0.0, 0.01]]), vis,
                       torch.tensor([5, 9, 2]), width=100, height=50)
    assert g.densify_grad_sum.tolist() == pytest.approx([50.0, 0.0, 0.25])
    assert g.densify_count.tolist() == [1, 0, 1]
    assert g.merge_grad_mean().tolist() == pytest.approx([5.0, 0.0, 2.0])  # unseen -> 0
    assert g.max_radii2d.tolist() == [5.0, 0.0, 2.0]


def test_position_lr_scaled_by_extent_and_decays() -> None:
    from memgs_ros.core.gaussians.learning_rates import GaussianLearningRates

    g = GaussianMap(0, lrs=GaussianLearningRates(means_decay=True, means_decay_steps=100),
                    spatial_lr_scale=2.0)
    assert g.update_learning_rate(0) == pytest.approx(3.2e-4)
    assert g.update_learning_rate(50) == pytest.approx(math.sqrt(3.2e-4 * 3.2e-6))
    assert g.update_learning_rate(1000) == pytest.approx(3.2e-6)
    lrs = {grp["name"]: grp["lr"] for grp in g.optimizer.param_groups}
    assert lrs["sh_rest"] == pytest.approx(0.0025 / 20) and lrs["opacity_logits"] == 0.05
    assert all(grp["eps"] == 1e-15 for grp in g.optimizer.param_groups)


def test_records_round_trip_exact_and_channel_major() -> None:
    g = _map_with_points(8, sh=2)
    with torch.no_grad():
        g.sh_rest.copy_(torch.randn_like(g.sh_rest))
        g.quats_wxyz.mul_(3.0)  # unnormalised quaternions survive
    rec = g.to_records()
    assert rec.f_rest.shape == (8, 45) and num_sh_rest(2) == 8
    # Channel-major: f_rest[:, c*15 + k] = sh_rest[:, k, c]; zeros beyond degree 2.
    assert rec.f_rest[3, 15 + 4] == g.sh_rest[3, 4, 1].item()
    assert np.all(rec.f_rest.reshape(8, 3, 15)[:, :, 8:] == 0)
    g2 = GaussianMap.from_records(rec, max_sh_degree=2)
    rec2 = g2.to_records()
    for f in ("ids", "xyz", "f_dc", "f_rest", "opacity", "scale", "rot"):
        assert np.array_equal(getattr(rec, f), getattr(rec2, f)), f
    assert g2.next_id == 8
    assert g2.add_from_points(np.ones((1, 3)), np.ones((1, 3)), 0, 0).tolist() == [8]


def test_records_validate_shapes_and_from_records_sorts_ids() -> None:
    with pytest.raises(DataError, match="xyz"):
        GaussianRecords(np.zeros(2, np.int64), np.zeros((3, 3), np.float32), np.zeros((2, 3), np.float32),
                        np.zeros((2, 45), np.float32), np.zeros(2, np.float32), np.zeros((2, 3), np.float32),
                        np.zeros((2, 4), np.float32))
    rec = _map_with_points(4).to_records()
    shuffled = GaussianRecords.from_arrays(rec.ids[::-1] + 10, rec.xyz[::-1], rec.f_dc[::-1], rec.f_rest[::-1],
                                           rec.opacity[::-1], rec.scale[::-1], rec.rot[::-1])
    g = GaussianMap.from_records(shuffled)
    assert g.ids.tolist() == [10, 11, 12, 13]
    assert np.array_equal(g.to_records().xyz, rec.xyz)
    dup = GaussianRecords.from_arrays(np.array([1, 1]), *(np.zeros((2,) + s) for s in [(3,), (3,), (45,), (), (3,), (4,)]))
    with pytest.raises(DataError, match="unique"):
        GaussianMap.from_records(dup)


def test_render_tensors_match_a_map_built_from_the_records() -> None:
    # The merger renders from records without a GaussianMap (no gradients or Adam state): the
    # inputs must equal the map's own tensors row for row, SH layout included.
    g = _map_with_points(50, seed=3)
    with torch.no_grad():
        g.sh_rest.normal_(0, 0.1)  # non-zero higher bands, so a wrong SH layout shows
    rec = g.to_records()
    ref = GaussianMap.from_records(rec, max_sh_degree=3)
    got = render_tensors(rec)
    want = (ref.means, ref.quats_wxyz, ref.log_scales, ref.opacity_logits, ref.sh_dc, ref.sh_rest)
    for a, b in zip(got, want):
        assert a.shape == b.shape and torch.equal(a, b.detach())
        assert not a.requires_grad
    assert rec.nbytes == 50 * (8 + 4 * (3 + 3 + 45 + 1 + 3 + 4))

"""Voxel merge (MemGS Sec. II-D): W2 algebra, pair generation, gating, covariance merge, surgery."""
from __future__ import annotations

import itertools
import math

import pytest
import torch

from memgs_ros.core.gaussians.gaussian_map import GaussianMap
from memgs_ros.core.merge.voxel_merge import (
    CHI2_3DOF_95,
    MergeConfig,
    candidate_mask,
    mahalanobis_sq,
    merge_covariance,
    merge_pass,
    merged_mean,
    select_min_pair_per_voxel,
    voxel_keys,
    voxel_pairs,
)
from memgs_ros.core.merge.wasserstein import (
    _w2_sq_eigh,
    covariance_from_scale_quat,
    precision_from_scale_quat,
    slerp_wxyz,
    w2_barycenter_fixed_point,
    w2_sq,
    w2_sq_factored,
)
from memgs_ros.errors import ConfigError

F64 = torch.float64


def _random_factors(n: int, gen: torch.Generator, spread: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    scales = torch.exp(torch.randn(n, 3, generator=gen, dtype=F64) * spread)
    quats = torch.randn(n, 4, generator=gen, dtype=F64)
    return scales, quats


def _sqrtm(A: torch.Tensor) -> torch.Tensor:
    e, V = torch.linalg.eigh(A)
    return (V * e.clamp_min(0).sqrt()[:, None, :]) @ V.transpose(-1, -2)


# ---------------------------------------------------------------------------- W2 algebra
@pytest.mark.parametrize("n", [0, 1, 7, 300])
def test_w2_sq_matches_eigh_twin_forward_and_backward(n: int) -> None:
    gen = torch.Generator().manual_seed(n)
    A = covariance_from_scale_quat(*_random_factors(n, gen)).requires_grad_(True)
    B = covariance_from_scale_quat(*_random_factors(n, gen)).requires_grad_(True)
    fast, ref = w2_sq(A, B), _w2_sq_eigh(A, B)
    assert fast.shape == (n,)
    torch.testing.assert_close(fast, ref, rtol=1e-8, atol=1e-8)
    if n == 0:
        return
    cot = torch.randn(n, generator=gen, dtype=F64)
    # only the symmetric part of a matrix gradient is meaningful for symmetric inputs
    g_fast = [0.5 * (g + g.transpose(-1, -2)) for g in torch.autograd.grad(fast, (A, B), cot)]
    g_ref = [0.5 * (g + g.transpose(-1, -2)) for g in torch.autograd.grad(ref, (A, B), cot)]
    for gf, gr in zip(g_fast, g_ref):
        torch.testing.assert_close(gf, gr, rtol=1e-6, atol=1e-8)


def test_w2_sq_factored_matches_dense() -> None:
    gen = torch.Generator().manual_seed(1)
    sa, qa = _random_factors(50, gen)
    sb, qb = _random_factors(50, gen)
    dense = w2_sq(covariance_from_scale_quat(sa, qa), covariance_from_scale_quat(sb, qb))
    torch.testing.assert_close(w2_sq_factored(sa, qa, sb, qb), dense, rtol=1e-9, atol=1e-10)


def test_w2_gradient_finite_and_zero_at_equal_covariances() -> None:
    """Equal covariances and repeated eigenvalues: exactly where eigh gradients blow up."""
    gen = torch.Generator().manual_seed(2)
    s, q = _random_factors(5, gen)
    s[0] = 0.7  # isotropic: all eigenvalues equal
    S = covariance_from_scale_quat(s, q)
    E = torch.randn(5, 3, 3, generator=gen, dtype=F64)
    E = E + E.transpose(-1, -2)  # symmetric direction
    t = torch.zeros(5, dtype=F64, requires_grad=True)
    val = w2_sq(S + t[:, None, None] * E, S)
    (g,) = torch.autograd.grad(val.sum(), t)
    assert torch.isfinite(g).all()
    torch.testing.assert_close(val.detach(), torch.zeros(5, dtype=F64), atol=1e-9, rtol=0)
    torch.testing.assert_close(g, torch.zeros(5, dtype=F64), atol=1e-6, rtol=0)


def test_w2_closed_form_isotropic() -> None:
    """W2(aI, bI)^2 = 3 (sqrt a - sqrt b)^2."""
    eye = torch.eye(3, dtype=F64).expand(4, 3, 3)
    a = torch.tensor([1.0, 4.0, 0.01, 9.0], dtype=F64)
    b = torch.tensor([4.0, 4.0, 0.04, 1.0], dtype=F64)
    val = w2_sq(a[:, None, None] * eye, b[:, None, None] * eye)
    torch.testing.assert_close(val, 3 * (a.sqrt() - b.sqrt()) ** 2)


def test_slerp_takes_short_arc_and_hits_midpoint() -> None:
    half = math.pi / 4  # rotations of 0 and pi/2 about z
    q0 = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64)
    q1 = torch.tensor([[math.cos(half), 0.0, 0.0, math.sin(half)]], dtype=F64)
    want = torch.tensor([[math.cos(half / 2), 0.0, 0.0, math.sin(half / 2)]], dtype=F64)
    torch.testing.assert_close(slerp_wxyz(q0, q1, 0.5), want)
    mid = slerp_wxyz(q0, -q1, 0.5)  # -q1 is the same rotation: must give the same midpoint up to sign
    torch.testing.assert_close(mid * torch.sign(mid[:, :1]), want)
    torch.testing.assert_close(slerp_wxyz(q0, q0, 0.5), q0)


# ------------------------------------------------------------------------- pure merge maths
def test_merged_mean_equals_formula() -> None:
    gen = torch.Generator().manual_seed(3)
    si, qi = _random_factors(20, gen, 0.5)
    sj, qj = _random_factors(20, gen, 0.5)
    mu_i = torch.randn(20, 3, generator=gen, dtype=F64)
    mu_j = torch.randn(20, 3, generator=gen, dtype=F64)
    Pi, Pj = precision_from_scale_quat(si, qi), precision_from_scale_quat(sj, qj)
    Si, Sj = covariance_from_scale_quat(si, qi), covariance_from_scale_quat(sj, qj)
    torch.testing.assert_close(Pi, torch.linalg.inv(Si))
    want = (torch.linalg.inv(torch.linalg.inv(Si) + torch.linalg.inv(Sj))
            @ (torch.linalg.inv(Si) @ mu_i[:, :, None] + torch.linalg.inv(Sj) @ mu_j[:, :, None]))[:, :, 0]
    torch.testing.assert_close(merged_mean(mu_i, Pi, mu_j, Pj), want)


def test_mahalanobis_sq_axis_aligned() -> None:
    s = torch.tensor([[0.5, 2.0, 1.0]], dtype=F64)
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64)
    d = mahalanobis_sq(torch.zeros(1, 3, dtype=F64), precision_from_scale_quat(s, q),
                       torch.tensor([[1.0, 2.0, 3.0]], dtype=F64))
    torch.testing.assert_close(d, torch.tensor([4.0 + 1.0 + 9.0], dtype=F64))


@pytest.mark.parametrize("parametrization", ["sqrt_cov", "quat_scale"])
def test_equal_covariances_merge_to_the_same(parametrization: str) -> None:
    gen = torch.Generator().manual_seed(4)
    s = 0.004 * torch.exp(torch.randn(30, 3, generator=gen, dtype=F64) * 0.5)
    q = torch.randn(30, 4, generator=gen, dtype=F64)
    qk, sk, _ = merge_covariance(q, s, -q, s, parametrization=parametrization)  # -q: same rotation
    S, K = covariance_from_scale_quat(s, q), covariance_from_scale_quat(sk, qk)
    rel = (K - S).norm(dim=(1, 2)) / S.norm(dim=(1, 2))
    assert float(rel.max()) < 1e-4


@pytest.mark.parametrize("parametrization", ["sqrt_cov", "quat_scale"])
def test_commuting_covariances_sqrt_is_mean_of_sqrts(parametrization: str) -> None:
    """Same rotation, different scales: the W2 barycentre's sqrt-covariance is (Si^1/2 + Sj^1/2)/2."""
    gen = torch.Generator().manual_seed(5)
    q = torch.randn(40, 4, generator=gen, dtype=F64)
    si = 0.005 * torch.exp(torch.randn(40, 3, generator=gen, dtype=F64) * 0.6)
    sj = 0.005 * torch.exp(torch.randn(40, 3, generator=gen, dtype=F64) * 0.6)
    qk, sk, _ = merge_covariance(q, si, q, sj, parametrization=parametrization)
    got = _sqrtm(covariance_from_scale_quat(sk, qk))
    want = 0.5 * (_sqrtm(covariance_from_scale_quat(si, q)) + _sqrtm(covariance_from_scale_quat(sj, q)))
    scale = want.norm(dim=(1, 2))
    assert float(((got - want).norm(dim=(1, 2)) / scale).max()) < 1e-4


def test_general_pairs_match_fixed_point_barycentre_unit_quats_positive_scales() -> None:
    gen = torch.Generator().manual_seed(6)
    n = 400
    base = 0.005 * torch.exp(torch.randn(n, 3, generator=gen) * 0.5)
    si = base * torch.exp(torch.randn(n, 3, generator=gen) * 0.2)
    sj = base * torch.exp(torch.randn(n, 3, generator=gen) * 0.2)
    qi = torch.randn(n, 4, generator=gen)
    qj = qi + 0.3 * torch.randn(n, 4, generator=gen)
    qk, sk, n_iter = merge_covariance(qi, si, qj, sj)  # float32 in, float32 out
    assert qk.dtype == torch.float32 and sk.dtype == torch.float32 and 1 <= n_iter <= 15
    torch.testing.assert_close(qk.norm(dim=1), torch.ones(n), atol=1e-6, rtol=0)
    assert bool((qk[:, 0] >= 0).all()) and bool((sk > 0).all())
    ref = w2_barycenter_fixed_point(covariance_from_scale_quat(si.double(), qi.double()),
                                    covariance_from_scale_quat(sj.double(), qj.double()))
    got = covariance_from_scale_quat(sk.double(), qk.double())
    rel = (got - ref).norm(dim=(1, 2)) / ref.norm(dim=(1, 2))
    assert float(rel.median()) < 1e-4 and float(rel.max()) < 1e-2


def test_merge_covariance_empty_and_bad_parametrization() -> None:
    q, s, n = merge_covariance(torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3))
    assert q.shape == (0, 4) and s.shape == (0, 3) and n == 0
    with pytest.raises(ConfigError, match="parametrization"):
        merge_covariance(torch.ones(1, 4), torch.ones(1, 3), torch.ones(1, 4), torch.ones(1, 3),
                         parametrization="euler")  # type: ignore[arg-type]


# --------------------------------------------------------------------------- candidates / voxels
def test_candidate_mask() -> None:
    grad = torch.tensor([0.0, 5e-4, 2e-3, 0.0, 0.0])
    kf = torch.tensor([10, 10, 10, 4, 11])
    got = candidate_mask(grad, kf, tau=1e-3, k_min=5, k_max=10)
    assert got.tolist() == [True, True, False, False, False]


def test_voxel_keys_equal_iff_same_voxel() -> None:
    gen = torch.Generator().manual_seed(7)
    pts = torch.rand(2000, 3, generator=gen) * 0.2 - 0.1
    keys = voxel_keys(pts, 0.01)
    cells = torch.round(pts.double() / 0.01).long()
    same_key = keys[:, None] == keys[None, :]
    same_cell = (cells[:, None, :] == cells[None, :, :]).all(-1)
    assert torch.equal(same_key, same_cell)
    far = torch.tensor([[0.0, 0.0, 0.0], [1e5, 0.0, 0.0], [1e5, 0.0, 0.001]])  # > 2^21 voxels: fallback
    k = voxel_keys(far, 0.01)
    assert k[1] == k[2] and k[0] != k[1]


def _brute_pairs(keys: list[int], order: list[int], cap: int) -> set[tuple[int, int]]:
    out = set()
    for key in set(keys):
        members = sorted((o, n) for n, (k, o) in enumerate(zip(keys, order)) if k == key)[:cap]
        for (oa, a), (ob, b) in itertools.combinations(members, 2):
            out.add((a, b))
    return out


@pytest.mark.parametrize("cap", [2, 3, 32])
def test_voxel_pairs_match_brute_force(cap: int) -> None:
    gen = torch.Generator().manual_seed(cap)
    keys = torch.randint(0, 12, (60,), generator=gen)
    order = torch.randperm(60, generator=gen) * 3 + 5  # unique, not sorted
    pairs = voxel_pairs(keys, order, cap)
    got = set(zip(pairs.i.tolist(), pairs.j.tolist()))
    assert len(got) == pairs.i.shape[0]  # no duplicates
    assert got == _brute_pairs(keys.tolist(), order.tolist(), cap)
    assert bool((order[pairs.i] < order[pairs.j]).all())
    assert bool((keys[pairs.i] == keys[pairs.j]).all())
    # compact voxel index: same index <=> same key
    assert torch.equal(pairs.voxel[:, None] == pairs.voxel[None, :], keys[pairs.i][:, None] == keys[pairs.i][None, :])
    assert pairs.n_voxels == int(torch.unique(keys).shape[0])


def test_voxel_pairs_empty_and_singletons() -> None:
    p = voxel_pairs(torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64))
    assert p.i.numel() == 0 and p.n_voxels == 0
    p = voxel_pairs(torch.arange(5), torch.arange(5))
    assert p.i.numel() == 0 and p.n_voxels == 5


def test_select_min_pair_per_voxel() -> None:
    d2 = torch.tensor([3.0, 1.0, 1.0, 9.0, float("nan"), 0.5])
    vox = torch.tensor([0, 0, 0, 2, 2, 3])
    got = select_min_pair_per_voxel(d2, vox, 4)
    assert got.tolist() == [1, 3, 5]  # tie -> lowest index; NaN never beats a number; voxel 1 empty


# ----------------------------------------------------------------------------------- merge_pass
def _make_map(rows: list[dict], sh_degree: int = 1) -> GaussianMap:
    """One Gaussian per row: pos (m), scale (m, isotropic unless a triple), kf, rgb, grad."""
    gmap = GaussianMap(max_sh_degree=sh_degree)
    for r in rows:
        s = r.get("scale", 0.003)
        s = torch.tensor([s, s, s] if isinstance(s, float) else s, dtype=torch.float32)
        q = torch.tensor(r.get("quat", [1.0, 0.0, 0.0, 0.0]), dtype=torch.float32)
        rgb = torch.tensor(r.get("rgb", [0.5, 0.5, 0.5]), dtype=torch.float32)
        gmap.add(torch.tensor([r["pos"]], dtype=torch.float32), s.log()[None], q[None],
                 torch.tensor([[r.get("opacity", 0.0)]]), rgb.reshape(1, 1, 3),
                 torch.full((1, gmap.k_rest, 3), 0.1), r.get("kf", 100), iteration=0)
    grads = torch.tensor([r.get("grad", 0.0) for r in rows])
    gmap.merge_grad_sum += grads * 4
    gmap.merge_count += torch.where(grads > 0, 4, 0)
    return gmap


def _ids_of_pairs(res) -> set[frozenset[int]]:
    ids = res.removed_ids.reshape(-1, 2).tolist()
    return {frozenset(p) for p in ids}


def test_gating_merges_only_the_eligible_pair() -> None:
    v = 0.01
    rows = [
        # 0, 1: eligible (d2 = (0.002 / 0.003)^2 = 0.44) -> merged
        {"pos": [0.0, 0.0, 0.0]}, {"pos": [0.002, 0.0, 0.0]},
        # 2, 3: same voxel but d2 = (0.004 / 0.001)^2 = 16 > 7.815
        {"pos": [1.0, 0.0, 0.0], "scale": 0.001}, {"pos": [1.004, 0.0, 0.0], "scale": 0.001},
        # 4, 5: tiny d2 but straddling a voxel boundary (round(0.49) = 0, round(0.51) = 1)
        {"pos": [2.0049, 0.0, 0.0]}, {"pos": [2.0051, 0.0, 0.0]},
        # 6, 7: created by keyframes outside the window [51, 100]
        {"pos": [3.0, 0.0, 0.0], "kf": 50}, {"pos": [3.001, 0.0, 0.0], "kf": 50},
        # 8, 9: gradients above tau
        {"pos": [4.0, 0.0, 0.0], "grad": 0.01}, {"pos": [4.001, 0.0, 0.0], "grad": 0.01},
        # 10, 11: one of them with a large gradient: no pair left
        {"pos": [5.0, 0.0, 0.0]}, {"pos": [5.001, 0.0, 0.0], "grad": 0.01},
    ]
    gmap = _make_map(rows)
    d2_gate = (0.004 / 0.001) ** 2
    assert d2_gate > CHI2_3DOF_95
    res = merge_pass(gmap, MergeConfig(voxel_size_m=v, window_keyframes=50, min_age_iters=0), newest_keyframe_id=100,
                     iteration=7)
    assert res.n_merged == 1
    assert _ids_of_pairs(res) == {frozenset({0, 1})}
    assert res.n_candidates == 7  # rows 6, 7, 8, 9, 11 excluded
    assert res.n_voxels == 5  # {0, 1}, {2, 3}, {4}, {5}, {10}
    assert res.n_pairs == 2  # (0, 1) and (2, 3)
    assert len(gmap) == len(rows) - 1
    assert set(res.timings) >= {"masking", "hashing", "distances", "lbfgs", "surgery", "total"}


def test_three_similar_gaussians_in_a_voxel_merge_one_pair_per_pass() -> None:
    rows = [{"pos": [0.0, 0.0, 0.0], "kf": 60}, {"pos": [0.001, 0.0, 0.0], "kf": 61},
            {"pos": [0.0, 0.0015, 0.0], "kf": 62}]
    gmap = _make_map(rows)
    res = merge_pass(gmap, MergeConfig(min_age_iters=0), newest_keyframe_id=100, iteration=1)
    assert res.n_pairs == 3 and res.n_merged == 1 and len(gmap) == 2
    assert _ids_of_pairs(res) == {frozenset({0, 1})}  # the minimum d2: 0.11 vs 0.25 and 0.36
    res2 = merge_pass(gmap, MergeConfig(min_age_iters=0), newest_keyframe_id=100, iteration=2)
    assert res2.n_merged == 1 and len(gmap) == 1  # the survivor and the merged one


def test_disabled_and_empty() -> None:
    gmap = _make_map([{"pos": [0.0, 0.0, 0.0]}, {"pos": [0.001, 0.0, 0.0]}])
    res = merge_pass(gmap, MergeConfig(enabled=False), 100, 0)
    assert res.n_merged == 0 and len(gmap) == 2
    res = merge_pass(GaussianMap(), MergeConfig(), 100, 0)
    assert res.n_merged == 0 and res.removed_ids.numel() == 0


@pytest.mark.parametrize("colour_from", ["older", "newer"])
def test_surgery_bookkeeping(colour_from: str) -> None:
    gen = torch.Generator().manual_seed(9)
    rows = []
    for k in range(40):  # 40 voxels along x, each with 2 or 3 similar Gaussians, plus loners
        n = 2 + k % 2
        for m in range(n):
            off = (torch.rand(3, generator=gen) - 0.5) * 0.002
            rows.append({"pos": (torch.tensor([k * 0.05, 0.0, 0.0]) + off).tolist(),
                         "scale": (0.003 * torch.exp(torch.randn(3, generator=gen) * 0.2)).tolist(),
                         "quat": torch.randn(4, generator=gen).tolist(),
                         "rgb": torch.rand(3, generator=gen).tolist(), "opacity": float(m),
                         "kf": 60 + m})
    for k in range(10):
        rows.append({"pos": [k * 0.05, 1.0, 0.0]})
    gmap = _make_map(rows)
    # give every row Adam state so we can check new rows start from zero moments
    for p in gmap.params().values():
        p.grad = torch.ones_like(p)
    gmap.optimizer_step()
    gmap.merge_grad_sum[:] = 1e-5  # seen, stable: still candidates
    gmap.merge_count[:] = 1
    before_ids = gmap.ids.clone()
    before = {name: getattr(gmap, name).detach().clone() for name in ("means", "log_scales", "quats_wxyz",
                                                                       "opacity_logits", "sh_dc", "sh_rest")}
    before_kf = gmap.keyframe_ids.clone()
    before_m = gmap.optimizer.state[gmap.means]["exp_avg"].clone()
    max_id = int(before_ids.max())

    res = merge_pass(gmap, MergeConfig(colour_from=colour_from, min_age_iters=0), newest_keyframe_id=100,
                     iteration=123)
    assert res.n_merged == 40
    removed, added = res.removed_ids.tolist(), res.added_ids.tolist()
    assert len(removed) == 2 * len(added) == 2 * res.n_merged
    untouched = sorted(set(before_ids.tolist()) - set(removed))
    now = gmap.ids.tolist()
    # every Gaussian accounted for exactly once, new ids fresh
    assert len(set(removed)) == len(removed) and set(removed) <= set(before_ids.tolist())
    assert sorted(now) == sorted(untouched + added) and len(now) == len(set(now))
    assert min(added) > max_id
    assert len(gmap) == len(before_ids) - res.n_merged

    old_row = {int(i): r for r, i in enumerate(before_ids.tolist())}
    new_row = {int(i): r for r, i in enumerate(now)}
    # untouched rows keep every parameter bit for bit
    keep_old = torch.tensor([old_row[i] for i in untouched])
    keep_new = torch.tensor([new_row[i] for i in untouched])
    for name, val in before.items():
        assert torch.equal(getattr(gmap, name).detach()[keep_new], val[keep_old]), name
    assert torch.equal(gmap.optimizer.state[gmap.means]["exp_avg"][keep_new], before_m[keep_old])
    # merged rows: colour/opacity from the chosen source, keyframe of the older, zero moments
    pairs = res.removed_ids.reshape(-1, 2)
    assert bool((pairs[:, 0] < pairs[:, 1]).all())  # older first
    src_ids = pairs[:, 0] if colour_from == "older" else pairs[:, 1]
    src = torch.tensor([old_row[int(i)] for i in src_ids])
    older = torch.tensor([old_row[int(i)] for i in pairs[:, 0]])
    newer = torch.tensor([old_row[int(i)] for i in pairs[:, 1]])
    dst = torch.tensor([new_row[int(i)] for i in res.added_ids])
    for name in ("opacity_logits", "sh_dc", "sh_rest"):
        assert torch.equal(getattr(gmap, name).detach()[dst], before[name][src]), name
    assert torch.equal(gmap.keyframe_ids[dst], before_kf[older])
    assert bool((gmap.created_iter[dst] == 123).all())
    for p in gmap.params().values():
        assert bool((gmap.optimizer.state[p]["exp_avg"][dst] == 0).all())
        assert bool((gmap.optimizer.state[p]["exp_avg_sq"][dst] == 0).all())
    assert bool((gmap.merge_count[dst] == 0).all()) and bool((gmap.merge_grad_sum[dst] == 0).all())
    # merged mean: the closed form from the two parents
    mu_i, mu_j = before["means"][older].double(), before["means"][newer].double()
    Pi = precision_from_scale_quat(before["log_scales"][older].double().exp(), before["quats_wxyz"][older].double())
    Pj = precision_from_scale_quat(before["log_scales"][newer].double().exp(), before["quats_wxyz"][newer].double())
    torch.testing.assert_close(gmap.means.detach()[dst].double(), merged_mean(mu_i, Pi, mu_j, Pj),
                               atol=1e-7, rtol=0)
    q = gmap.quats_wxyz.detach()[dst]
    torch.testing.assert_close(q.norm(dim=1), torch.ones(len(dst)), atol=1e-6, rtol=0)


@pytest.mark.parametrize("kwargs,field", [
    ({"tau": 0.0}, "tau"), ({"voxel_size_m": -1.0}, "voxel_size_m"), ({"window_keyframes": 0}, "window_keyframes"),
    ({"colour_from": "both"}, "colour_from"), ({"max_per_voxel": 1}, "max_per_voxel"),
    ({"slerp_t": 1.0}, "slerp_t"), ({"init_scale_offset_m": (0.1, 0.2)}, "init_scale_offset_m"),
    ({"lbfgs_parametrization": "euler"}, "lbfgs_parametrization"),
])
def test_config_validation_names_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        MergeConfig(**kwargs)


def test_unknown_keyframe_ids_are_never_candidates() -> None:
    gmap = _make_map([{"pos": [0.0, 0.0, 0.0], "kf": -1}, {"pos": [0.001, 0.0, 0.0], "kf": -1},
                      {"pos": [1.0, 0.0, 0.0], "kf": 3}, {"pos": [1.001, 0.0, 0.0], "kf": 4}])
    res = merge_pass(gmap, MergeConfig(min_age_iters=0), newest_keyframe_id=5, iteration=0)
    assert res.n_candidates == 2 and _ids_of_pairs(res) == {frozenset({2, 3})}


def test_seeds_younger_than_min_age_are_not_candidates() -> None:
    """A seed not trained yet has no gradient to be still by: it waits min_age_iters iterations."""
    rows = [{"pos": [0.0, 0.0, 0.0], "kf": 60}, {"pos": [0.001, 0.0, 0.0], "kf": 61}]
    gmap = _make_map(rows)  # created at iteration 0
    assert merge_pass(gmap, MergeConfig(min_age_iters=200), newest_keyframe_id=100, iteration=199).n_merged == 0
    assert merge_pass(gmap, MergeConfig(min_age_iters=200), newest_keyframe_id=100, iteration=200).n_merged == 1

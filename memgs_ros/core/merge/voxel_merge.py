"""Voxel-based merging of geometrically similar Gaussians (MemGS Sec. II-D, reference section 4).

One pass, all vectorised (no Python loop over voxels or pairs):

1. ``candidate_mask``: stable Gaussians, mean 3D positional gradient norm < tau, created by one of
   the newest ``window_keyframes`` keyframes.
2. ``voxel_keys`` / ``voxel_pairs``: candidates hashed to voxels of ``voxel_size_m``; every pair
   (i older, j newer) inside a voxel.
3. ``mahalanobis_sq``: ``d2 = (mu_j - mu_i)^T Sigma_i^-1 (mu_j - mu_i)``;
   ``select_min_pair_per_voxel`` keeps each voxel's minimum, merged only if ``d2 < 7.815``
   (chi-square, 3 dof, 95 %; the paper's direction, the released code's is inverted).
4. ``merged_mean``: ``(Si^-1 + Sj^-1)^-1 (Si^-1 mu_i + Sj^-1 mu_j)``.
5. ``merge_covariance``: ``argmin_Sk W2(Sk, Si)^2 + W2(Sk, Sj)^2`` by one batched L-BFGS
   (torch.optim.LBFGS, strong Wolfe) initialised as the paper does (slerp of the rotations,
   mean scale + [1, 2, 3] mm), over the symmetric square root of Sk (default; well conditioned
   for a shared line search) or the paper's quaternion + scale; the result is returned as
   quaternion + scale either way; on the host whatever the map's device (small, sequential
   problems). ``memgs_ros.core.merge.wasserstein`` holds the eigh-free, repeated-eigenvalue-safe W2.
6. ``merge_pass``: the map surgery. Each merged pair becomes ONE new Gaussian (fresh id, zero
   Adam moments and accumulators) with colour, SH and opacity from the older Gaussian (paper;
   ``colour_from="newer"`` is the released code's choice); both old ids are removed.

Pair order: ids are monotonic, so "older" = smaller id.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, NamedTuple

import torch

from memgs_ros.core.geometry.poses import quat_wxyz_to_rotmat_torch, rotmat_to_quat_wxyz_torch
from memgs_ros.core.merge.config import CHI2_3DOF_95, MergeConfig
from memgs_ros.core.merge.wasserstein import precision_from_scale_quat, slerp_wxyz, trace_sqrt_spd3
from memgs_ros.errors import ConfigError

if TYPE_CHECKING:
    from memgs_ros.core.gaussians.gaussian_map import GaussianMap

__all__ = ["CHI2_3DOF_95", "MergeConfig", "MergeResult", "VoxelPairs", "candidate_mask", "mahalanobis_sq",
           "merge_covariance", "merge_pass", "merged_mean", "select_min_pair_per_voxel", "voxel_keys", "voxel_pairs"]

# Voxel coordinates are packed into one int64 as three 21-bit fields (after shifting by the
# minimum), i.e. up to 2,097,152 voxels per axis: 20 km at 1 cm. Larger extents fall back to
# torch.unique over rows.
_KEY_BITS = 21
_KEY_SPAN = 1 << _KEY_BITS


class VoxelPairs(NamedTuple):
    """Candidate pairs inside voxels. i, j: [P] int64 indices into the candidate arrays with
    order[i] < order[j] (i older); voxel: [P] int64 compact voxel index of each pair;
    n_voxels: number of occupied voxels."""

    i: torch.Tensor
    j: torch.Tensor
    voxel: torch.Tensor
    n_voxels: int


@dataclass(frozen=True)
class MergeResult:
    """What one ``merge_pass`` did.

    removed_ids: [2P] int64 ids removed (each merged pair's older then newer id, pair by pair);
    added_ids: [P] int64 fresh ids of the merged Gaussians (added_ids[p] replaces
    removed_ids[2p], removed_ids[2p+1]); n_candidates: Gaussians passing the mask; n_voxels:
    occupied candidate voxels; n_pairs: pairs whose d2 was computed; n_merged: P;
    lbfgs_iters: L-BFGS iterations run; timings: seconds per stage (masking, hashing,
    distances, lbfgs, surgery, total).
    """

    removed_ids: torch.Tensor
    added_ids: torch.Tensor
    n_candidates: int
    n_voxels: int
    n_pairs: int
    n_merged: int
    lbfgs_iters: int = 0
    timings: dict[str, float] = field(default_factory=dict)


# ------------------------------------------------------------------ pure tensor functions
def candidate_mask(pos_grad_mean: torch.Tensor,  # [N]
                   keyframe_ids: torch.Tensor,  # [N]
                   tau: float, k_min: int, k_max: int,
                   ) -> torch.Tensor:  # [N] bool
    """Eq. (merge mask): ``grad < tau AND k_min <= keyframe id <= k_max``.

    pos_grad_mean: [N] mean 3D positional gradient norm (0 for unseen Gaussians);
    keyframe_ids: [N] int64 creating keyframe. Returns [N] bool.
    """
    assert pos_grad_mean.shape == keyframe_ids.shape and pos_grad_mean.dim() == 1, \
        f"candidate_mask: shapes {tuple(pos_grad_mean.shape)}, {tuple(keyframe_ids.shape)}"
    return (pos_grad_mean < tau) & (keyframe_ids >= k_min) & (keyframe_ids <= k_max)


def voxel_keys(means: torch.Tensor,  # [M, 3]
               voxel_size: float,
               ) -> torch.Tensor:  # [M] int64
    """One int64 key per point for the voxel ``round(position / voxel_size)``.

    means: [M, 3]. Equal keys <=> same voxel. The three integer coordinates are shifted by
    their minimum and packed as 21-bit fields; extents beyond 2^21 voxels on an axis fall back to
    ``torch.unique`` over rows (keys are then the rows' ranks). Returns [M] int64.
    """
    assert means.dim() == 2 and means.shape[1] == 3, f"voxel_keys: means {tuple(means.shape)}"
    if means.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64, device=means.device)
    v = torch.round(means.to(torch.float64) / voxel_size).to(torch.int64)  # [M, 3]
    v = v - v.min(dim=0).values
    if int(v.max()) < _KEY_SPAN:
        return (v[:, 0] << (2 * _KEY_BITS)) | (v[:, 1] << _KEY_BITS) | v[:, 2]
    return torch.unique(v, dim=0, return_inverse=True)[1]


def voxel_pairs(keys: torch.Tensor,  # [M]
                order: torch.Tensor,  # [M]
                max_per_voxel: int = 32,
                ) -> VoxelPairs:
    """Every pair (i, j) of points sharing a key, with order[i] < order[j].

    keys: [M] int64 voxel keys; order: [M] int64 insertion order (ids; unique). Points are sorted
    by (key, order); a point of rank r in a voxel holding n points pairs with the n-1-r later
    ones. Pairs come from index arithmetic (repeat_interleave + cumsum), no loop. Only the
    ``max_per_voxel`` oldest points of a voxel are paired, so a pathological voxel yields at most
    cap(cap-1)/2 pairs instead of n^2/2. Returns ``VoxelPairs(i [P], j [P], voxel [P], n_voxels)``.
    """
    assert keys.shape == order.shape and keys.dim() == 1, f"voxel_pairs: {tuple(keys.shape)}, {tuple(order.shape)}"
    dev = keys.device
    m = keys.shape[0]
    empty = torch.zeros(0, dtype=torch.int64, device=dev)
    if m == 0:
        return VoxelPairs(empty, empty, empty, 0)
    perm = torch.argsort(order, stable=True)
    perm = perm[torch.argsort(keys[perm], stable=True)]  # by key, then by order
    _, counts = torch.unique_consecutive(keys[perm], return_counts=True)  # [V]
    n_vox = int(counts.shape[0])
    vox_sorted = torch.repeat_interleave(torch.arange(n_vox, device=dev), counts)  # [M]
    starts = torch.cumsum(counts, 0) - counts  # [V]
    rank = torch.arange(m, device=dev) - starts[vox_sorted]  # [M]
    n_eff = counts.clamp_max(max_per_voxel)[vox_sorted]  # [M]
    n_later = (n_eff - 1 - rank).clamp_min(0)  # [M] pairs in which this point is the older
    total = int(n_later.sum())
    if total == 0:
        return VoxelPairs(empty, empty, empty, n_vox)
    i_sorted = torch.repeat_interleave(torch.arange(m, device=dev), n_later)  # [P]
    block_start = torch.cumsum(n_later, 0) - n_later  # [M]
    offset = torch.arange(total, device=dev) - block_start[i_sorted]  # [P] 0 .. n_later-1
    j_sorted = i_sorted + 1 + offset
    return VoxelPairs(perm[i_sorted], perm[j_sorted], vox_sorted[i_sorted], n_vox)


def mahalanobis_sq(mu_i: torch.Tensor,  # [P, 3]
                   prec_i: torch.Tensor,  # [P, 3, 3]
                   mu_j: torch.Tensor,  # [P, 3]
                   ) -> torch.Tensor:  # [P]
    """``d2 = (mu_j - mu_i)^T Sigma_i^-1 (mu_j - mu_i)``. mu_i, mu_j: [P, 3]; prec_i: [P, 3, 3]
    the precision of i (``precision_from_scale_quat``). Returns [P]."""
    d = mu_j - mu_i  # [P, 3]
    return torch.einsum("pa,pab,pb->p", d, prec_i, d)


def select_min_pair_per_voxel(d2: torch.Tensor,  # [P]
                              voxel_of_pair: torch.Tensor,  # [P]
                              n_voxels: int,
                              ) -> torch.Tensor:  # [V'] int64
    """Index of the pair with the smallest d2 in each voxel that has pairs (ties: the lowest pair
    index; NaN counts as +inf). d2: [P]; voxel_of_pair: [P] int64 in [0, n_voxels).
    Returns [V'] int64 pair indices, one per voxel with pairs, ascending by voxel."""
    dev = d2.device
    if d2.numel() == 0:
        return torch.zeros(0, dtype=torch.int64, device=dev)
    d = torch.nan_to_num(d2, nan=math.inf)
    vmin = torch.full((n_voxels,), math.inf, dtype=d.dtype, device=dev)
    vmin = vmin.scatter_reduce(0, voxel_of_pair, d, reduce="amin", include_self=True)
    is_min = d == vmin[voxel_of_pair]  # an all-inf voxel: every pair "is" its minimum
    idx = torch.arange(d.shape[0], device=dev)
    big = torch.full((n_voxels,), d.shape[0], dtype=torch.int64, device=dev)
    first = big.scatter_reduce(0, voxel_of_pair[is_min], idx[is_min], reduce="amin", include_self=True)
    return first[first < d.shape[0]]


def merged_mean(mu_i: torch.Tensor,  # [P, 3]
                prec_i: torch.Tensor,  # [P, 3, 3]
                mu_j: torch.Tensor,  # [P, 3]
                prec_j: torch.Tensor,  # [P, 3, 3]
                ) -> torch.Tensor:  # [P, 3]
    """Maximum joint likelihood mean ``(Si^-1 + Sj^-1)^-1 (Si^-1 mu_i + Sj^-1 mu_j)`` by batched
    3x3 solves. mu_*: [P, 3]; prec_*: [P, 3, 3] precisions. Returns [P, 3]."""
    rhs = (prec_i @ mu_i[:, :, None] + prec_j @ mu_j[:, :, None])  # [P, 3, 1]
    return torch.linalg.solve(prec_i + prec_j, rhs)[:, :, 0]


# ------------------------------------------------------------------------- covariance
def _w2_terms_soa(x: torch.Tensor,  # [7, P]
                  q_t: torch.Tensor,  # [4, P]
                  v_t: torch.Tensor,  # [3, P]
                  adj_t: torch.Tensor,  # [3, P]
                  r_t: torch.Tensor,  # [P]
                  ) -> torch.Tensor:  # [P]
    """W2(Sk, St)^2 per column, structure-of-arrays (pairs innermost, contiguous: every op is
    one vectorised pass over P). x rows: quaternion (wxyz, unnormalised) then log-scales of Sk;
    q_t: target unit quaternions; v_t: target variances s^2; adj_t: products of the other two
    variances (eigenvalues of adj St); r_t: prod(s). Returns [P]."""
    kw, kx, ky, kz, s0, s1, s2 = x.unbind(0)  # one unbind: per-row indexing costs a [7, P] zero-fill each in backward
    sc = torch.stack([s0, s1, s2])
    tw, tx, ty, tz = q_t.unbind(0)
    # relative rotation Q = Rk^T Rt = R(conj(qk) (x) qt); entries of R(q) / |q|^2 for unnormalised q
    w = kw * tw + kx * tx + ky * ty + kz * tz
    a = kw * tx - kx * tw - ky * tz + kz * ty
    b = kw * ty + kx * tz - ky * tw - kz * tx
    c = kw * tz - kx * ty + ky * tx - kz * tw
    n2 = kw * kw + kx * kx + ky * ky + kz * kz  # |qr|^2 = |qk|^2 (qt unit)
    ww, aa, bb, cc = w * w, a * a, b * b, c * c
    ab, ac, bc, wa, wb, wc = a * b, a * c, b * c, w * a, w * b, w * c
    Q = torch.stack([
        ww + aa - bb - cc, 2 * (ab - wc), 2 * (ac + wb),
        2 * (ab + wc), ww - aa + bb - cc, 2 * (bc - wa),
        2 * (ac - wb), 2 * (bc + wa), ww - aa - bb + cc,
    ]).reshape(3, 3, -1) / n2  # [3, 3, P]
    W = Q * Q  # doubly stochastic
    v_k = sc * sc  # [3, P]
    adj_k = torch.stack([v_k[1] * v_k[2], v_k[0] * v_k[2], v_k[0] * v_k[1]])  # [3, P]
    I1 = (v_k[:, None, :] * W * v_t[None, :, :]).sum((0, 1))
    I2 = (adj_k[:, None, :] * W * adj_t[None, :, :]).sum((0, 1))
    r = sc.prod(0).abs() * r_t
    return v_k.sum(0) + v_t.sum(0) - 2.0 * trace_sqrt_spd3(I1, I2, r)


Sym6 = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def _sym_sq_soa(X: Sym6) -> Sym6:
    """X @ X for symmetric 3x3 given as six [P] tensors (00, 11, 22, 01, 02, 12). Tuples of
    separate [P] tensors, not a stacked [6, P]: indexing a stacked tensor costs a zero-filled
    [6, P] gradient per index in backward, which dominated the run time."""
    a, d, f, b, c, e = X
    return (a * a + b * b + c * c, b * b + d * d + e * e, c * c + e * e + f * f,
            a * b + b * d + c * e, a * c + b * e + c * f, b * c + d * e + e * f)


def _sym_adj_soa(X: Sym6) -> Sym6:
    """Adjugate of symmetric 3x3 given as six [P] tensors (00, 11, 22, 01, 02, 12)."""
    a, d, f, b, c, e = X
    return (d * f - e * e, a * f - c * c, a * d - b * b, c * e - b * f, b * e - c * d, b * c - a * e)


def _sym_dot_soa(A: Sym6, B: Sym6) -> torch.Tensor:  # -> [P]
    """<A, B> = tr(A B) of symmetric matrices given as six [P] tensors."""
    return A[0] * B[0] + A[1] * B[1] + A[2] * B[2] + 2.0 * (A[3] * B[3] + A[4] * B[4] + A[5] * B[5])


def _sym_from_dense(A: torch.Tensor) -> torch.Tensor:  # [P, 3, 3] -> [6, P]
    return torch.stack([A[:, 0, 0], A[:, 1, 1], A[:, 2, 2], A[:, 0, 1], A[:, 0, 2], A[:, 1, 2]]).contiguous()


def _w2_terms_sqrtcov_soa(X: torch.Tensor,  # [6, P]
                          S_t: torch.Tensor,  # [6, P]
                          adj_t: torch.Tensor,  # [6, P]
                          r_t: torch.Tensor,  # [P]
                          ) -> torch.Tensor:  # [P]
    """W2(X^2, St)^2 per column for symmetric X (the merged covariance's square root), rows
    (00, 11, 22, 01, 02, 12), pairs innermost. In the commuting case this is exactly
    ||X - St^1/2||_F^2: the Hessian is ~2I whatever the pair's shape, so one L-BFGS over many
    pairs behaves like one over a single pair. S_t, adj_t: target covariance and its adjugate;
    r_t: sqrt(det St)."""
    Xs: Sym6 = X.unbind(0)  # type: ignore[assignment]
    St: Sym6 = S_t.unbind(0)  # type: ignore[assignment]
    At: Sym6 = adj_t.unbind(0)  # type: ignore[assignment]
    a, _, _, b, c, _ = Xs  # (a, d, f, b, c, e): only the first row enters the determinant
    adj_x = _sym_adj_soa(Xs)
    det_x = a * adj_x[0] + b * adj_x[3] + c * adj_x[4]  # cofactor expansion along the first row
    S_k = _sym_sq_soa(Xs)
    adj_k = _sym_sq_soa(adj_x)  # adj(X^2) = adj(X)^2
    I1 = _sym_dot_soa(S_k, St)
    I2 = _sym_dot_soa(adj_k, At)
    r = det_x.abs() * r_t
    tr_k = S_k[0] + S_k[1] + S_k[2]
    tr_t = St[0] + St[1] + St[2]
    return tr_k + tr_t - 2.0 * trace_sqrt_spd3(I1, I2, r)


def _dense_from_sym(X: torch.Tensor) -> torch.Tensor:  # [6, P] -> [P, 3, 3]
    return torch.stack([X[0], X[3], X[4], X[3], X[1], X[5], X[4], X[5], X[2]], -1).reshape(-1, 3, 3)


def merge_covariance(q_i: torch.Tensor,  # [P, 4]
                     s_i: torch.Tensor,  # [P, 3]
                     q_j: torch.Tensor,  # [P, 4]
                     s_j: torch.Tensor,  # [P, 3]
                     *,
                     lr: float = 1.0,
                     max_iter: int = 15,
                     history_size: int = 20,
                     tolerance_change: float = 1e-8,
                     tolerance_grad: float = 1e-7,
                     init_scale_offset_m: tuple[float, float, float] = (0.001, 0.002, 0.003),
                     slerp_t: float = 0.5,
                     parametrization: Literal["sqrt_cov", "quat_scale"] = "sqrt_cov",
                     ) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Merged covariance ``argmin_Sk W2(Sk, Si)^2 + W2(Sk, Sj)^2`` as (unit quaternion, scale).

    q_i, q_j: [P, 4] wxyz (any norm); s_i, s_j: [P, 3] activated scales (metres, > 0).

    One ``torch.optim.LBFGS`` (strong-Wolfe line search) over all pairs at once: the loss is the
    sum of independent per-pair terms, so the concatenated problem has the same minimisers. Each
    pair is solved in its own units (covariances divided by c^2, c = geometric mean of the pair's
    six scales; W2 barycentres are equivariant under scaling), so tolerances mean the same for
    1 mm and 1 m Gaussians; ``tolerance_change`` is absolute on the summed normalised loss.
    Init (paper): q0 = slerp(q_i, q_j, slerp_t) on the short arc, s0 = (s_i + s_j)/2 + offset.

    parametrization:
      "sqrt_cov" (default): the variables are the 6 entries of the symmetric square root
        X = R(q) diag(s) R(q)^T of Sk, initialised from (q0, s0) and converted back to (q, s) by
        one float64 eigh at the end. W2 is ~||X - Si^1/2||^2 in these variables (exact when the
        covariances commute), so every pair's Hessian is ~2I and the shared line search and
        shared L-BFGS memory suit all pairs at once: 10k pairs converge to ~1e-6 relative
        (median) in ~11 iterations.
      "quat_scale": the paper's variables, an unnormalised quaternion and the scale vector
        (positivity by |s|: the loss is even in each s). Its Hessian varies with each pair's
        anisotropy, so one batched L-BFGS converges much more slowly (~1e-2 relative median
        after 15 iterations on 10k pairs); kept for comparison.
    Runs with gradients enabled whatever the caller's mode; float64 inside.
    Returns (q_k [P, 4] unit wxyz with w >= 0, s_k [P, 3] > 0, both in s_i's dtype,
    number of L-BFGS iterations run).
    """
    P = q_i.shape[0]
    assert q_i.shape == q_j.shape == (P, 4) and s_i.shape == s_j.shape == (P, 3), \
        f"merge_covariance: {tuple(q_i.shape)} {tuple(s_i.shape)} {tuple(q_j.shape)} {tuple(s_j.shape)}"
    if parametrization not in ("sqrt_cov", "quat_scale"):
        raise ConfigError("merge_covariance: parametrization must be 'sqrt_cov' or 'quat_scale', "
                          f"got {parametrization!r}")
    out_dtype = s_i.dtype
    if P == 0:
        return q_i.new_zeros((0, 4)), s_i.new_zeros((0, 3)), 0
    pairs = _normalised_pairs(q_i, s_i, q_j, s_j, init_scale_offset_m, slerp_t)
    problem = _sqrt_cov_problem if parametrization == "sqrt_cov" else _quat_scale_problem
    x, loss_fn = problem(pairs)
    opt = torch.optim.LBFGS([x], lr=lr, max_iter=max_iter, history_size=history_size,
                            tolerance_change=tolerance_change, tolerance_grad=tolerance_grad,
                            line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad(set_to_none=False)
        loss = loss_fn()
        loss.backward()
        return loss

    with torch.enable_grad():
        opt.step(closure)
    n_iter = int(opt.state[x].get("n_iter", 0))
    with torch.no_grad():
        solution = _sqrt_cov_solution if parametrization == "sqrt_cov" else _quat_scale_solution
        q, s = solution(x.detach(), pairs.c)
        q = torch.where(q[:, :1] < 0, -q, q)
        s = s.clamp_min(torch.finfo(out_dtype).tiny)
    return q.to(out_dtype).contiguous(), s.to(out_dtype).contiguous(), n_iter


class _Pairs(NamedTuple):
    """merge_covariance's pairs in float64, each in its own units: qi, qj [P, 4] unit; si_n, sj_n
    [P, 3] scales / c; c [P, 1] the geometric mean of the pair's six scales; q0 [P, 4], s0 [P, 3]
    (/ c) the paper's initial guess."""

    qi: torch.Tensor
    qj: torch.Tensor
    si_n: torch.Tensor
    sj_n: torch.Tensor
    c: torch.Tensor
    q0: torch.Tensor
    s0: torch.Tensor


def _normalised_pairs(q_i: torch.Tensor, s_i: torch.Tensor, q_j: torch.Tensor, s_j: torch.Tensor,
                      init_scale_offset_m: tuple[float, float, float], slerp_t: float) -> _Pairs:
    f64 = torch.float64
    qi = q_i.detach().to(f64)
    qj = q_j.detach().to(f64)
    si = s_i.detach().to(f64)
    sj = s_j.detach().to(f64)
    qi = qi / qi.norm(dim=-1, keepdim=True)
    qj = qj / qj.norm(dim=-1, keepdim=True)
    c = (0.5 * (si.log().mean(-1) + sj.log().mean(-1))).exp()[:, None]  # [P, 1]
    offset = torch.tensor(init_scale_offset_m, dtype=f64, device=si.device)
    s0 = (0.5 * (si + sj) + offset) / c  # [P, 3]
    return _Pairs(qi, qj, si / c, sj / c, c, slerp_wxyz(qi, qj, slerp_t), s0)


LossFn = Callable[[], torch.Tensor]


def _sqrt_cov_problem(pairs: _Pairs) -> tuple[torch.Tensor, LossFn]:
    """The variable X [6, P] (symmetric square root of Sk, from (q0, s0)) and the summed W2 loss."""
    def target(q: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, ...]:
        R = quat_wxyz_to_rotmat_torch(q)
        S = _sym_from_dense((R * (s * s)[:, None, :]) @ R.transpose(-1, -2))
        return S, torch.stack(_sym_adj_soa(S.unbind(0))), s.prod(-1)  # type: ignore[arg-type]  # [6, ...]

    ti, tj = target(pairs.qi, pairs.si_n), target(pairs.qj, pairs.sj_n)
    S_t, adj_t, r_t = (torch.cat([a, b], -1) for a, b in zip(ti, tj))  # 2P columns: i terms, j terms
    R0 = quat_wxyz_to_rotmat_torch(pairs.q0)
    x = _sym_from_dense((R0 * pairs.s0[:, None, :]) @ R0.transpose(-1, -2)).requires_grad_(True)  # [6, P]
    return x, lambda: _w2_terms_sqrtcov_soa(torch.cat([x, x], -1), S_t, adj_t, r_t).sum()


def _quat_scale_problem(pairs: _Pairs) -> tuple[torch.Tensor, LossFn]:
    """The variable [7, P] (unnormalised quaternion, scales; from (q0, s0)) and the summed W2 loss."""
    def target(q: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, ...]:
        v = s * s
        p = s.prod(-1)
        return q.T.contiguous(), v.T.contiguous(), ((p * p)[:, None] / v).T.contiguous(), p

    ti, tj = target(pairs.qi, pairs.si_n), target(pairs.qj, pairs.sj_n)
    q_t, v_t, adjv_t, r_t = (torch.cat([a, b], -1) for a, b in zip(ti, tj))
    x = torch.cat([pairs.q0.T, pairs.s0.T], 0).contiguous().requires_grad_(True)  # [7, P]
    return x, lambda: _w2_terms_soa(torch.cat([x, x], -1), q_t, v_t, adjv_t, r_t).sum()


def _sqrt_cov_solution(x: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """X [6, P] -> (q [P, 4], s [P, 3] in metres) by one float64 eigh."""
    evals, evecs = torch.linalg.eigh(_dense_from_sym(x))  # X = V diag(e) V^T
    s = evals.abs() * c  # X^2 = V diag(e^2) V^T: the scale is |e|
    # a proper rotation: flip one eigenvector when det = -1 (X is unchanged by the sign)
    flip = torch.linalg.det(evecs) < 0
    evecs = torch.where(flip[:, None, None], evecs * evecs.new_tensor([1.0, 1.0, -1.0]), evecs)
    return rotmat_to_quat_wxyz_torch(evecs), s


def _quat_scale_solution(x: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """[7, P] -> (unit q [P, 4], s [P, 3] in metres)."""
    q = x[0:4].T
    return q / q.norm(dim=-1, keepdim=True), x[4:7].T.abs() * c


# ----------------------------------------------------------------------------- surgery
def _sync(device: torch.device) -> None:
    """Wait for queued GPU work so stage timings are honest (no-op on CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def merge_pass(gmap: GaussianMap, cfg: MergeConfig, newest_keyframe_id: int, iteration: int) -> MergeResult:
    """One merge pass over ``gmap`` in place (reference section 4).

    Candidates: ``merge_grad_mean() < cfg.tau`` and keyframe id in
    ``[max(newest_keyframe_id - cfg.window_keyframes + 1, 0), newest_keyframe_id]`` (ids < 0,
    i.e. loaded Gaussians of unknown keyframe, are never candidates), created at least
    ``cfg.min_age_iters`` iterations before ``iteration``. Per voxel the pair
    with minimum d2 is merged iff d2 < ``cfg.chi2_gate``: at most one merge per voxel per pass, so
    no Gaussian is in two merges. Each merged pair is removed and replaced by one Gaussian with a
    fresh id: closed-form mean, L-BFGS covariance, colour/SH/opacity from the older
    (``cfg.colour_from``), keyframe id and nothing else from the older Gaussian (it keeps the
    pair in the window as long as its older half would have been), created_iter = ``iteration``,
    zero Adam moments and accumulators. All other rows are untouched. Returns ``MergeResult``.
    """
    dev = gmap.device
    clock = _StageClock(dev)
    empty = torch.zeros(0, dtype=torch.int64, device=dev)
    if not cfg.enabled or len(gmap) == 0:
        return MergeResult(empty, empty, 0, 0, 0, 0, 0, {"total": clock.total()})
    with torch.no_grad():
        cand, pairs = _candidate_pairs(gmap, cfg, newest_keyframe_id, clock, iteration)
        chosen = _chosen_pairs(gmap, cfg, cand, pairs)
        clock.lap("distances")
    q_k, s_k, n_iter = _pair_covariances(chosen, cfg, dev)
    clock.lap("lbfgs")
    counts = (int(cand.shape[0]), pairs.n_voxels, int(chosen.d2.shape[0]))
    if chosen.n_merged == 0:
        clock.timings["surgery"] = 0.0
        return MergeResult(empty, empty, *counts, 0, n_iter, {**clock.timings, "total": clock.total()})
    with torch.no_grad():
        pair_ids, added = _replace_pairs(gmap, cfg, chosen, q_k, s_k, iteration)
        clock.lap("surgery")
    return MergeResult(pair_ids, added, *counts, chosen.n_merged, n_iter, {**clock.timings, "total": clock.total()})


class _StageClock:
    """Seconds per stage of one merge pass, waiting for queued GPU work at each lap."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.t0 = self.last = time.perf_counter()
        self.timings: dict[str, float] = {}

    def lap(self, name: str) -> None:
        _sync(self.device)
        now = time.perf_counter()
        self.timings[name] = now - self.last
        self.last = now

    def total(self) -> float:
        return time.perf_counter() - self.t0


class _Chosen(NamedTuple):
    """The pairs a pass merges. d2: [P] of every candidate pair; mi, mj: [P'] map rows (mi older);
    mu_k: [P', 3] merged means; q_i, s_i, q_j, s_j: [P', 4] / [P', 3] float64 of the two rows."""

    d2: torch.Tensor
    mi: torch.Tensor
    mj: torch.Tensor
    mu_k: torch.Tensor
    q_i: torch.Tensor
    s_i: torch.Tensor
    q_j: torch.Tensor
    s_j: torch.Tensor

    @property
    def n_merged(self) -> int:
        return int(self.mi.shape[0])


def _candidate_pairs(gmap: GaussianMap, cfg: MergeConfig, newest_keyframe_id: int, clock: _StageClock,
                     iteration: int = 0) -> tuple[torch.Tensor, VoxelPairs]:
    """The candidate rows [M] (``candidate_mask``, and old enough: ``cfg.min_age_iters``) and their
    pairs inside voxels (laps "masking" and "hashing")."""
    k_max = int(newest_keyframe_id)
    # keyframe id -1 marks Gaussians of unknown origin (a loaded map): never in the window
    k_min = max(k_max - cfg.window_keyframes + 1, 0)
    mask = candidate_mask(gmap.merge_grad_mean(), gmap.keyframe_ids, cfg.tau, k_min, k_max)
    if cfg.min_age_iters > 0:
        mask &= gmap.created_iter <= iteration - cfg.min_age_iters
    cand = torch.nonzero(mask).reshape(-1)  # [M] rows
    clock.lap("masking")
    keys = voxel_keys(gmap.means.detach()[cand], cfg.voxel_size_m)
    pairs = voxel_pairs(keys, gmap.ids[cand], cfg.max_per_voxel)
    clock.lap("hashing")
    return cand, pairs


def _chosen_pairs(gmap: GaussianMap, cfg: MergeConfig, cand: torch.Tensor, pairs: VoxelPairs) -> _Chosen:
    """Each voxel's closest pair if its d2 passes the gate, with the merged mean."""
    ri, rj = cand[pairs.i], cand[pairs.j]  # [P] map rows, ri older
    f64 = torch.float64
    mu_i = gmap.means.detach()[ri].to(f64)
    mu_j = gmap.means.detach()[rj].to(f64)
    s_i = gmap.log_scales.detach()[ri].to(f64).exp()
    q_i = gmap.quats_wxyz.detach()[ri].to(f64)
    prec_i = precision_from_scale_quat(s_i, q_i)
    d2 = mahalanobis_sq(mu_i, prec_i, mu_j)
    best = select_min_pair_per_voxel(d2, pairs.voxel, pairs.n_voxels)
    best = best[d2[best] < cfg.chi2_gate]
    mi, mj = ri[best], rj[best]  # [P'] rows of the merged pairs
    s_j = gmap.log_scales.detach()[mj].to(f64).exp()
    q_j = gmap.quats_wxyz.detach()[mj].to(f64)
    prec_j = precision_from_scale_quat(s_j, q_j)
    mu_k = merged_mean(mu_i[best], prec_i[best], mu_j[best], prec_j)
    return _Chosen(d2, mi, mj, mu_k, q_i[best], s_i[best], q_j, s_j)


def _pair_covariances(chosen: _Chosen, cfg: MergeConfig, dev: torch.device
                      ) -> tuple[torch.Tensor, torch.Tensor, int]:
    """merge_covariance of the chosen pairs with cfg's L-BFGS settings, solved on the host."""
    # The covariance solve runs on the host whatever the map's device: a few thousand 3x3
    # problems take ~50 ms on one core, while on a GPU the strong-Wolfe line search waits for the
    # device at every evaluation and cuSOLVER's batched eigh takes ~0.5 MB of workspace per 3x3
    # matrix (1.38 GB for 2663 pairs on an H200: the mapper's whole CUDA peak).
    host = torch.device("cpu")
    q_k, s_k, n_iter = merge_covariance(
        chosen.q_i.to(host), chosen.s_i.to(host), chosen.q_j.to(host), chosen.s_j.to(host), lr=cfg.lbfgs_lr,
        max_iter=cfg.lbfgs_max_iter, history_size=cfg.lbfgs_history, tolerance_change=cfg.lbfgs_tolerance_change,
        tolerance_grad=cfg.lbfgs_tolerance_grad, init_scale_offset_m=cfg.init_scale_offset_m,
        slerp_t=cfg.slerp_t, parametrization=cfg.lbfgs_parametrization)
    return q_k.to(dev), s_k.to(dev), n_iter


def _replace_pairs(gmap: GaussianMap, cfg: MergeConfig, chosen: _Chosen, q_k: torch.Tensor, s_k: torch.Tensor,
                   iteration: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Removes both rows of each chosen pair and appends the merged Gaussian in one resize.
    Returns (removed ids [2P'] older then newer, pair by pair; added ids [P'])."""
    mi, mj = chosen.mi, chosen.mj
    src = mi if cfg.colour_from == "older" else mj
    remove = torch.zeros(len(gmap), dtype=torch.bool, device=gmap.device)
    remove[mi] = True
    remove[mj] = True
    pair_ids = torch.stack([gmap.ids[mi], gmap.ids[mj]], 1).reshape(-1)  # [2P'] older, newer
    added = gmap.add(chosen.mu_k.to(gmap.means.dtype), s_k.log().to(gmap.log_scales.dtype),
                     q_k.to(gmap.quats_wxyz.dtype), gmap.opacity_logits.detach()[src].clone(),
                     gmap.sh_dc.detach()[src].clone(), gmap.sh_rest.detach()[src].clone(),
                     gmap.keyframe_ids[mi].clone(), iteration, remove=remove)
    return pair_ids, added

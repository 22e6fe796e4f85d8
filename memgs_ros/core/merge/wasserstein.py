"""Gaussian covariance algebra for the voxel merge (MemGS Sec. II-D): 2-Wasserstein distances.

The merge needs ``W2(A, B)^2 = tr(A + B - 2 (A^1/2 B A^1/2)^1/2)`` between 3x3 SPD covariances,
differentiable, for ~10k pairs at a time, and robust at the very point the optimiser aims for
(equal covariances, equal eigenvalues). Eigen-decomposition gradients contain
``1 / (lambda_a - lambda_b)`` and blow up there, so the fast path never differentiates an eigh:

``tr(M^1/2)`` of a 3x3 SPD ``M`` depends only on the invariants of ``M``. With ``a, b, c`` the
eigenvalues of ``M^1/2``, ``p = a + b + c``, ``q = ab + bc + ca``, ``r = abc`` and the invariants
``I1 = tr M``, ``I2`` (sum of principal 2x2 minors), ``det M``::

    p^2 = I1 + 2 q,    q^2 = I2 + 2 r p,    r = sqrt(det M)
    =>  F(p) = (p^2 - I1)^2 - 4 I2 - 8 r p = 0,   p = the largest root.

For ``M = A^1/2 B A^1/2`` the invariants are those of ``AB``: ``I1 = <A, B>``,
``I2 = <adj A, adj B>`` (adjugates multiply), ``det M = det A det B``: polynomials in the entries,
no matrix square root needed. ``p`` is found by Newton's method from an upper bound (monotone
convergence: ``F`` is convex above its largest root), and its gradient by the implicit function
theorem, ``dp = (q dI1 + dI2 + 2 p dr) / (2 (a+b)(b+c)(c+a))``, which stays finite when
eigenvalues coincide. ``_w2_sq_eigh`` is the textbook eigh-based twin used by the tests.
"""
from __future__ import annotations

import torch

from memgs_ros.core.geometry.poses import quat_wxyz_to_rotmat_torch

__all__ = [
    "adjugate_sym3",
    "covariance_from_scale_quat",
    "precision_from_scale_quat",
    "slerp_wxyz",
    "trace_sqrt_spd3",
    "w2_barycenter_fixed_point",
    "w2_sq",
    "w2_sq_factored",
]

# Newton steps that polish the closed-form (trigonometric) estimate of the largest root.
_NEWTON_POLISH_STEPS = 2


def covariance_from_scale_quat(scales: torch.Tensor,  # [N, 3]
                               quats_wxyz: torch.Tensor,  # [N, 4]
                               ) -> torch.Tensor:  # [N, 3, 3]
    """``Sigma = R diag(s^2) R^T``. scales: [N, 3] activated (metres, > 0); quats_wxyz: [N, 4]
    (normalised here). Returns [N, 3, 3]."""
    R = quat_wxyz_to_rotmat_torch(quats_wxyz)  # [N, 3, 3]
    return (R * (scales * scales)[:, None, :]) @ R.transpose(-1, -2)


def precision_from_scale_quat(scales: torch.Tensor,  # [N, 3]
                              quats_wxyz: torch.Tensor,  # [N, 4]
                              ) -> torch.Tensor:  # [N, 3, 3]
    """``Sigma^-1 = R diag(1 / s^2) R^T`` without a general inverse. scales: [N, 3] (> 0);
    quats_wxyz: [N, 4]. Returns [N, 3, 3]."""
    R = quat_wxyz_to_rotmat_torch(quats_wxyz)  # [N, 3, 3]
    return (R * (1.0 / (scales * scales))[:, None, :]) @ R.transpose(-1, -2)


def adjugate_sym3(A: torch.Tensor,  # [N, 3, 3]
                  ) -> torch.Tensor:  # [N, 3, 3]
    """Adjugate (transposed cofactor matrix) of symmetric 3x3 matrices A: [N, 3, 3] -> [N, 3, 3]."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    c11 = a * f - c * c
    c12 = b * c - a * e
    c22 = a * d - b * b
    return torch.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], -1).reshape(-1, 3, 3)


def _largest_root(I1: torch.Tensor, I2: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Largest root p of (p^2 - I1)^2 - 4 I2 - 8 r p = 0, i.e. tr(M^1/2), for [P] float64 inputs.

    The eigenvalues of M come from the trigonometric solution of its characteristic cubic
    (accurate to ~1e-8 relative even when they coincide), then Newton polishes p from slightly
    above the root, where F is convex, so it converges monotonically and never crosses to a
    smaller root. No data-dependent loop: no host synchronisation on a GPU. Returns [P].
    """
    scale = I1.clamp_min(torch.finfo(I1.dtype).tiny)  # p ~ sqrt(I1): x = p / sqrt(I1) lies in [1, sqrt 3]
    i2 = (I2 / (scale * scale)).clamp_min(0.0)
    rr = (r / (scale * scale.sqrt())).clamp_min(0.0)
    det = rr * rr
    # lambda^3 - lambda^2 + i2 lambda - det = 0 (normalised so that tr = 1)
    Q = ((1.0 - 3.0 * i2) / 9.0).clamp_min(0.0)
    R = (9.0 * i2 - 2.0 - 27.0 * det) / 54.0
    sq = Q.sqrt()
    cos_arg = (R / (Q * sq).clamp_min(1e-300)).clamp(-1.0, 1.0)
    # eigenvalues 1/3 - 2 sqrt(Q) cos(phi + 2 pi k / 3), phi = acos(.) / 3 in [0, pi/3]; the k = 1, 2
    # cosines by angle addition (float64 cos is slow on CPU: one call instead of three)
    cos_phi = torch.cos(torch.acos(cos_arg) / 3.0)
    sin_phi = (1.0 - cos_phi * cos_phi).clamp_min(0.0).sqrt()
    half_sqrt3 = 0.8660254037844386
    x = (1.0 / 3.0 - 2.0 * sq * cos_phi).clamp_min(0.0).sqrt()
    x = x + (1.0 / 3.0 + sq * (cos_phi + 2.0 * half_sqrt3 * sin_phi)).clamp_min(0.0).sqrt()
    x = x + (1.0 / 3.0 + sq * (cos_phi - 2.0 * half_sqrt3 * sin_phi)).clamp_min(0.0).sqrt()
    x = (x * (1.0 + 1e-7)).clamp(1.0, 3.0 ** 0.5)
    for _ in range(_NEWTON_POLISH_STEPS):
        x2m1 = x * x - 1.0
        f = x2m1 * x2m1 - 4.0 * i2 - 8.0 * rr * x
        fp = 4.0 * x * x2m1 - 8.0 * rr
        step = torch.where(fp > 0, f / fp.clamp_min(1e-300), torch.zeros_like(f))
        x = (x - step).clamp_min(1.0)  # p^2 = I1 + 2q >= I1
    return x * scale.sqrt()


class _TraceSqrtSPD3(torch.autograd.Function):
    """tr(M^1/2) from the invariants (I1, I2, r = sqrt(det M)) of a 3x3 SPD M; implicit gradient."""

    @staticmethod
    def forward(ctx, I1: torch.Tensor, I2: torch.Tensor, r: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        p = _largest_root(I1, I2, r)
        ctx.save_for_backward(p, I1, r)
        return p

    @staticmethod
    def backward(ctx, v_p: torch.Tensor):  # type: ignore[override]
        p, I1, r = ctx.saved_tensors
        q = 0.5 * (p * p - I1)
        # pq - r = (a+b)(b+c)(c+a) > 0 for any non-degenerate M, also when eigenvalues coincide.
        denom = 2.0 * (p * q - r).clamp_min(torch.finfo(p.dtype).tiny)
        g = v_p / denom
        return g * q, g, g * 2.0 * p


def trace_sqrt_spd3(I1: torch.Tensor,  # [P]
                    I2: torch.Tensor,  # [P]
                    r: torch.Tensor,  # [P]
                    ) -> torch.Tensor:  # [P]
    """``tr(M^1/2)`` for 3x3 SPD M given by its invariants: I1 = tr M [P], I2 = sum of principal
    2x2 minors [P], r = sqrt(det M) [P]. Differentiable (implicit gradient, finite at repeated
    eigenvalues). Returns [P] in the inputs' dtype (use float64)."""
    return _TraceSqrtSPD3.apply(I1, I2, r)


def w2_sq(A: torch.Tensor,  # [P, 3, 3]
          B: torch.Tensor,  # [P, 3, 3]
          ) -> torch.Tensor:  # [P]
    """Squared 2-Wasserstein distance between zero-mean Gaussians with SPD covariances A, B:
    ``tr(A + B - 2 (A^1/2 B A^1/2)^1/2)``. A, B: [P, 3, 3] -> [P]. Eigh-free and differentiable
    (see the module docstring); its reference twin is ``_w2_sq_eigh``. Compute in float64."""
    assert A.shape == B.shape and A.shape[1:] == (3, 3), f"w2_sq: shapes {tuple(A.shape)}, {tuple(B.shape)}"
    I1 = (A * B).sum((-1, -2))
    I2 = (adjugate_sym3(A) * adjugate_sym3(B)).sum((-1, -2))
    r = (torch.linalg.det(A) * torch.linalg.det(B)).clamp_min(0.0).sqrt()
    trA = A.diagonal(dim1=-2, dim2=-1).sum(-1)
    trB = B.diagonal(dim1=-2, dim2=-1).sum(-1)
    return trA + trB - 2.0 * trace_sqrt_spd3(I1, I2, r)


def _sqrtm_sym_eigh(A: torch.Tensor) -> torch.Tensor:
    """Symmetric PSD square root by float64 eigh, eigenvalues clamped at 0. A: [P, 3, 3]."""
    evals, evecs = torch.linalg.eigh(A.to(torch.float64))
    return ((evecs * evals.clamp_min(0.0).sqrt()[:, None, :]) @ evecs.transpose(-1, -2)).to(A.dtype)


def _w2_sq_eigh(A: torch.Tensor,  # [P, 3, 3]
                B: torch.Tensor,  # [P, 3, 3]
                ) -> torch.Tensor:  # [P]
    """Reference twin of ``w2_sq`` with two eigh-based matrix square roots (gradient unstable at
    repeated eigenvalues; use for tests only). A, B: [P, 3, 3] -> [P]."""
    As = _sqrtm_sym_eigh(A)
    M = As @ B @ As
    M = 0.5 * (M + M.transpose(-1, -2))
    cross = _sqrtm_sym_eigh(M).diagonal(dim1=-2, dim2=-1).sum(-1)
    return A.diagonal(dim1=-2, dim2=-1).sum(-1) + B.diagonal(dim1=-2, dim2=-1).sum(-1) - 2.0 * cross


def w2_sq_factored(scales_a: torch.Tensor,  # [P, 3]
                   quats_a: torch.Tensor,  # [P, 4]
                   scales_b: torch.Tensor,  # [P, 3]
                   quats_b: torch.Tensor,  # [P, 4]
                   ) -> torch.Tensor:  # [P]
    """``w2_sq`` for covariances given as (scale, quaternion wxyz): the adjugate of
    ``R diag(s^2) R^T`` is ``R diag(s_y^2 s_z^2, s_x^2 s_z^2, s_x^2 s_y^2) R^T`` and the
    determinant ``prod(s)^2``, so nothing cancels. scales_*: [P, 3] (> 0), quats_*: [P, 4] -> [P]."""
    Ra = quat_wxyz_to_rotmat_torch(quats_a)  # [P, 3, 3]
    Rb = quat_wxyz_to_rotmat_torch(quats_b)
    va, vb = scales_a * scales_a, scales_b * scales_b  # [P, 3] variances
    pa, pb = scales_a.prod(-1), scales_b.prod(-1)  # [P]
    adj_va = (pa * pa)[:, None] / va.clamp_min(torch.finfo(va.dtype).tiny)  # [P, 3] products of the other two
    adj_vb = (pb * pb)[:, None] / vb.clamp_min(torch.finfo(vb.dtype).tiny)
    # <Ra Da Ra^T, Rb Db Rb^T> = sum_kl Da_k Db_l (Ra^T Rb)_kl^2
    W = (Ra.transpose(-1, -2) @ Rb).square()  # [P, 3, 3] doubly stochastic
    I1 = (va[:, :, None] * W * vb[:, None, :]).sum((-1, -2))
    I2 = (adj_va[:, :, None] * W * adj_vb[:, None, :]).sum((-1, -2))
    r = pa * pb
    return va.sum(-1) + vb.sum(-1) - 2.0 * trace_sqrt_spd3(I1, I2, r)


def slerp_wxyz(q0: torch.Tensor,  # [P, 4]
               q1: torch.Tensor,  # [P, 4]
               t: float,
               ) -> torch.Tensor:  # [P, 4]
    """Spherical linear interpolation of unit quaternions (wxyz) along the short arc (q1 is
    negated where q0 . q1 < 0: q and -q are the same rotation). q0, q1: [P, 4] -> [P, 4] unit."""
    q0 = q0 / q0.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    q1 = q1 / q1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    theta = torch.acos(dot)
    sin_theta = torch.sin(theta)
    near = sin_theta < 1e-6  # nearly equal: the normalised lerp is exact to first order
    safe = torch.where(near, torch.ones_like(sin_theta), sin_theta)
    w0 = torch.where(near, torch.full_like(theta, 1.0 - t), torch.sin((1.0 - t) * theta) / safe)
    w1 = torch.where(near, torch.full_like(theta, t), torch.sin(t * theta) / safe)
    q = w0 * q0 + w1 * q1
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def w2_barycenter_fixed_point(A: torch.Tensor,  # [P, 3, 3]
                              B: torch.Tensor,  # [P, 3, 3]
                              iters: int = 50,
                              ) -> torch.Tensor:  # [P, 3, 3]
    """Equal-weight W2 barycenter of N(0, A) and N(0, B) by the fixed-point iteration
    ``S <- S^-1/2 ((S^1/2 A S^1/2)^1/2 / 2 + (S^1/2 B S^1/2)^1/2 / 2)^2 S^-1/2`` (Alvarez-Esteban
    et al. 2016), float64 eigh. The exact minimiser of W2(S, A)^2 + W2(S, B)^2: an independent
    check of the L-BFGS merge. A, B: [P, 3, 3] -> [P, 3, 3]."""
    A = A.to(torch.float64)
    B = B.to(torch.float64)
    S = 0.5 * (A + B)
    for _ in range(iters):
        evals, evecs = torch.linalg.eigh(S)
        s_half = (evecs * evals.clamp_min(1e-300).sqrt()[:, None, :]) @ evecs.transpose(-1, -2)
        s_mhalf = (evecs * evals.clamp_min(1e-300).rsqrt()[:, None, :]) @ evecs.transpose(-1, -2)
        T = 0.5 * (_sqrtm_sym_eigh(s_half @ A @ s_half) + _sqrtm_sym_eigh(s_half @ B @ s_half))
        S = s_mhalf @ T @ T @ s_mhalf
        S = 0.5 * (S + S.transpose(-1, -2))
    return S

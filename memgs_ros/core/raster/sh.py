"""Real spherical harmonics colour evaluation, 3DGS convention (degrees 0..3).

``colour = max(0, sum_l sum_m Y_lm(dir) * coeff_lm + 0.5)`` where ``Y_00 = 0.28209...``
and ``dir`` points from the camera centre to the Gaussian. Plain autograd: O(N).
"""
from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from memgs_ros.core.gaussians.records import SH_C0

SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel up to ``degree`` inclusive: (degree + 1)^2."""
    return (degree + 1) ** 2


def _sh_basis_rows(x: Tensor, y: Tensor, z: Tensor, degree: int) -> list[Tensor]:
    """The real SH basis functions 0..(degree + 1)^2 - 1 at unit directions (x, y, z): [N] each."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    rows = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        rows += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        rows += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        rows += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return rows


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """The real SH basis at unit directions.

    dirs: [N, 3] unit vectors. Returns [N, (degree + 1)^2].
    """
    x, y, z = dirs.unbind(-1)
    return torch.stack(_sh_basis_rows(x, y, z, degree), dim=-1)


def _eval_sh_colors_reference(
    sh_dc: Tensor,  # [N, 1, 3]
    sh_rest: Tensor,  # [N, K, 3]
    dirs: Tensor,  # [N, 3]
    degree: int,
) -> Tensor:
    """Plain-autograd twin of :func:`eval_sh_colors` (same arguments and result), for tests."""
    n_rest = num_sh_bases(degree) - 1
    if degree == 0:
        rgb = SH_C0 * sh_dc[:, 0, :]
    else:
        basis = sh_basis(dirs, degree)  # [N, B]
        coeffs = torch.cat([sh_dc, sh_rest[:, :n_rest, :]], dim=1)  # [N, B, 3]
        rgb = (basis.unsqueeze(-1) * coeffs).sum(dim=1)  # [N, 3]
    return (rgb + 0.5).clamp_min(0.0)


def _sh_basis_vjp(x: Tensor, y: Tensor, z: Tensor, v_basis: Tensor, degree: int) -> Tensor:
    """d(sum_b v_basis_b Y_b(x, y, z)) / d(x, y, z) for the bands 1..degree.

    x, y, z: [N] direction components; v_basis: [(degree + 1)^2 - 1, N] (band 0 is constant).
    Returns [N, 3].
    """
    v = v_basis.unbind(0)
    gx = -SH_C1 * v[2]
    gy = -SH_C1 * v[0]
    gz = SH_C1 * v[1]
    if degree >= 2:
        gx = gx + SH_C2[0] * y * v[3] - 2.0 * SH_C2[2] * x * v[5] + SH_C2[3] * z * v[6] + 2.0 * SH_C2[4] * x * v[7]
        gy = gy + SH_C2[0] * x * v[3] + SH_C2[1] * z * v[4] - 2.0 * SH_C2[2] * y * v[5] - 2.0 * SH_C2[4] * y * v[7]
        gz = gz + SH_C2[1] * y * v[4] + 4.0 * SH_C2[2] * z * v[5] + SH_C2[3] * x * v[6]
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        gx = (
            gx
            + SH_C3[0] * 6.0 * xy * v[8]
            + SH_C3[1] * yz * v[9]
            - SH_C3[2] * 2.0 * xy * v[10]
            - SH_C3[3] * 6.0 * xz * v[11]
            + SH_C3[4] * (4.0 * zz - 3.0 * xx - yy) * v[12]
            + SH_C3[5] * 2.0 * xz * v[13]
            + SH_C3[6] * 3.0 * (xx - yy) * v[14]
        )
        gy = (
            gy
            + SH_C3[0] * 3.0 * (xx - yy) * v[8]
            + SH_C3[1] * xz * v[9]
            + SH_C3[2] * (4.0 * zz - xx - 3.0 * yy) * v[10]
            - SH_C3[3] * 6.0 * yz * v[11]
            - SH_C3[4] * 2.0 * xy * v[12]
            - SH_C3[5] * 2.0 * yz * v[13]
            - SH_C3[6] * 6.0 * xy * v[14]
        )
        gz = (
            gz
            + SH_C3[1] * xy * v[9]
            + SH_C3[2] * 8.0 * yz * v[10]
            + SH_C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * v[11]
            + SH_C3[4] * 8.0 * xz * v[12]
            + SH_C3[5] * (xx - yy) * v[13]
        )
    return torch.stack([gx, gy, gz], dim=-1)


class _ShColorsFn(torch.autograd.Function):
    """SH colours for degree >= 1 with a hand-written backward (autograd over the ~40 basis
    ops per Gaussian costs about 3x more on CPU). Twin: :func:`_eval_sh_colors_reference`."""

    @staticmethod
    def forward(ctx: Any, dirs: Tensor, sh_dc: Tensor, sh_rest: Tensor, degree: int) -> Tensor:  # type: ignore[override]
        n_rest = num_sh_bases(degree) - 1
        # Component rows made contiguous first: elementwise ops on stride-3 views are slow
        # (and stack(unbind) is faster than .T.contiguous() for [N, 3]).
        xyz = torch.stack(dirs.unbind(-1))  # [3, N]
        basis = torch.stack(_sh_basis_rows(xyz[0], xyz[1], xyz[2], degree)[1:])  # [B - 1, N]
        rest = sh_rest[:, :n_rest, :]  # [N, B - 1, 3]
        # Per-Gaussian [1, B-1] @ [B-1, 3]: batched matmul beats a broadcast product reduced
        # over the short band axis by ~2x on CPU.
        raw = torch.bmm(basis.T.unsqueeze(1), rest).squeeze(1) + (SH_C0 * sh_dc[:, 0, :] + 0.5)  # [N, 3]
        ctx.degree = degree
        ctx.n_rest_total = sh_rest.shape[1]
        ctx.save_for_backward(xyz, basis, rest, raw)
        return raw.clamp_min(0.0)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, v_rgb: Tensor) -> tuple[Tensor | None, ...]:
        xyz, basis, rest, raw = ctx.saved_tensors  # [3, N], [B - 1, N], [N, B - 1, 3], [N, 3]
        v = v_rgb * (raw >= 0)  # [N, 3]; clamp_min passes the gradient at and above 0
        v_dc = (SH_C0 * v).unsqueeze(1)  # [N, 1, 3]
        v_rest = None
        if ctx.needs_input_grad[2]:
            v_rest = torch.zeros(v.shape[0], ctx.n_rest_total, 3, dtype=v.dtype, device=v.device)
            v_rest[:, : basis.shape[0]] = basis.T.unsqueeze(-1) * v.unsqueeze(1)
        v_dirs = None
        if ctx.needs_input_grad[0]:
            v_basis = torch.bmm(rest, v.unsqueeze(-1)).squeeze(-1).T.contiguous()  # [B - 1, N]
            v_dirs = _sh_basis_vjp(xyz[0], xyz[1], xyz[2], v_basis, ctx.degree)
        return v_dirs, v_dc, v_rest, None


def eval_sh_colors(
    sh_dc: Tensor,  # [N, 1, 3]
    sh_rest: Tensor,  # [N, K, 3]
    dirs: Tensor,  # [N, 3]
    degree: int,
) -> Tensor:
    """RGB colours [N, 3] of Gaussians seen along ``dirs`` (unit, camera -> Gaussian).

    sh_dc: [N, 1, 3]; sh_rest: [N, K, 3] with K >= (degree + 1)^2 - 1 (higher bands ignored);
    dirs: [N, 3]. Returns [N, 3], clamped at 0 from below after the +0.5 offset.
    """
    n_rest = num_sh_bases(degree) - 1
    if sh_rest.shape[1] < n_rest:
        raise ValueError(f"sh_rest has {sh_rest.shape[1]} coefficients, degree {degree} needs {n_rest}")
    if degree == 0:
        return (SH_C0 * sh_dc[:, 0, :] + 0.5).clamp_min(0.0)
    return _ShColorsFn.apply(dirs, sh_dc, sh_rest, degree)

"""Real spherical harmonics colour evaluation, 3DGS convention (degrees 0..3).

``colour = max(0, sum_l sum_m Y_lm(dir) * coeff_lm + 0.5)`` where ``Y_00 = 0.28209...``
and ``dir`` points from the camera centre to the Gaussian. Plain autograd: O(N).
"""
from __future__ import annotations

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814
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


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """The real SH basis at unit directions.

    dirs: [N, 3] unit vectors. Returns [N, (degree + 1)^2].
    """
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    x, y, z = dirs.unbind(-1)
    cols = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        cols += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        cols += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        cols += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(cols, dim=-1)


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
        rgb = SH_C0 * sh_dc[:, 0, :]
    else:
        basis = sh_basis(dirs, degree)  # [N, B]
        coeffs = torch.cat([sh_dc, sh_rest[:, :n_rest, :]], dim=1)  # [N, B, 3]
        rgb = (basis.unsqueeze(-1) * coeffs).sum(dim=1)  # [N, 3]
    return (rgb + 0.5).clamp_min(0.0)

"""EWA projection of 3D Gaussians to screen space (plain autograd, O(N)).

World -> camera with ``T_cw``; the 3D covariance ``R S S^T R^T`` is mapped to the image by
``J W Sigma W^T J^T`` (W = rotation of T_cw, J = Jacobian of the pinhole projection at the
Gaussian's centre) and dilated by 0.3 px^2 on the diagonal, as in 3DGS. The principal point
(cx, cy) is used as is: pixel (u, v) has its centre at integer coordinates (OpenCV convention).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from memgs_ros.core.gaussians.tensors import Gaussians
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.poses import quat_wxyz_to_rotmat_torch
from memgs_ros.core.raster.sh import eval_sh_colors
from memgs_ros.core.raster.values import Splats2D

COV2D_DILATION = 0.3  # px^2 added to the 2D covariance diagonal (3DGS low-pass filter)
# The Jacobian is evaluated with x/z, y/z clamped to 1.3x the half field of view (3DGS/gsplat):
# a Gaussian far outside the frustum otherwise gets an unbounded 2D covariance and gradient.
JACOBIAN_FOV_MARGIN = 0.3


@dataclass(frozen=True)
class Projected:
    """Per-Gaussian screen-space quantities, differentiable w.r.t. the Gaussian parameters.

    means2d: [N, 2] pixel coordinates of the centres; cov2d: [N, 3] (xx, xy, yy) dilated
    2D covariance; conics: [N, 3] (a, b, c) of its inverse [[a, b], [b, c]];
    depths: [N] camera-frame z; opacities: [N] in (0, 1); colors: [N, 3];
    in_front: [N] bool, z > near. Rows with ``in_front`` False hold finite placeholder values.
    """

    means2d: Tensor
    cov2d: Tensor
    conics: Tensor
    depths: Tensor
    opacities: Tensor
    colors: Tensor
    in_front: Tensor

    def splats(self) -> Splats2D:
        """What a compositor takes (the same tensors: gradients flow back through them)."""
        return Splats2D(self.means2d, self.conics, self.opacities, self.colors, self.depths)


def project_gaussians(
    gaussians: Gaussians,
    T_cw: Tensor,  # [4, 4]
    camera: PinholeCamera,
    sh_degree: int,
    near: float,
) -> Projected:
    """Activate and project N Gaussians into ``camera`` at world-to-camera pose ``T_cw``.

    means: [N, 3]; quats_wxyz: [N, 4]; log_scales: [N, 3]; opacity_logits: [N, 1];
    sh_dc: [N, 1, 3]; sh_rest: [N, K, 3]; T_cw: [4, 4]. Returns a :class:`Projected` with [N, ...] rows.
    """
    means, quats_wxyz, log_scales, opacity_logits, sh_dc, sh_rest = gaussians
    R = T_cw[:3, :3]  # [3, 3]
    t = T_cw[:3, 3]  # [3]
    p_c = means @ R.T + t  # [N, 3]
    x, y, z = p_c.unbind(-1)
    in_front = z > near
    # Culled rows get z = 1 so that no division makes inf/NaN that would leak into gradients.
    z_safe = torch.where(in_front, z, torch.ones_like(z))
    inv_z = 1.0 / z_safe
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    means2d = torch.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], dim=-1)  # [N, 2]

    half_tan_x = 0.5 * camera.width / fx
    half_tan_y = 0.5 * camera.height / fy
    lim_x_pos = (camera.width - cx) / fx + JACOBIAN_FOV_MARGIN * half_tan_x
    lim_x_neg = cx / fx + JACOBIAN_FOV_MARGIN * half_tan_x
    lim_y_pos = (camera.height - cy) / fy + JACOBIAN_FOV_MARGIN * half_tan_y
    lim_y_neg = cy / fy + JACOBIAN_FOV_MARGIN * half_tan_y
    tx = (x * inv_z).clamp(-lim_x_neg, lim_x_pos)
    ty = (y * inv_z).clamp(-lim_y_neg, lim_y_pos)
    # cov2d = A A^T with A = J W R_g S ([N, 2, 3]); J has only four non-zeros, so each row of
    # J W is a combination of two rows of W. Elementwise broadcasting instead of batched 2x3 / 3x3
    # matmuls, which are slow on CPU for millions of tiny matrices (forward and backward).
    jw0 = (fx * inv_z)[:, None] * R[0] - (fx * tx * inv_z)[:, None] * R[2]  # [N, 3]
    jw1 = (fy * inv_z)[:, None] * R[1] - (fy * ty * inv_z)[:, None] * R[2]  # [N, 3]
    rot = quat_wxyz_to_rotmat_torch(quats_wxyz)  # [N, 3, 3]
    scales = torch.exp(log_scales)  # [N, 3]
    # (Sums over the length-3 axes written out: torch reductions over such short axes are slow.)
    a0 = (jw0[:, 0:1] * rot[:, 0] + jw0[:, 1:2] * rot[:, 1] + jw0[:, 2:3] * rot[:, 2]) * scales  # [N, 3] row 0 of A
    a1 = (jw1[:, 0:1] * rot[:, 0] + jw1[:, 1:2] * rot[:, 1] + jw1[:, 2:3] * rot[:, 2]) * scales  # [N, 3]
    ones = torch.ones(3, 1, dtype=a0.dtype, device=a0.device)
    sxx = ((a0 * a0) @ ones)[:, 0] + COV2D_DILATION
    sxy = ((a0 * a1) @ ones)[:, 0]
    syy = ((a1 * a1) @ ones)[:, 0] + COV2D_DILATION
    det = sxx * syy - sxy * sxy  # > 0.09 thanks to the dilation
    inv_det = 1.0 / det
    conics = torch.stack([syy * inv_det, -sxy * inv_det, sxx * inv_det], dim=-1)  # [N, 3]
    cov2d = torch.stack([sxx, sxy, syy], dim=-1)  # [N, 3]

    opacities = torch.sigmoid(opacity_logits[:, 0])  # [N]
    cam_centre = -(R.T @ t)  # [3]
    dirs = means - cam_centre  # [N, 3]
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    colors = eval_sh_colors(sh_dc, sh_rest, dirs, sh_degree)  # [N, 3]
    return Projected(
        means2d=means2d,
        cov2d=cov2d,
        conics=conics,
        depths=z,
        opacities=opacities,
        colors=colors,
        in_front=in_front,
    )


def screen_radii(cov2d: Tensor) -> Tensor:
    """3-sigma screen radius in pixels, ceil(3 sqrt(lambda_max)) (3DGS), [N, 3] -> [N] int32."""
    with torch.no_grad():
        sxx, sxy, syy = cov2d.unbind(-1)
        mid = 0.5 * (sxx + syy)
        lam = mid + torch.sqrt((mid * mid - (sxx * syy - sxy * sxy)).clamp_min(0.1))
        return torch.ceil(3.0 * torch.sqrt(lam)).to(torch.int32)


def alpha_cutoff_sq(opacities: Tensor, min_alpha: float) -> Tensor:
    """Squared Mahalanobis radius beyond which ``opacity * exp(-0.5 r^2) < min_alpha``.

    opacities: [N]. Returns [N]; negative where the Gaussian can never reach ``min_alpha``.
    """
    return 2.0 * torch.log(opacities.clamp_min(1e-30) / min_alpha) if min_alpha > 0 else torch.full_like(
        opacities, math.inf
    )

"""Optional CUDA backend: the same :func:`rasterize` contract on top of gsplat (>= 1.0).

Used only when ``gsplat`` imports and the tensors live on a CUDA device (``backend="auto"``),
or when asked for by name. It is not exercised by the CPU test-suite (no GPU in CI); what it
maps, and where gsplat's semantics differ from the torch backend:

- parameters are activated here (exp scales, sigmoid opacity) and the SH coefficients are
  passed raw with ``sh_degree``; gsplat applies the same 3DGS SH convention (+0.5, clamp at 0);
- ``render_mode="RGB+D"`` gives the alpha-blended, un-normalised depth (the paper's D_p);
- gsplat bins by a 3-sigma box on 16x16 tiles, so pixels far in a Gaussian's tail can differ
  from the torch backend by up to one 1/255 step of alpha;
- pixel centres: gsplat evaluates pixel (i, j) at (j + 0.5, i + 0.5), this package (OpenCV, and
  the torch/numba backends) at (j, i). gsplat gets the principal point shifted by +0.5 px
  (:func:`gsplat_intrinsics`), so both render the same image from the same camera, and its
  ``means2d`` come back shifted by -0.5 px into this package's convention. (Passing K
  unchanged rendered every image half a pixel off: the cause of the first GPU parity failure.)
- ``means2d`` is a detached [N, 2] copy of gsplat's ``meta["means2d"]`` whose ``.grad`` a
  backward hook fills (it is not part of the graph: do not differentiate through it).
- ``packed=True`` (the registry's ``gsplat_packed``): gsplat keeps only the Gaussians a camera
  sees ([nnz] rows with ``meta["gaussian_ids"]``) instead of dense [C, N] arrays; the adapter
  scatters them back to [N] (means2d and radii 0, and no gradient, for the others, which the
  torch backend gives a screen position but no pixel).
"""
from __future__ import annotations

import torch
from torch import Tensor

from memgs_ros.core.gaussians.tensors import Gaussians
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.raster.values import RenderOutput


def gsplat_available() -> bool:
    """True when the gsplat package can be imported."""
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


# gsplat's pixel (i, j) has its centre at (j + 0.5, i + 0.5); this package's at (j, i).
GSPLAT_PIXEL_CENTRE = 0.5


def gsplat_intrinsics(camera: PinholeCamera, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[3, 3] K to hand gsplat so that it renders what the torch backend renders from ``camera``:
    the principal point moved by +0.5 px (see the module docstring)."""
    c = GSPLAT_PIXEL_CENTRE
    return torch.tensor(
        [[camera.fx, 0.0, camera.cx + c], [0.0, camera.fy, camera.cy + c], [0.0, 0.0, 1.0]], dtype=dtype, device=device
    )


def rasterize_gsplat(
    gaussians: Gaussians,
    T_cw: Tensor,  # [4, 4]
    camera: PinholeCamera,
    sh_degree: int,
    background: Tensor | None,  # [3]
    near: float,
    packed: bool = False,
) -> RenderOutput:
    """gsplat twin of :func:`memgs_ros.core.raster.rasterize`; same arguments and result
    (``packed``: gsplat's packed mode, see the module docstring)."""
    means, quats_wxyz, log_scales, opacity_logits, sh_dc, sh_rest = gaussians
    from gsplat import rasterization

    dtype, device = means.dtype, means.device
    K = gsplat_intrinsics(camera, dtype, device)
    n_bases = (sh_degree + 1) ** 2
    coeffs = torch.cat([sh_dc, sh_rest[:, : n_bases - 1]], dim=1)  # [N, B, 3]
    renders, alphas, meta = rasterization(
        means=means,
        quats=quats_wxyz,
        scales=torch.exp(log_scales),
        opacities=torch.sigmoid(opacity_logits[:, 0]),
        colors=coeffs,
        viewmats=T_cw[None],
        Ks=K[None],
        width=camera.width,
        height=camera.height,
        near_plane=near,
        sh_degree=sh_degree,
        packed=packed,
        # gsplat 1.5.3's packed mode checks backgrounds against [channels], not [1, channels],
        # and refuses a camera batch's; the background is composited below instead, as gsplat does.
        backgrounds=None if background is None or packed else background[None],
        render_mode="RGB+D",
    )
    # gsplat's means2d is [1, N, 2] ([nnz, 2] packed); hand out an [N, 2] leaf whose .grad a hook
    # fills, so that callers read out.means2d.grad exactly as with the torch backend.
    n = means.shape[0]
    full = meta["means2d"]
    radii = meta["radii"] if packed else meta["radii"][0]
    if radii.dim() == 2:  # gsplat >= 1.5 returns per-axis radii [N, 2]
        radii = radii.max(dim=-1).values
    if packed:
        ids = meta["gaussian_ids"].long()  # [nnz]
        means2d = torch.zeros(n, 2, dtype=dtype, device=device)
        means2d[ids] = full.detach() - GSPLAT_PIXEL_CENTRE
        radii = torch.zeros(n, dtype=radii.dtype, device=device).index_copy_(0, ids, radii)
    else:
        ids = None
        means2d = full[0].detach() - GSPLAT_PIXEL_CENTRE  # a shift: the gradient is the same
    if full.requires_grad:

        def _store(grad: Tensor) -> None:
            g = grad[0] if ids is None else torch.zeros(n, 2, dtype=grad.dtype, device=grad.device).index_add_(
                0, ids, grad)
            means2d.grad = g if means2d.grad is None else means2d.grad + g

        full.register_hook(_store)
    radii = radii.to(torch.int32)
    color = renders[0, ..., :3].permute(2, 0, 1)  # [3, H, W]
    if packed and background is not None:
        color = color + (1.0 - alphas[0, ..., 0])[None] * background[:, None, None]
    return RenderOutput(
        color=color,
        depth=renders[0, ..., 3],
        alpha=alphas[0, ..., 0],
        means2d=means2d,
        radii=radii,
        visible=radii > 0,
    )

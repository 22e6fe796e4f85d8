"""Compiled CPU projection + SH colours (numba), behind :func:`project_gaussians`'s signature.

Twin of :func:`memgs_ros.core.raster.projection.project_gaussians` (plain torch autograd, the
reference): same inputs, same :class:`Projected` result, same clamps, gradients w.r.t. every
tensor input including ``T_cw``. One autograd Function: the forward kernel writes all outputs
in one pass over the Gaussians (float64 inside, outputs in the input dtype); the backward kernel
recomputes the per-Gaussian intermediates and applies the analytic vector-Jacobian products, so
nothing but the inputs is saved. The torch path runs ~60 small kernels over [N] tensors in each
direction; here each Gaussian costs a few hundred flops in registers.

Threads: the kernels release the GIL and take a row range; ranges are spread over Python threads
(``cpu_threads()``) when there are enough Gaussians to pay for the thread start-up.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from memgs_ros.core.gaussians.tensors import Gaussians
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.raster.projection import JACOBIAN_FOV_MARGIN, Projected
from memgs_ros.core.raster.sh import num_sh_bases
from memgs_ros.core.runtime.cpu import numba_available
from memgs_ros.core.runtime.pool import cpu_threads, parallel_map
from memgs_ros.errors import ConfigError

__all__ = ["project_gaussians_numba"]

# Rows per Python thread at least (fewer threads otherwise). With threads made per call a split
# bought nothing at 20k Gaussians; on the process's persistent pool (core/runtime/pool.py) the
# backward pass of a 30k-Gaussian step at 320x240 went from 5.7 to 3.4 ms on 2 cores.
MIN_ROWS_PER_THREAD = 4096


def _kernels() -> Any:
    if not numba_available():
        raise ConfigError("project_gaussians_numba: numba is not importable (or MEMGS_DISABLE_NUMBA is set)")
    from memgs_ros.core.raster import _projection_kernels

    return _projection_kernels


KERNEL_DTYPES = (torch.float32, torch.float64)


def _arr(t: Tensor, dtype: torch.dtype) -> np.ndarray:
    """A contiguous numpy view of ``t`` (detached) in ``dtype``, copied only when needed."""
    return t.detach().to(dtype).contiguous().numpy()


def _camera_array(camera: PinholeCamera, near: float) -> np.ndarray:
    """[9] (fx, fy, cx, cy, x/z lower limit, x/z upper limit, y/z lower, y/z upper, near), as in project_gaussians."""
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    half_tan_x = 0.5 * camera.width / fx
    half_tan_y = 0.5 * camera.height / fy
    return np.array(
        [
            fx,
            fy,
            cx,
            cy,
            cx / fx + JACOBIAN_FOV_MARGIN * half_tan_x,
            (camera.width - cx) / fx + JACOBIAN_FOV_MARGIN * half_tan_x,
            cy / fy + JACOBIAN_FOV_MARGIN * half_tan_y,
            (camera.height - cy) / fy + JACOBIAN_FOV_MARGIN * half_tan_y,
            near,
        ],
        dtype=np.float64,
    )


def _ranges(n: int, threads: int) -> list[tuple[int, int, int]]:
    """(k, lo, hi) row ranges, one per thread that pays for itself."""
    jobs = max(1, min(threads, n // MIN_ROWS_PER_THREAD))
    bounds = np.linspace(0, n, jobs + 1).astype(np.int64)
    return [(k, int(bounds[k]), int(bounds[k + 1])) for k in range(jobs)]


class _ProjectNumbaFn(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means: Tensor,  # [N, 3]
        quats_wxyz: Tensor,  # [N, 4]
        log_scales: Tensor,  # [N, 3]
        opacity_logits: Tensor,  # [N, 1]
        sh_dc: Tensor,  # [N, 1, 3]
        sh_rest: Tensor,  # [N, K, 3]
        T_cw: Tensor,  # [4, 4]
        cam: np.ndarray,  # [9]
        sh_degree: int,
        threads: int,
    ) -> tuple[Tensor, ...]:
        k = _kernels()
        n = means.shape[0]
        # The kernels read and write float32 or float64 arrays directly (float64 arithmetic
        # inside): no conversion copies of the [N, K, 3] SH coefficients in either direction.
        dtype = means.dtype if means.dtype in KERNEL_DTYPES else torch.float64
        pose = _arr(torch.cat([T_cw[:3, :3].reshape(-1), T_cw[:3, 3]]), torch.float64)  # [12]
        means2d = torch.empty(n, 2, dtype=dtype)
        cov2d = torch.empty(n, 3, dtype=dtype)
        conics = torch.empty(n, 3, dtype=dtype)
        depths = torch.empty(n, dtype=dtype)
        opac = torch.empty(n, dtype=dtype)
        colors = torch.empty(n, 3, dtype=dtype)
        in_front = torch.empty(n, dtype=torch.bool)
        args = (
            _arr(means, dtype),
            _arr(quats_wxyz, dtype),
            _arr(log_scales, dtype),
            _arr(opacity_logits, dtype).reshape(n),
            _arr(sh_dc, dtype).reshape(n, 3),
            _arr(sh_rest, dtype),
            pose,
            cam,
            sh_degree,
        )
        outs = (means2d.numpy(), cov2d.numpy(), conics.numpy(), depths.numpy(), opac.numpy(), colors.numpy(),
                in_front.numpy())
        jobs = _ranges(n, threads)
        parallel_map(lambda j: k.project_forward(j[1], j[2], args, outs), jobs, threads)
        ctx.args = args
        ctx.jobs = jobs
        ctx.threads = threads
        ctx.dtype = dtype
        ctx.rest_shape = tuple(sh_rest.shape)
        ctx.dtypes = (means.dtype, quats_wxyz.dtype, log_scales.dtype, opacity_logits.dtype, sh_dc.dtype, sh_rest.dtype,
                      T_cw.dtype)
        ctx.mark_non_differentiable(in_front)
        out_dtype = means.dtype
        return (
            means2d.to(out_dtype),
            cov2d.to(out_dtype),
            conics.to(out_dtype),
            depths.to(out_dtype),
            opac.to(out_dtype),
            colors.to(out_dtype),
            in_front,
        )

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, *v_out: Tensor | None) -> tuple[Tensor | None, ...]:
        k = _kernels()
        means_np = ctx.args[0]
        n = means_np.shape[0]
        sh_degree = ctx.args[-1]
        shapes = ((n, 2), (n, 3), (n, 3), (n,), (n,), (n, 3))
        dtype = ctx.dtype
        cot = tuple(
            np.zeros(s, dtype=means_np.dtype) if v is None else _arr(v, dtype).reshape(s)
            for v, s in zip(v_out[:6], shapes)
        )
        f64 = torch.float64
        v_means = torch.empty(n, 3, dtype=dtype)
        v_quats = torch.empty(n, 4, dtype=dtype)
        v_log_scales = torch.empty(n, 3, dtype=dtype)
        v_logits = torch.empty(n, 1, dtype=dtype)
        v_dc = torch.empty(n, 1, 3, dtype=dtype)
        # Written in full by the kernel (zeros above the active degree); not used at degree 0.
        v_rest = torch.empty(ctx.rest_shape if sh_degree > 0 else (n, 0, 3), dtype=dtype)
        acc = np.zeros((len(ctx.jobs), k.ACC_COLS))
        grads = (
            v_means.numpy(),
            v_quats.numpy(),
            v_log_scales.numpy(),
            v_logits.numpy().reshape(n),
            v_dc.numpy().reshape(n, 3),
            v_rest.numpy(),
        )
        parallel_map(lambda j: k.project_backward(j[1], j[2], ctx.args, cot, grads, acc[j[0]]),
                     ctx.jobs, ctx.threads)
        v_T = None
        if ctx.needs_input_grad[6]:
            g = acc.sum(0)  # [ACC_COLS], summed in range order (deterministic)
            pose = ctx.args[6]
            R, t = pose[:9].reshape(3, 3), pose[9:]
            v_R = g[:9].reshape(3, 3)
            v_t = g[9:12].copy()
            v_d = g[12:15]  # dL/d(mean - c) summed; c = -R^T t, so dL/dc = -v_d
            v_R = v_R + np.outer(t, v_d)
            v_t += R @ v_d
            v_T = torch.zeros(4, 4, dtype=f64)
            v_T[:3, :3] = torch.from_numpy(v_R)
            v_T[:3, 3] = torch.from_numpy(v_t)
            v_T = v_T.to(ctx.dtypes[6])
        dt = ctx.dtypes
        return (
            v_means.to(dt[0]) if ctx.needs_input_grad[0] else None,
            v_quats.to(dt[1]) if ctx.needs_input_grad[1] else None,
            v_log_scales.to(dt[2]) if ctx.needs_input_grad[2] else None,
            v_logits.to(dt[3]) if ctx.needs_input_grad[3] else None,
            v_dc.to(dt[4]) if ctx.needs_input_grad[4] else None,
            # Degree 0 does not use sh_rest: no gradient, as in the torch path.
            v_rest.to(dt[5]) if ctx.needs_input_grad[5] and sh_degree > 0 else None,
            v_T,
            None,
            None,
            None,
        )


def project_gaussians_numba(
    gaussians: Gaussians,
    T_cw: Tensor,  # [4, 4]
    camera: PinholeCamera,
    sh_degree: int,
    near: float,
    threads: int | None = None,
) -> Projected:
    """Compiled twin of :func:`memgs_ros.core.raster.projection.project_gaussians` (CPU tensors).

    means: [N, 3]; quats_wxyz: [N, 4]; log_scales: [N, 3]; opacity_logits: [N, 1];
    sh_dc: [N, 1, 3]; sh_rest: [N, K, 3]; T_cw: [4, 4]; threads: Python threads (default
    :func:`cpu_threads`; one below MIN_ROWS_PER_THREAD rows per thread). Returns a
    :class:`Projected` with [N, ...] rows, in the input dtype (computed in float64).
    """
    means, quats_wxyz, log_scales, opacity_logits, sh_dc, sh_rest = gaussians
    for name, t in (("means", means), ("T_cw", T_cw)):
        if t.device.type != "cpu":
            raise ValueError(f"project_gaussians_numba: {name} must be a CPU tensor, got {t.device}")
    n_rest = num_sh_bases(sh_degree) - 1
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
    if sh_rest.shape[1] < n_rest:
        raise ValueError(f"sh_rest has {sh_rest.shape[1]} coefficients, degree {sh_degree} needs {n_rest}")
    means2d, cov2d, conics, depths, opacities, colors, in_front = _ProjectNumbaFn.apply(
        means,
        quats_wxyz,
        log_scales,
        opacity_logits,
        sh_dc,
        sh_rest,
        T_cw,
        _camera_array(camera, near),
        sh_degree,
        cpu_threads() if threads is None else threads,
    )
    return Projected(
        means2d=means2d,
        cov2d=cov2d,
        conics=conics,
        depths=depths,
        opacities=opacities,
        colors=colors,
        in_front=in_front,
    )

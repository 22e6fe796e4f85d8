"""The compositors' one autograd boundary: what every compositor (torch, numba) takes and gives back.

A compositor is a forward function (:data:`CompositeForward`) that renders the splats and
returns, beside the images, a closure (:data:`CompositeBackward`) holding whatever its own
backward pass needs. :func:`apply_compositor` wraps it in a single ``torch.autograd.Function``,
so the argument list, the missing-cotangent handling and the layout of the per-Gaussian
gradients are written once, not once per compositor.

Per-Gaussian gradient layout, [N, 10]: mean x, mean y, conic a, b, c, opacity, r, g, b, z (the
order of the compositors' own tables).
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from memgs_ros.core.raster.tiles import TilePlan
from memgs_ros.core.raster.values import Splats2D

# backward(grads [5, H, W] dL/d (r, g, b, depth, alpha), background_needed) ->
# (dL/d splats [N, 10] in the layout above, dL/d background [3] or None)
CompositeBackward = Callable[[Tensor, bool], "tuple[Tensor, Tensor | None]"]
# forward(splats, background [3], plan) -> (colour [3, H, W], depth [H, W], alpha [H, W], backward)
CompositeForward = Callable[[Splats2D, Tensor, TilePlan], "tuple[Tensor, Tensor, Tensor, CompositeBackward]"]


class _CompositeFn(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, run: CompositeForward, plan: TilePlan, background: Tensor, *splat: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        color, depth, alpha, backward = run(Splats2D(*splat), background, plan)
        ctx.composite_backward = backward
        ctx.grad_dtype = splat[0].dtype
        return color, depth, alpha

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, v_color: Tensor | None, v_depth: Tensor | None,
                 v_alpha: Tensor | None) -> tuple[Any, ...]:
        # torch passes zeros for an output without a cotangent (materialised grads); None is still handled
        ref = next(t for t in (v_color, v_depth, v_alpha) if t is not None)
        h, w = ref.shape[-2:]
        parts = [
            v_color if v_color is not None else ref.new_zeros(3, h, w),
            (v_depth if v_depth is not None else ref.new_zeros(h, w))[None],
            (v_alpha if v_alpha is not None else ref.new_zeros(h, w))[None],
        ]
        grads = torch.cat([p.to(ctx.grad_dtype) for p in parts])  # [5, H, W]
        v_gauss, v_bg = ctx.composite_backward(grads, ctx.needs_input_grad[2])
        return (None, None, v_bg, v_gauss[:, 0:2], v_gauss[:, 2:5], v_gauss[:, 5], v_gauss[:, 6:9], v_gauss[:, 9])


def apply_compositor(run: CompositeForward, splats: Splats2D, background: Tensor,
                     plan: TilePlan) -> tuple[Tensor, Tensor, Tensor]:
    """``run`` as an autograd op: colour [3, H, W], depth [H, W] and alpha [H, W], differentiable
    w.r.t. every splat tensor and the background."""
    return _CompositeFn.apply(run, plan, background, *splats.contiguous())

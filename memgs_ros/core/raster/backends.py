"""The rasterizer backends, registered by name: what ``rasterize(..., backend=NAME)`` runs.

A :class:`Backend` renders :class:`~memgs_ros.core.gaussians.tensors.Gaussians` into a
:class:`~memgs_ros.core.raster.values.RenderOutput` and says whether it can run on a device now.
``backend="auto"`` takes the first registered backend whose ``auto`` accepts the tensors' device
(gsplat on CUDA when importable, numba on the CPU when importable, else torch). A new backend is
one :func:`register` call; nothing else changes.
"""
from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from memgs_ros.core.gaussians.tensors import Gaussians
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.raster.composite import composite
from memgs_ros.core.raster.composite_numba import NUMBA_TILE_SIZE, composite_numba
from memgs_ros.core.raster.gsplat_backend import gsplat_available, rasterize_gsplat
from memgs_ros.core.raster.projection import Projected, alpha_cutoff_sq, project_gaussians, screen_radii
from memgs_ros.core.raster.projection_numba import project_gaussians_numba
from memgs_ros.core.raster.rules import MIN_ALPHA
from memgs_ros.core.raster.tiles import TILE_SIZE, TilePlan, build_tile_plan, pairs_per_chunk_for
from memgs_ros.core.raster.values import RenderOutput
from memgs_ros.core.runtime.cpu import numba_available

# render(gaussians, T_cw [4, 4], camera, sh_degree, background [3] or None, near) -> RenderOutput
RenderFn = Callable[[Gaussians, Tensor, PinholeCamera, int, "Tensor | None", float], RenderOutput]


@dataclass(frozen=True)
class Backend:
    """name: what ``backend=`` says; render: see ``RenderFn``; why_not(device): "" when asking
    for it by name on tensors of that device can work, else the reason (one clause); auto(device):
    ``backend="auto"`` may take it there (asked in registration order)."""

    name: str
    render: RenderFn
    why_not: Callable[[torch.device], str]
    auto: Callable[[torch.device], bool]


REGISTRY: dict[str, Backend] = {}


def register(backend: Backend) -> None:
    REGISTRY[backend.name] = backend


def auto_backend(device: torch.device) -> Backend:
    """The backend ``backend="auto"`` takes for tensors on ``device``."""
    return next(b for b in REGISTRY.values() if b.auto(device))


def _tiled(project: Callable[..., Projected], compositor: Callable[..., tuple[Tensor, Tensor, Tensor]],
           tile_size: int) -> RenderFn:
    """A backend of the package's own: project, bin into tiles, composite."""

    def render(g: Gaussians, T_cw: Tensor, camera: PinholeCamera, sh_degree: int, background: Tensor | None,
               near: float) -> RenderOutput:
        means = g.means
        proj = project(g, T_cw, camera, sh_degree, near)
        if proj.means2d.requires_grad:
            proj.means2d.retain_grad()
        plan: TilePlan = build_tile_plan(
            proj.means2d, proj.cov2d, alpha_cutoff_sq(proj.opacities.detach(), MIN_ALPHA), proj.depths,
            proj.in_front, camera.width, camera.height, tile_size,
            pairs_per_chunk_for(means.device),  # only the torch compositor reads it
        )
        bg = background if background is not None else torch.zeros(3, dtype=means.dtype, device=means.device)
        color, depth, alpha = compositor(proj.splats(), bg, plan)
        visible = plan.gaussian_hit
        radii = torch.where(visible, screen_radii(proj.cov2d), torch.zeros_like(visible, dtype=torch.int32))
        return RenderOutput(color=color, depth=depth, alpha=alpha, means2d=proj.means2d, radii=radii, visible=visible)

    return render


def _numba_why_not(device: torch.device) -> str:
    if device.type != "cpu":
        return "the tensors are on CUDA" if device.type == "cuda" else f"the tensors are on {device}"
    return "" if numba_available() else "numba is not importable (or MEMGS_DISABLE_NUMBA is set)"


def _gsplat_why_not(_device: torch.device) -> str:
    return "" if gsplat_available() else "the gsplat package is not installed"


# In order of preference for backend="auto".
register(Backend("gsplat", rasterize_gsplat, _gsplat_why_not,
                 auto=lambda device: device.type == "cuda" and gsplat_available()))
# gsplat's packed mode: per-camera arrays of the visible Gaussians only (by name, not "auto").
register(Backend("gsplat_packed", functools.partial(rasterize_gsplat, packed=True), _gsplat_why_not,
                 auto=lambda _device: False))
# The compiled projection goes with the compiled compositor (same CPU, same dependency).
register(Backend("numba", _tiled(project_gaussians_numba, composite_numba, NUMBA_TILE_SIZE), _numba_why_not,
                 auto=lambda device: not _numba_why_not(device)))
register(Backend("torch", _tiled(project_gaussians, composite, TILE_SIZE), lambda _device: "",
                 auto=lambda _device: True))

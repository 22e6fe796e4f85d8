"""The gsplat adapter's conventions, checked on the CPU against a stand-in for gsplat.

gsplat only runs on CUDA (test_cuda.py runs the real one where a GPU is). What the adapter
must get right is the translation between the two conventions: activations, the SH layout,
the background, the depth mode, result shapes, the means2d gradient hook and the pixel-centre
convention (gsplat evaluates pixel (i, j) at (j + 0.5, i + 0.5); this package at (j, i)). The
stand-in below is ``gsplat.rasterization`` as its documentation and kernels define it, built
from the package's projection and brute-force reference compositor: raw parameters in, pixel centres at +0.5,
[C, ...] batched outputs. An adapter that passed K unchanged (the first GPU parity failure)
renders half a pixel off here too.
"""
from __future__ import annotations

import dataclasses
import sys
import types

import pytest
import torch
from test_raster import CAM_64, CAM_OFFCENTRE, PARAM_NAMES, _scene

from memgs_ros.core.gaussians.tensors import Gaussians
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.raster import rasterize
from memgs_ros.core.raster.projection import project_gaussians, screen_radii
from memgs_ros.core.raster.reference import _composite_reference


def _fake_rasterization(
    means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane=0.01,
    sh_degree=None, packed=True, backgrounds=None, render_mode="RGB", **_: object,
):
    """gsplat.rasterization's contract for one camera (classic 3DGS, RGB+D)."""
    assert viewmats.shape == (1, 4, 4) and Ks.shape == (1, 3, 3)
    assert render_mode == "RGB+D" and sh_degree is not None
    assert opacities.dim() == 1 and scales.shape == means.shape  # activated, not logits
    # gsplat 1.5.3's packed rasterize_to_pixels checks backgrounds against [channels], so the
    # [1, channels] that rasterization() hands it fails there (seen on an H200).
    assert not (packed and backgrounds is not None), "gsplat 1.5.3 packed mode fails on backgrounds"
    K = Ks[0]
    cam = PinholeCamera(width, height, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    op = opacities.clamp(1e-7, 1 - 1e-7)
    g = Gaussians(means, quats, torch.log(scales), torch.log(op / (1 - op))[:, None], colors[:, :1], colors[:, 1:])
    proj = project_gaussians(g, viewmats[0], cam, sh_degree, near_plane)
    bg = torch.zeros(3, dtype=means.dtype) if backgrounds is None else backgrounds[0]
    # gsplat's pixel (i, j) is evaluated at (j + 0.5, i + 0.5): the reference compositor (pixel
    # centres at (j, i)) draws that image from means moved by -0.5 px.
    hit_any = screen_radii(proj.cov2d) > 0
    ids = torch.nonzero(hit_any).reshape(-1)
    if packed:  # [nnz, 2] rows of the Gaussians the camera sees; what the compositor reads
        packed_2d = proj.means2d[ids]
        means2d_all = torch.zeros_like(proj.means2d).index_put((ids,), packed_2d)
    else:  # [1, N, 2]
        packed_2d = proj.means2d[None]
        means2d_all = packed_2d[0]
    # gsplat's pixel (i, j) is evaluated at (j + 0.5, i + 0.5): the reference compositor (pixel
    # centres at (j, i)) draws that image from means moved by -0.5 px.
    color, depth, alpha, hit = _composite_reference(proj.splats()._replace(means2d=means2d_all - 0.5), bg,
                                                    proj.in_front, width, height)
    renders = torch.cat([color.permute(1, 2, 0), depth[..., None]], dim=-1)[None]  # [1, H, W, 4]
    r = torch.where(hit, screen_radii(proj.cov2d), torch.zeros_like(hit, dtype=torch.int32))
    radii = torch.stack([r, r], dim=-1)  # [N, 2] (gsplat >= 1.5)
    if packed:
        meta = {"means2d": packed_2d, "radii": radii[ids], "gaussian_ids": ids.int(),
                "camera_ids": torch.zeros_like(ids)}
    else:
        meta = {"means2d": packed_2d, "radii": radii[None]}
    return renders, alpha[None, ..., None], meta


@pytest.fixture()
def fake_gsplat(monkeypatch: pytest.MonkeyPatch) -> None:
    module = types.ModuleType("gsplat")
    module.rasterization = _fake_rasterization  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "gsplat", module)


def _loss(out) -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    return sum((img * torch.randn(img.shape, generator=g, dtype=img.dtype)).sum()
               for img in (out.color, out.depth, out.alpha))


@pytest.mark.parametrize("backend", ["gsplat", "gsplat_packed"])
@pytest.mark.parametrize("cam", [CAM_64, CAM_OFFCENTRE], ids=["centred", "offcentre"])
def test_gsplat_adapter_renders_what_the_torch_backend_renders(fake_gsplat: None, cam: PinholeCamera,
                                                               backend: str) -> None:
    params, T = _scene(80, seed=5, sh_deg_max=1)
    p_t = [p.detach().clone().requires_grad_() for p in params]
    p_g = [p.detach().clone().requires_grad_() for p in params]
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    ours = rasterize(Gaussians(*p_t), T, cam, 1, background=bg, backend="torch")
    theirs = rasterize(Gaussians(*p_g), T, cam, 1, background=bg, backend=backend)
    for name in ("color", "depth", "alpha"):
        torch.testing.assert_close(getattr(theirs, name), getattr(ours, name), atol=1e-9, rtol=0, msg=name)
    seen = ours.visible  # packed: the Gaussians the camera does not see have no screen position
    torch.testing.assert_close(theirs.means2d[seen], ours.means2d[seen], atol=1e-9, rtol=0)
    if backend == "gsplat":
        torch.testing.assert_close(theirs.means2d, ours.means2d, atol=1e-9, rtol=0)
    assert 0 < int(seen.sum()) < len(seen)  # the scene has Gaussians on both sides
    assert theirs.radii.dtype == torch.int32 and torch.equal(theirs.radii, ours.radii)
    assert torch.equal(theirs.visible, theirs.radii > 0)
    _loss(ours).backward()
    _loss(theirs).backward()
    for name, a, b in zip(PARAM_NAMES, p_t, p_g):
        torch.testing.assert_close(b.grad, a.grad, atol=1e-8, rtol=1e-6, msg=name)
    # The densification statistic arrives in means2d.grad through the adapter's hook.
    assert theirs.means2d.grad is not None
    torch.testing.assert_close(theirs.means2d.grad, ours.means2d.grad, atol=1e-8, rtol=1e-6)


def test_unshifted_intrinsics_would_be_caught(fake_gsplat: None, monkeypatch: pytest.MonkeyPatch) -> None:
    """The convention check above can fail: K passed unchanged gives a half-pixel shift that the
    parity tolerance of test_cuda (mean |diff| < 2e-3) does not accept."""
    from memgs_ros.core.raster import gsplat_backend

    monkeypatch.setattr(gsplat_backend, "GSPLAT_PIXEL_CENTRE", 0.0)
    params, T = _scene(200, seed=5, sh_deg_max=1, dtype=torch.float32)
    bg = torch.tensor([0.1, 0.2, 0.3])
    with torch.no_grad():
        ours = rasterize(Gaussians(*params), T, CAM_64, 1, background=bg, backend="torch")
        theirs = rasterize(Gaussians(*params), T, CAM_64, 1, background=bg, backend="gsplat")
    worst = max(float((getattr(ours, n) - getattr(theirs, n)).abs().mean()) for n in ("color", "depth", "alpha"))
    assert worst > 2e-3


def test_gsplat_intrinsics_shift_only_the_principal_point() -> None:
    from memgs_ros.core.raster.gsplat_backend import gsplat_intrinsics

    cam = dataclasses.replace(CAM_64)
    K = gsplat_intrinsics(cam, torch.float64, torch.device("cpu"))
    assert K.tolist() == [[cam.fx, 0.0, cam.cx + 0.5], [0.0, cam.fy, cam.cy + 0.5], [0.0, 0.0, 1.0]]

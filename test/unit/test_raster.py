"""Tests of the Gaussian rasterizer: tiled custom-autograd path vs the brute-force reference,
finite differences, projection geometry, and edge cases. CPU, small images, generated data."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from memgs_ros.core.gaussians.tensors import Gaussians
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.poses import quat_wxyz_to_rotmat_torch
from memgs_ros.core.raster import RenderOutput, _rasterize_reference, rasterize
from memgs_ros.core.raster.composite import composite
from memgs_ros.core.raster.projection import alpha_cutoff_sq, project_gaussians
from memgs_ros.core.raster.rules import MIN_ALPHA
from memgs_ros.core.raster.tiles import build_tile_plan
from memgs_ros.core.raster.values import Splats2D

PARAM_NAMES = ("means", "quats_wxyz", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


def _pose_cw(seed: int, dtype: torch.dtype) -> torch.Tensor:
    """A random world-to-camera pose [4, 4] (rotation by up to ~30 degrees, small translation)."""
    g = torch.Generator().manual_seed(seed)
    q = torch.cat([torch.ones(1, dtype=dtype), 0.3 * torch.randn(3, generator=g, dtype=dtype)])
    T = torch.eye(4, dtype=dtype)
    T[:3, :3] = quat_wxyz_to_rotmat_torch(q[None])[0]
    T[:3, 3] = 0.2 * torch.randn(3, generator=g, dtype=dtype)
    return T


def _scene(
    n: int,
    seed: int,
    dtype: torch.dtype = torch.float64,
    sh_deg_max: int = 1,
    spread: float = 1.0,
    depth: float = 4.0,
    T_cw: torch.Tensor | None = None,
) -> tuple[list[torch.Tensor], torch.Tensor]:
    """n random Gaussians in front of the camera (camera z ~ depth), as leaf tensors needing grad.

    spread scales the lateral extent: > 1 puts many Gaussians partly or fully off-screen.
    Returns ([means, quats, log_scales, opacity_logits, sh_dc, sh_rest], T_cw).
    """
    g = torch.Generator().manual_seed(seed)
    T = _pose_cw(seed + 1000, dtype) if T_cw is None else T_cw
    p_c = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.0 * spread, 0.7 * spread, 0.5], dtype=dtype)
    p_c[:, 2] += depth
    R, t = T[:3, :3], T[:3, 3]
    means = (p_c - t) @ R  # world = R^T (p_c - t)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    log_scales = torch.log(torch.rand(n, 3, generator=g, dtype=dtype) * 0.2 + 0.03)
    opacity_logits = torch.randn(n, 1, generator=g, dtype=dtype) * 2.0
    sh_dc = torch.randn(n, 1, 3, generator=g, dtype=dtype)
    sh_rest = 0.3 * torch.randn(n, (sh_deg_max + 1) ** 2 - 1, 3, generator=g, dtype=dtype)
    params = [p.requires_grad_() for p in (means, quats, log_scales, opacity_logits, sh_dc, sh_rest)]
    return params, T


def _loss(out: RenderOutput, seed: int) -> torch.Tensor:
    """A random linear functional of the three images (random cotangents)."""
    g = torch.Generator().manual_seed(seed)
    dtype = out.color.dtype
    total = (out.color * torch.randn(out.color.shape, generator=g, dtype=dtype)).sum()
    total = total + (out.depth * torch.randn(out.depth.shape, generator=g, dtype=dtype)).sum()
    return total + (out.alpha * torch.randn(out.alpha.shape, generator=g, dtype=dtype)).sum()


CAM_64 = PinholeCamera(64, 48, 50.0, 52.0, 30.3, 25.7)
# Principal point far from the centre: catches code that assumes a centred frustum.
CAM_OFFCENTRE = PinholeCamera(48, 40, 45.0, 40.0, 12.0, 31.0)
CAM_32 = PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5)


def _compare(
    params, T_cw, cam, deg, background=None, atol_fwd=1e-10, rtol_grad=1e-8, seed=7, backend="torch"
) -> RenderOutput:
    out = rasterize(Gaussians(*params), T_cw, cam, deg, background=background, backend=backend)
    ref = _rasterize_reference(Gaussians(*params), T_cw, cam, deg, background=background)
    for name in ("color", "depth", "alpha"):
        a, b = getattr(out, name), getattr(ref, name)
        assert a.shape == b.shape
        err = (a - b).abs().max().item() if a.numel() else 0.0
        assert err <= atol_fwd, f"{name}: max |fast - reference| = {err}"
    inputs = list(params) + ([T_cw] if T_cw.requires_grad else [])
    g_out = torch.autograd.grad(_loss(out, seed), inputs + [out.means2d], allow_unused=True, retain_graph=True)
    g_ref = torch.autograd.grad(_loss(ref, seed), inputs + [ref.means2d], allow_unused=True)
    names = list(PARAM_NAMES) + (["T_cw"] if T_cw.requires_grad else []) + ["means2d"]
    for name, a, b in zip(names, g_out, g_ref):
        assert (a is None) == (b is None), name
        if a is None:
            continue
        scale = max(1.0, b.abs().max().item())
        err = (a - b).abs().max().item() if a.numel() else 0.0
        assert err <= rtol_grad * scale, f"d/d{name}: max error {err} (scale {scale})"
    assert torch.equal(out.radii[ref.visible], ref.radii[ref.visible])
    # The tiled path may call a Gaussian visible whose support only grazes the image (binning
    # margin), never the other way round.
    assert not (ref.visible & ~out.visible).any()
    return out


@pytest.mark.parametrize(
    "n,cam,deg,seed",
    [(5, CAM_32, 0, 1), (60, CAM_64, 1, 2), (200, CAM_64, 3, 3), (120, CAM_OFFCENTRE, 2, 4)],
)
def test_matches_reference_float64(n: int, cam: PinholeCamera, deg: int, seed: int) -> None:
    params, T = _scene(n, seed, sh_deg_max=3)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    out = _compare(params, T, cam, deg, background=bg)
    assert out.alpha.max() > 0.5  # the scene is not empty, so the comparison means something


def test_matches_reference_float32() -> None:
    params, T = _scene(150, 11, dtype=torch.float32, sh_deg_max=2)
    _compare(params, T, CAM_64, 2, atol_fwd=1e-4, rtol_grad=1e-3)


def test_offscreen_and_large_gaussians() -> None:
    # Lateral spread 3x the frustum and some Gaussians close to the camera (large on screen).
    params, T = _scene(150, 21, spread=3.0, depth=2.0)
    with torch.no_grad():
        params[2][:20] += 1.5  # a few big ones
    out = _compare(params, T, CAM_OFFCENTRE, 1)
    proj_u = out.means2d.detach()[:, 0]
    partly = out.visible & ((proj_u < 0) | (proj_u >= CAM_OFFCENTRE.width))
    assert partly.any(), "the scene must contain visible Gaussians centred off-screen"


def test_pose_gradient_matches_reference() -> None:
    params, T = _scene(40, 31)
    T = T.clone().requires_grad_()
    _compare(params, T, CAM_32, 1)


@pytest.mark.parametrize("deg", [0, 1, 2, 3])
def test_sh_degrees(deg: int) -> None:
    params, T = _scene(30, 40 + deg, sh_deg_max=3)
    out = _compare(params, T, CAM_32, deg)
    # Bands above the active degree must not influence the image.
    if deg < 3:
        g = torch.autograd.grad(out.color.sum(), params[5], allow_unused=True)[0]
        n_active = (deg + 1) ** 2 - 1
        if deg == 0:
            assert g is None  # sh_rest is not used at all
        else:
            assert g[:, n_active:].abs().max() == 0
            assert g[:, :n_active].abs().max() > 0


@pytest.mark.parametrize("deg", [1, 2, 3])
def test_sh_hand_written_backward_matches_autograd(deg: int) -> None:
    from memgs_ros.core.raster.sh import _eval_sh_colors_reference, eval_sh_colors

    g = torch.Generator().manual_seed(deg)
    n = 64
    dc = torch.randn(n, 1, 3, dtype=torch.float64, generator=g).requires_grad_()
    rest = torch.randn(n, 15, 3, dtype=torch.float64, generator=g).requires_grad_()
    d = torch.randn(n, 3, dtype=torch.float64, generator=g).requires_grad_()
    cot = torch.randn(n, 3, dtype=torch.float64, generator=g)
    results = []
    for fn in (eval_sh_colors, _eval_sh_colors_reference):
        rgb = fn(dc, rest, d / d.norm(dim=-1, keepdim=True), deg)
        results.append((rgb, torch.autograd.grad((rgb * cot).sum(), [dc, rest, d])))
    (fast, g_fast), (ref, g_ref) = results
    assert (ref == 0).any(), "some colours should hit the clamp at 0"
    torch.testing.assert_close(fast, ref, rtol=0, atol=1e-12)
    for a, b in zip(g_fast, g_ref):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_degree_zero_without_rest_coefficients() -> None:
    params, T = _scene(20, 50, sh_deg_max=0)
    assert params[5].shape == (20, 0, 3)
    _compare(params, T, CAM_32, 0)


def test_finite_differences_float64() -> None:
    """Directional derivatives of the tiled path against central differences, per parameter."""
    params, T = _scene(12, 61, sh_deg_max=1)
    cam = CAM_32
    out = rasterize(Gaussians(*params), T, cam, 1, backend="torch")
    grads = torch.autograd.grad(_loss(out, 3), params)
    g = torch.Generator().manual_seed(9)
    eps = 1e-6
    for name, p, gp in zip(PARAM_NAMES, params, grads):
        for _ in range(2):
            d = torch.randn(p.shape, generator=g, dtype=p.dtype)
            with torch.no_grad():
                shifted = []
                for sign in (1.0, -1.0):
                    moved = [q + sign * eps * d if q is p else q for q in params]
                    shifted.append(_loss(rasterize(Gaussians(*moved), T, cam, 1, backend="torch"), 3).item())
            fd = (shifted[0] - shifted[1]) / (2 * eps)
            an = (gp * d).sum().item()
            assert abs(fd - an) <= 1e-5 * max(1.0, abs(an)), f"{name}: finite diff {fd} vs analytic {an}"


def test_means2d_grad_populated() -> None:
    params, T = _scene(50, 71)
    out = rasterize(Gaussians(*params), T, CAM_64, 1, backend="torch")
    _loss(out, 1).backward()
    assert out.means2d.grad is not None and out.means2d.grad.shape == (50, 2)
    assert (out.means2d.grad[out.visible].abs().sum(-1) > 0).any()
    assert (out.means2d.grad[~out.visible] == 0).all()


def test_no_gaussians() -> None:
    params, T = _scene(0, 1)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out = rasterize(Gaussians(*params), T, CAM_32, 1, background=bg, backend="torch")
    assert out.color.shape == (3, 24, 32) and out.depth.shape == (24, 32) and out.alpha.shape == (24, 32)
    assert torch.allclose(out.color, bg[:, None, None].expand(3, 24, 32))
    assert (out.depth == 0).all() and (out.alpha == 0).all()
    assert out.radii.shape == (0,) and out.visible.shape == (0,)
    g = torch.autograd.grad(out.color.sum(), params[0])[0]
    assert g.shape == (0, 3)


def test_all_behind_camera() -> None:
    params, T = _scene(30, 81, depth=-3.0)
    out = rasterize(Gaussians(*params), T, CAM_32, 1, backend="torch")
    assert (out.color == 0).all() and (out.alpha == 0).all() and (out.depth == 0).all()
    assert not out.visible.any() and (out.radii == 0).all()
    grads = torch.autograd.grad(out.color.sum() + out.depth.sum(), params, allow_unused=True)
    for name, gp in zip(PARAM_NAMES, grads):
        assert gp is None or (torch.isfinite(gp).all() and (gp == 0).all()), name


def test_near_plane_culls() -> None:
    params, T = _scene(40, 91, depth=1.0)
    out_near = rasterize(Gaussians(*params), T, CAM_32, 0, near=0.01, backend="torch")
    out_far = rasterize(Gaussians(*params), T, CAM_32, 0, near=100.0, backend="torch")
    assert out_near.visible.any() and not out_far.visible.any()


def test_projection_geometry() -> None:
    """means2d is the pinhole projection; cov2d is J Sigma_c J^T + 0.3 I with J from autograd."""
    params, T = _scene(25, 101, sh_deg_max=0)
    cam = CAM_OFFCENTRE
    means, quats, log_scales = params[0].detach(), params[1].detach(), params[2].detach()
    proj = project_gaussians(Gaussians(*[p.detach() for p in params]), T, cam, 0, 0.01)
    p_c = means @ T[:3, :3].T + T[:3, 3]
    u, v = cam.project(p_c.numpy())
    np.testing.assert_allclose(proj.means2d[:, 0].numpy(), u, rtol=0, atol=1e-9)
    np.testing.assert_allclose(proj.means2d[:, 1].numpy(), v, rtol=0, atol=1e-9)

    def pix(p: torch.Tensor) -> torch.Tensor:
        return torch.stack([cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy])

    inside = (proj.means2d[:, 0].abs() < 40) & (proj.means2d[:, 1].abs() < 40)  # no FOV clamp active
    for i in torch.nonzero(inside).squeeze(1).tolist():
        J = torch.autograd.functional.jacobian(pix, p_c[i])  # [2, 3]
        R = quat_wxyz_to_rotmat_torch(quats[i : i + 1])[0]
        S = torch.diag(torch.exp(log_scales[i]))
        sigma_c = T[:3, :3] @ R @ S @ S @ R.T @ T[:3, :3].T
        cov = J @ sigma_c @ J.T + 0.3 * torch.eye(2, dtype=torch.float64)
        expect = torch.stack([cov[0, 0], cov[0, 1], cov[1, 1]])
        torch.testing.assert_close(proj.cov2d[i], expect, rtol=1e-10, atol=1e-10)


def test_image_does_not_depend_on_tiles_or_threads() -> None:
    """Exact ellipse binning keeps every alpha >= 1/255; chunking and threads change nothing."""
    params, T = _scene(120, 111)
    cam = CAM_64
    proj = project_gaussians(Gaussians(*params), T, cam, 1, 0.01)
    cut = alpha_cutoff_sq(proj.opacities.detach(), MIN_ALPHA)
    bg = torch.zeros(3, dtype=torch.float64)
    images = []
    for tile, chunk, workers in [(4, 1 << 18, 1), (8, 2000, 2), (16, 500, 3)]:
        plan = build_tile_plan(proj.means2d, proj.cov2d, cut, proj.depths, proj.in_front, 64, 48, tile, chunk)
        images.append(composite(proj.splats(), bg, plan, workers))
    for other in images[1:]:
        for a, b in zip(images[0], other):
            assert (a - b).abs().max() < 1e-12
    # Backward on several threads: the same gradients as on one.
    plan = build_tile_plan(proj.means2d, proj.cov2d, cut, proj.depths, proj.in_front, 64, 48, 4, 3000)
    assert len(plan.chunks) > 3
    inputs = (proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths)
    grads = []
    for workers in (1, 3):
        color, depth, alpha = composite(Splats2D(*inputs), bg, plan, workers)
        loss = (color * color).sum() + depth.sum() + alpha.sum()
        grads.append(torch.autograd.grad(loss, inputs, retain_graph=True))
    for a, b in zip(*grads):
        assert torch.equal(a, b)


@pytest.mark.parametrize("width,height", [(1, 1), (33, 17), (7, 40)])
def test_odd_image_sizes(width: int, height: int) -> None:
    cam = PinholeCamera(width, height, 30.0, 30.0, width / 2 - 0.3, height / 2 + 0.2)
    params, T = _scene(40, 171 + width)
    _compare(params, T, cam, 1)


def test_backward_recomputes_when_pairs_exceed_budget(monkeypatch: pytest.MonkeyPatch) -> None:
    """Above the saved-pairs budget alpha/T are recomputed per chunk: same gradients."""
    import memgs_ros.core.raster.composite as composite_mod

    params, T = _scene(80, 141)
    out = rasterize(Gaussians(*params), T, CAM_64, 1, backend="torch")
    saved = torch.autograd.grad(_loss(out, 2), params)
    monkeypatch.setattr(composite_mod, "SAVED_PAIRS_BUDGET_BYTES", 0)
    out2 = rasterize(Gaussians(*params), T, CAM_64, 1, backend="torch")
    recomputed = torch.autograd.grad(_loss(out2, 2), params)
    for a, b in zip(saved, recomputed):
        assert torch.equal(a, b)


def test_render_without_grad_matches() -> None:
    params, T = _scene(60, 151)
    with_grad = rasterize(Gaussians(*params), T, CAM_64, 1, backend="torch")
    with torch.no_grad():
        no_grad = rasterize(Gaussians(*params), T, CAM_64, 1, backend="torch")
    assert not no_grad.color.requires_grad
    for name in ("color", "depth", "alpha"):
        assert torch.equal(getattr(with_grad, name).detach(), getattr(no_grad, name))


def test_tile_lists_are_front_to_back() -> None:
    params, T = _scene(80, 121)
    proj = project_gaussians(Gaussians(*[p.detach() for p in params]), T, CAM_64, 1, 0.01)
    cut = alpha_cutoff_sq(proj.opacities, MIN_ALPHA)
    plan = build_tile_plan(proj.means2d, proj.cov2d, cut, proj.depths, proj.in_front, 64, 48)
    z = proj.depths[plan.pair_gid]
    same_tile = plan.pair_tile[1:] == plan.pair_tile[:-1]
    assert (z[1:][same_tile] >= z[:-1][same_tile]).all()
    assert (plan.pair_tile[1:] >= plan.pair_tile[:-1]).all()
    covered = torch.cat([c.tiles for c in plan.chunks])
    assert torch.equal(torch.sort(covered).values, torch.nonzero(plan.tile_count).squeeze(1))


def test_bad_shapes_are_refused() -> None:
    params, T = _scene(10, 131)
    bad = list(params)
    bad[1] = bad[1][:, :3]
    with pytest.raises(ValueError, match=r"quats_wxyz must have shape \[10, 4\], got \[10, 3\]"):
        rasterize(Gaussians(*bad), T, CAM_32, 1)
    with pytest.raises(ValueError, match="sh_degree 2 needs"):
        rasterize(Gaussians(*params), T, CAM_32, 2)
    with pytest.raises(ValueError, match="backend"):
        rasterize(Gaussians(*params), T, CAM_32, 1, backend="opengl")


def test_gsplat_backend_refused_without_gsplat() -> None:
    from memgs_ros.core.raster.gsplat_backend import gsplat_available
    from memgs_ros.errors import ConfigError

    if gsplat_available():
        pytest.skip("gsplat is installed here; the refusal path cannot be exercised")
    params, T = _scene(5, 161)
    with pytest.raises(ConfigError, match="gsplat package is not installed"):
        rasterize(Gaussians(*params), T, CAM_32, 1, backend="gsplat")
    # "auto" on CPU falls back to a CPU compositor.
    assert rasterize(Gaussians(*params), T, CAM_32, 1, backend="auto").color.shape == (3, 24, 32)


def test_opaque_front_gaussian_terminates() -> None:
    """A wall of opaque Gaussians hides everything behind it (early termination at T < 1e-4)."""
    dtype = torch.float64
    ys, xs = torch.meshgrid(torch.linspace(-1.0, 1.0, 6, dtype=dtype), torch.linspace(-1.3, 1.3, 7, dtype=dtype), indexing="ij")
    layer = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)
    wall = torch.cat([torch.cat([layer, torch.full((42, 1), z, dtype=dtype)], -1) for z in (2.0, 2.1, 2.2)])
    behind = torch.tensor([[0.0, 0.0, 3.0]], dtype=dtype)
    means = torch.cat([wall, behind]).requires_grad_()
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=dtype).repeat(n, 1).requires_grad_()
    log_scales = torch.full((n, 3), math.log(0.3), dtype=dtype).requires_grad_()
    opac = torch.full((n, 1), 8.0, dtype=dtype).requires_grad_()
    dc = torch.randn(n, 1, 3, dtype=dtype, generator=torch.Generator().manual_seed(0)).requires_grad_()
    rest = torch.zeros(n, 0, 3, dtype=dtype).requires_grad_()
    T = torch.eye(4, dtype=dtype)
    out = _compare([means, quats, log_scales, opac, dc, rest], T, CAM_32, 0)
    g = torch.autograd.grad(out.color.sum(), dc)[0]
    assert g[-1].abs().max() == 0  # the hidden Gaussian gets no gradient
    assert out.alpha.min() > 0.998


# ------------------------------------------------------------------ numba compositor
def _numba() -> None:
    pytest.importorskip("numba")
    from memgs_ros.core.runtime.cpu import numba_available

    if not numba_available():
        pytest.skip("numba is disabled here (MEMGS_DISABLE_NUMBA)")


def _opaque_stack(dtype: torch.dtype = torch.float64) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Three layers of near-opaque Gaussians (opacity 0.9997: alpha clamps at 0.99) over one hidden
    Gaussian: nearly every pixel terminates early."""
    ys, xs = torch.meshgrid(
        torch.linspace(-1.0, 1.0, 6, dtype=dtype), torch.linspace(-1.3, 1.3, 7, dtype=dtype), indexing="ij"
    )
    layer = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)
    wall = torch.cat([torch.cat([layer, torch.full((42, 1), z, dtype=dtype)], -1) for z in (2.0, 2.1, 2.2)])
    means = torch.cat([wall, torch.tensor([[0.0, 0.0, 3.0]], dtype=dtype)])
    n = means.shape[0]
    g = torch.Generator().manual_seed(0)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=dtype).repeat(n, 1) + 0.1 * torch.randn(n, 4, generator=g, dtype=dtype)
    log_scales = torch.full((n, 3), math.log(0.3), dtype=dtype) + 0.2 * torch.randn(n, 3, generator=g, dtype=dtype)
    opac = torch.full((n, 1), 8.0, dtype=dtype)
    dc = torch.randn(n, 1, 3, dtype=dtype, generator=g)
    rest = 0.3 * torch.randn(n, 3, 3, dtype=dtype, generator=g)
    params = [p.requires_grad_() for p in (means, quats, log_scales, opac, dc, rest)]
    return params, torch.eye(4, dtype=dtype)


@pytest.mark.parametrize(
    "n,cam,deg,seed",
    [(5, CAM_32, 0, 1), (200, CAM_64, 3, 3), (120, CAM_OFFCENTRE, 2, 4)],
)
def test_numba_matches_reference_float64(n: int, cam: PinholeCamera, deg: int, seed: int) -> None:
    _numba()
    params, T = _scene(n, seed, sh_deg_max=3)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    out = _compare(params, T, cam, deg, background=bg, backend="numba")
    assert out.alpha.max() > 0.5


def test_numba_matches_reference_opaque_stack() -> None:
    """Early termination everywhere, alpha clamped at 0.99, a hidden Gaussian without gradient."""
    _numba()
    params, T = _opaque_stack()
    out = _compare(params, T, CAM_32, 1, background=torch.tensor([0.3, 0.1, 0.7], dtype=torch.float64), backend="numba")
    assert out.alpha.min() > 0.998
    assert torch.autograd.grad(out.color.sum(), params[4])[0][-1].abs().max() == 0


def test_numba_matches_reference_float32() -> None:
    _numba()
    params, T = _scene(150, 11, dtype=torch.float32, sh_deg_max=2)
    _compare(params, T, CAM_64, 2, atol_fwd=1e-4, rtol_grad=1e-3, backend="numba")


def test_numba_offscreen_large_and_odd_sizes() -> None:
    _numba()
    params, T = _scene(150, 21, spread=3.0, depth=2.0)
    with torch.no_grad():
        params[2][:20] += 1.5
    _compare(params, T, CAM_OFFCENTRE, 1, backend="numba")
    cam = PinholeCamera(33, 17, 30.0, 30.0, 16.2, 8.7)
    params, T = _scene(40, 204)
    _compare(params, T, cam, 1, backend="numba")


@pytest.mark.parametrize("scene", ["random", "opaque"])
@pytest.mark.parametrize("tile", [4, 16])
def test_numba_compositor_matches_torch_compositor(scene: str, tile: int) -> None:
    """Same plan, both compositors: every output and the gradient of every input, background included."""
    _numba()
    from memgs_ros.core.raster.composite_numba import composite_numba

    params, T = _scene(150, 301) if scene == "random" else _opaque_stack()
    cam = CAM_64 if scene == "random" else CAM_32
    proj = project_gaussians(Gaussians(*params), T, cam, 1, 0.01)
    cut = alpha_cutoff_sq(proj.opacities.detach(), MIN_ALPHA)
    plan = build_tile_plan(proj.means2d, proj.cov2d, cut, proj.depths, proj.in_front, cam.width, cam.height, tile)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64, requires_grad=True)
    inputs = (proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths, bg)
    g = torch.Generator().manual_seed(5)
    results = []
    for fn in (composite_numba, composite):
        outs = fn(Splats2D(*inputs[:5]), inputs[5], plan)
        cot = [torch.randn(o.shape, generator=g, dtype=o.dtype) for o in outs]
        g.manual_seed(5)
        results.append((outs, torch.autograd.grad(outs, inputs, cot, retain_graph=True)))
    (fast, v_fast), (ref, v_ref) = results
    for a, b in zip(fast, ref):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    for name, a, b in zip(("means2d", "conics", "opacities", "colors", "depths", "background"), v_fast, v_ref):
        scale = max(1.0, b.abs().max().item())
        assert (a - b).abs().max().item() <= 1e-10 * scale, name


def test_numba_threads_and_binning_are_deterministic(monkeypatch: pytest.MonkeyPatch) -> None:
    """Binning gives the torch expansion's plan exactly; results do not depend on the thread count."""
    _numba()
    import memgs_ros.core.raster.tiles as tiles_mod
    from memgs_ros.core.raster.composite_numba import composite_numba

    params, T = _scene(300, 311, spread=2.0)
    proj = project_gaussians(Gaussians(*params), T, CAM_64, 1, 0.01)
    cut = alpha_cutoff_sq(proj.opacities.detach(), MIN_ALPHA)
    args = (proj.means2d, proj.cov2d, cut, proj.depths, proj.in_front, 64, 48)
    for tile in (4, 16):
        plan = build_tile_plan(*args, tile)
        with monkeypatch.context() as m:
            m.setattr(tiles_mod, "_numba_binning", lambda device: False)
            plan_torch = build_tile_plan(*args, tile)
        assert plan.num_pairs > 0
        for field in ("pair_gid", "pair_tile", "tile_start", "tile_count", "gaussian_hit"):
            assert torch.equal(getattr(plan, field), getattr(plan_torch, field)), field
    inputs = (proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths)
    bg = torch.zeros(3, dtype=torch.float64)
    results = []
    for threads in (1, 3):
        color, depth, alpha = composite_numba(Splats2D(*inputs), bg, plan, threads=threads)
        loss = (color * color).sum() + depth.sum() + alpha.sum()
        results.append((color, depth, alpha) + torch.autograd.grad(loss, inputs, retain_graph=True))
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_numba_edge_cases() -> None:
    _numba()
    params, T = _scene(0, 1)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out = rasterize(Gaussians(*params), T, CAM_32, 1, background=bg, backend="numba")
    assert torch.allclose(out.color, bg[:, None, None].expand(3, 24, 32))
    assert (out.alpha == 0).all() and torch.autograd.grad(out.color.sum(), params[0])[0].shape == (0, 3)
    params, T = _scene(30, 81, depth=-3.0)
    out = rasterize(Gaussians(*params), T, CAM_32, 1, backend="numba")
    assert (out.color == 0).all() and not out.visible.any()
    params, T = _scene(60, 151)
    with torch.no_grad():
        no_grad = rasterize(Gaussians(*params), T, CAM_64, 1, backend="numba")
    with_grad = rasterize(Gaussians(*params), T, CAM_64, 1, backend="numba")
    for name in ("color", "depth", "alpha"):
        assert torch.equal(getattr(with_grad, name).detach(), getattr(no_grad, name))


def test_backend_selection_without_numba(numba_off: None) -> None:
    """Without numba, "auto" renders with the torch compositor and "numba" is refused by name."""
    from memgs_ros.errors import ConfigError

    params, T = _scene(20, 321)

    auto = rasterize(Gaussians(*params), T, CAM_32, 1)
    torch_out = rasterize(Gaussians(*params), T, CAM_32, 1, backend="torch")
    assert torch.equal(auto.color, torch_out.color)
    with pytest.raises(ConfigError, match="backend 'numba' was asked for but numba is not importable"):
        rasterize(Gaussians(*params), T, CAM_32, 1, backend="numba")


def test_gpu_chunk_schedule_matches_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    """The schedule a GPU gets (CUDA_PAIRS_PER_CHUNK: a few big chunks instead of many small ones)
    renders and differentiates exactly like the brute-force reference, here on the CPU."""
    from memgs_ros.core.raster import tiles

    cam = PinholeCamera(160, 120, 120.0, 118.0, 79.2, 60.7)
    params, T = _scene(400, 191, spread=1.4)
    proj = project_gaussians(Gaussians(*params), T, cam, 1, 0.01)
    cut = alpha_cutoff_sq(proj.opacities.detach(), MIN_ALPHA)
    chunks = {}
    for pairs in (tiles.PAIRS_PER_CHUNK // 64, tiles.CUDA_PAIRS_PER_CHUNK):
        plan = build_tile_plan(proj.means2d, proj.cov2d, cut, proj.depths, proj.in_front, cam.width, cam.height,
                               tiles.TILE_SIZE, pairs)
        chunks[pairs] = len(plan.chunks)
    assert chunks[tiles.CUDA_PAIRS_PER_CHUNK] == 1 < chunks[tiles.PAIRS_PER_CHUNK // 64]
    monkeypatch.setenv(tiles.CHUNK_PAIRS_ENV, str(tiles.CUDA_PAIRS_PER_CHUNK))
    bg = torch.tensor([0.3, 0.1, 0.6], dtype=torch.float64)
    out = _compare(params, T, cam, 1, background=bg)
    assert out.alpha.max() > 0.5


def test_chunk_size_by_device(monkeypatch: pytest.MonkeyPatch) -> None:
    from memgs_ros.core.raster import tiles
    from memgs_ros.errors import ConfigError

    monkeypatch.delenv(tiles.CHUNK_PAIRS_ENV, raising=False)
    assert tiles.pairs_per_chunk_for(torch.device("cpu")) == tiles.PAIRS_PER_CHUNK
    assert tiles.pairs_per_chunk_for(torch.device("cuda")) == tiles.CUDA_PAIRS_PER_CHUNK
    monkeypatch.setenv(tiles.CHUNK_PAIRS_ENV, "12345")
    assert tiles.pairs_per_chunk_for(torch.device("cpu")) == 12345
    for bad in ("0", "-3", "lots"):
        monkeypatch.setenv(tiles.CHUNK_PAIRS_ENV, bad)
        with pytest.raises(ConfigError, match=tiles.CHUNK_PAIRS_ENV):
            tiles.pairs_per_chunk_for(torch.device("cpu"))

"""Compiled projection (numba) against the torch projection: forward and every gradient."""
from __future__ import annotations

import math

import pytest
import torch

from memgs_ros.core.gaussians.tensors import Gaussians
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.poses import quat_wxyz_to_rotmat_torch
from memgs_ros.core.raster.projection import project_gaussians

OUTPUTS = ("means2d", "cov2d", "conics", "depths", "opacities", "colors")
INPUTS = ("means", "quats_wxyz", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "T_cw")
CAM = PinholeCamera(64, 48, 50.0, 52.0, 30.3, 25.7)
# Principal point far from the centre: the four Jacobian clamp limits all differ.
CAM_OFFCENTRE = PinholeCamera(48, 40, 45.0, 40.0, 12.0, 31.0)


@pytest.fixture(autouse=True)
def _needs_numba() -> None:
    pytest.importorskip("numba")
    from memgs_ros.core.runtime.cpu import numba_available

    if not numba_available():
        pytest.skip("numba is disabled here (MEMGS_DISABLE_NUMBA)")


def _inputs(n: int, seed: int, dtype: torch.dtype = torch.float64, k: int = 15) -> list[torch.Tensor]:
    """n Gaussians spread wide around a rotated, translated camera: many far outside the frustum
    (Jacobian clamps hit) and many behind it or in front of the near plane (culled rows).
    Unnormalised quaternions. Returns [means, quats, log_scales, opacity_logits, sh_dc, sh_rest, T_cw]."""
    g = torch.Generator().manual_seed(seed)
    p_c = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([3.0, 2.5, 2.0], dtype=torch.float64)
    p_c[:, 2] += 1.5
    T = torch.eye(4, dtype=torch.float64)
    q = torch.cat([torch.ones(1, dtype=torch.float64), 0.3 * torch.randn(3, generator=g, dtype=torch.float64)])
    T[:3, :3] = quat_wxyz_to_rotmat_torch(q[None])[0]
    T[:3, 3] = 0.3 * torch.randn(3, generator=g, dtype=torch.float64)
    means = (p_c - T[:3, 3]) @ T[:3, :3]
    quats = 2.0 * torch.randn(n, 4, generator=g, dtype=torch.float64)
    log_scales = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.7 - 2.5
    logits = torch.randn(n, 1, generator=g, dtype=torch.float64) * 3.0
    sh_dc = torch.randn(n, 1, 3, generator=g, dtype=torch.float64) * 2.0  # some colours clamp at 0
    sh_rest = 0.5 * torch.randn(n, k, 3, generator=g, dtype=torch.float64)
    return [t.to(dtype).requires_grad_() for t in (means, quats, log_scales, logits, sh_dc, sh_rest, T)]


def _project_both(inputs, cam, deg, near=0.01):
    from memgs_ros.core.raster.projection_numba import project_gaussians_numba

    ref = project_gaussians(Gaussians(*inputs[:6]), inputs[6], cam, deg, near)
    out = project_gaussians_numba(Gaussians(*inputs[:6]), inputs[6], cam, deg, near)
    return out, ref


def _check_grads(out, ref, inputs, seed: int, rtol: float) -> None:
    g = torch.Generator().manual_seed(seed)
    outs = [getattr(out, name) for name in OUTPUTS]
    refs = [getattr(ref, name) for name in OUTPUTS]
    cot = [torch.randn(r.shape, generator=g, dtype=torch.float64).to(r.dtype) for r in refs]
    g_out = torch.autograd.grad(outs, inputs, cot, allow_unused=True)
    g_ref = torch.autograd.grad(refs, inputs, cot, allow_unused=True)
    for name, a, b in zip(INPUTS, g_out, g_ref):
        assert (a is None) == (b is None), name
        if a is None:
            continue
        assert a.dtype == b.dtype and a.shape == b.shape, name
        scale = max(1.0, b.abs().max().item())
        err = (a - b).abs().max().item()
        assert err <= rtol * scale, f"d/d{name}: max error {err} (scale {scale})"


@pytest.mark.parametrize("deg", [0, 1, 2, 3])
@pytest.mark.parametrize("cam", [CAM, CAM_OFFCENTRE])
def test_matches_torch_projection_float64(deg: int, cam: PinholeCamera) -> None:
    inputs = _inputs(400, seed=deg + 10)
    out, ref = _project_both(inputs, cam, deg)
    # The scene exercises every special case.
    assert 0 < int(ref.in_front.sum()) < 400
    x_over_z = (ref.means2d[:, 0] - cam.cx) / cam.fx
    assert ((x_over_z > 2.0) & ref.in_front).any() and ((x_over_z < -2.0) & ref.in_front).any()
    assert (ref.colors == 0).any()
    assert torch.equal(out.in_front, ref.in_front)
    for name in OUTPUTS:
        a, b = getattr(out, name), getattr(ref, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        err = ((a - b).abs() / (1.0 + b.abs())).max().item()
        assert err <= 1e-12, f"{name}: max relative error {err}"
    _check_grads(out, ref, inputs, seed=deg, rtol=1e-11)


def test_pose_without_grad_and_partial_inputs() -> None:
    """T_cw and some parameters without requires_grad: None exactly where the torch path gives None."""
    inputs = _inputs(50, seed=3)
    inputs[6] = inputs[6].detach()
    inputs[1] = inputs[1].detach()
    out, ref = _project_both(inputs, CAM, 2)
    leaves = [t for t in inputs if t.requires_grad]
    g_out = torch.autograd.grad(out.colors.sum() + out.conics.sum() + out.opacities.sum(), leaves)
    g_ref = torch.autograd.grad(ref.colors.sum() + ref.conics.sum() + ref.opacities.sum(), leaves)
    for a, b in zip(g_out, g_ref):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)


def test_degree_zero_without_rest_and_zero_quaternion() -> None:
    inputs = _inputs(30, seed=4, k=0)
    with torch.no_grad():
        inputs[1][0] = 0.0  # a zero quaternion: the 1e-12 clamp, finite everywhere
    out, ref = _project_both(inputs, CAM, 0)
    for name in OUTPUTS:
        assert torch.allclose(getattr(out, name), getattr(ref, name), rtol=1e-12, atol=1e-12), name
    _check_grads(out, ref, inputs, seed=5, rtol=1e-11)


def test_float32_matches_float64_reference() -> None:
    """float32 in, float32 out (float64 inside): at least as close to the float64 truth as torch's float32 path."""
    inputs64 = _inputs(300, seed=6)
    inputs32 = [t.detach().float().requires_grad_() for t in inputs64]
    out32, ref32 = _project_both(inputs32, CAM, 3)
    truth = project_gaussians(Gaussians(*inputs64[:6]), inputs64[6], CAM, 3, 0.01)
    for name in OUTPUTS:
        a, b, c = getattr(out32, name), getattr(ref32, name), getattr(truth, name)
        assert a.dtype == torch.float32
        err_fast = ((a.double() - c) / (1.0 + c.abs())).abs().max().item()
        err_ref = ((b.double() - c) / (1.0 + c.abs())).abs().max().item()
        assert err_fast <= max(err_ref, 1e-6), f"{name}: {err_fast} vs torch float32 {err_ref}"
    _check_grads(out32, ref32, inputs32, seed=7, rtol=1e-4)


@pytest.mark.parametrize("threads", [1, 3])
def test_threads_are_deterministic(threads: int, monkeypatch: pytest.MonkeyPatch) -> None:
    import memgs_ros.core.raster.projection_numba as pn

    monkeypatch.setattr(pn, "MIN_ROWS_PER_THREAD", 7)
    inputs = _inputs(100, seed=8)
    one = pn.project_gaussians_numba(Gaussians(*inputs[:6]), inputs[6], CAM, 3, 0.01, threads=1)
    many = pn.project_gaussians_numba(Gaussians(*inputs[:6]), inputs[6], CAM, 3, 0.01, threads=threads)
    for name in OUTPUTS:
        assert torch.equal(getattr(one, name), getattr(many, name)), name
    cot = [torch.ones_like(getattr(one, name)) for name in OUTPUTS]
    g1 = torch.autograd.grad([getattr(one, name) for name in OUTPUTS], inputs, cot)
    g2 = torch.autograd.grad([getattr(many, name) for name in OUTPUTS], inputs, cot)
    for name, a, b in zip(INPUTS, g1, g2):
        # Per-Gaussian rows are bit-identical; the pose sums ranges in a different grouping.
        if name == "T_cw":
            assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)
        else:
            assert torch.equal(a, b), name


def test_no_gaussians_and_all_behind() -> None:
    inputs = _inputs(0, seed=9)
    out, ref = _project_both(inputs, CAM, 3)
    assert out.means2d.shape == (0, 2) and out.colors.shape == (0, 3)
    inputs = _inputs(20, seed=10)
    with torch.no_grad():
        inputs[6][:3, 3] += torch.tensor([0.0, 0.0, -100.0], dtype=torch.float64)  # everything behind
    out, ref = _project_both(inputs, CAM, 1)
    assert not out.in_front.any()
    assert torch.isfinite(out.conics).all()
    _check_grads(out, ref, inputs, seed=11, rtol=1e-11)


def test_means2d_grad_can_be_retained() -> None:
    from memgs_ros.core.raster.projection_numba import project_gaussians_numba

    inputs = _inputs(10, seed=12)
    out = project_gaussians_numba(Gaussians(*inputs[:6]), inputs[6], CAM, 1, 0.01)
    out.means2d.retain_grad()
    (out.means2d.square().sum() + out.colors.sum()).backward()
    assert out.means2d.grad is not None
    assert torch.allclose(out.means2d.grad, 2.0 * out.means2d.detach())
    assert math.isfinite(float(inputs[0].grad.abs().sum()))

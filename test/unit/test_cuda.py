"""CUDA paths: the torch rasterizer on a GPU, and the gsplat backend against it (forward and
gradients, a small scene). Run wherever CUDA (and, for the second, gsplat) is present; skipped
elsewhere (CI and the development machines have no GPU)."""
from __future__ import annotations

import pytest
import torch
from test_raster import CAM_64, PARAM_NAMES, _scene

from memgs_ros.core.gaussians.tensors import Gaussians
from memgs_ros.core.raster import _rasterize_reference, rasterize
from memgs_ros.core.raster.gsplat_backend import gsplat_available

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def _on(params: list[torch.Tensor], T: torch.Tensor, device: str, dtype: torch.dtype):
    moved = [p.detach().to(device=device, dtype=dtype).requires_grad_() for p in params]
    return moved, T.to(device=device, dtype=dtype)


def _cuda_loss(out) -> torch.Tensor:
    """A random linear functional of the three images (cotangents drawn on the CPU, seeded)."""
    g = torch.Generator().manual_seed(3)
    total = torch.zeros((), device=out.color.device, dtype=out.color.dtype)
    for img in (out.color, out.depth, out.alpha):
        total = total + (img * torch.randn(img.shape, generator=g, dtype=torch.float64).to(img)).sum()
    return total


@cuda
def test_torch_rasterizer_on_cuda_matches_reference() -> None:
    params, T = _scene(60, seed=11, sh_deg_max=1)
    p, Tc = _on(params, T, "cuda", torch.float64)
    out = rasterize(Gaussians(*p), Tc, CAM_64, 1, backend="torch")
    ref = _rasterize_reference(Gaussians(*p), Tc, CAM_64, 1)
    assert out.color.is_cuda
    for name in ("color", "depth", "alpha"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), atol=1e-9, rtol=0)
    grads = zip(PARAM_NAMES, torch.autograd.grad(_cuda_loss(out), p), torch.autograd.grad(_cuda_loss(ref), p))
    for name, a, b in grads:
        torch.testing.assert_close(a, b, atol=1e-7, rtol=1e-6, msg=name)


@cuda
@pytest.mark.skipif(not gsplat_available(), reason="gsplat is not installed")
@pytest.mark.parametrize("backend", ["gsplat", "gsplat_packed"])
def test_gsplat_backend_matches_torch_forward_and_gradients(backend: str) -> None:
    params, T = _scene(200, seed=5, sh_deg_max=1)
    p_t, Tc = _on(params, T, "cuda", torch.float32)
    p_g, _ = _on(params, T, "cuda", torch.float32)
    bg = torch.tensor([0.1, 0.2, 0.3], device="cuda")
    ours = rasterize(Gaussians(*p_t), Tc, CAM_64, 1, background=bg, backend="torch")
    theirs = rasterize(Gaussians(*p_g), Tc, CAM_64, 1, background=bg, backend=backend)
    # gsplat bins by a 3-sigma box on 16 px tiles: tails may differ by ~1/255 of alpha.
    for name in ("color", "depth", "alpha"):
        a, b = getattr(ours, name), getattr(theirs, name)
        assert a.shape == b.shape, name
        assert float((a - b).abs().mean()) < 2e-3, name
        assert float((a - b).abs().max()) < 0.05, name
    assert torch.equal(ours.visible.cpu(), theirs.visible.cpu()) or \
        float((ours.visible != theirs.visible).float().mean()) < 0.02
    _cuda_loss(ours).backward()
    _cuda_loss(theirs).backward()
    for name, pa, pb in zip(PARAM_NAMES, p_t, p_g):
        a, b = pa.grad, pb.grad
        a, b = a.reshape(-1).double(), b.reshape(-1).double()  # type: ignore[union-attr]
        if float(a.norm()) == 0.0:
            continue
        cos = float(torch.dot(a, b) / (a.norm() * b.norm()).clamp_min(1e-30))
        assert cos > 0.98, (name, cos)
        assert abs(float(b.norm() / a.norm()) - 1.0) < 0.05, name
    # The densification statistic arrives in means2d.grad on both backends.
    assert ours.means2d.grad is not None and theirs.means2d.grad is not None


def _pair_map(device: str, n_pairs: int = 3000):
    """``n_pairs`` overlapping pairs of Gaussians, one pair per 5 cm cell (so one per 1 cm voxel):
    every pair a merge candidate within the chi-square gate."""
    from memgs_ros.core.gaussians.gaussian_map import GaussianMap

    g = torch.Generator().manual_seed(5)
    cells = torch.stack(torch.meshgrid(*(torch.arange(15.0) * 0.05,) * 3, indexing="ij"), -1).reshape(-1, 3)[:n_pairs]
    means = torch.cat([cells, cells + (torch.rand(n_pairs, 3, generator=g) - 0.5) * 0.006])  # within a voxel
    m = means.shape[0]
    quats = torch.randn(m, 4, generator=g)
    scales = 0.003 + 0.001 * torch.rand(m, 3, generator=g)
    gmap = GaussianMap(max_sh_degree=1, device=device)
    gmap.add(means.to(device), scales.log().to(device), (quats / quats.norm(dim=1, keepdim=True)).to(device),
             torch.zeros(m, 1, device=device), torch.rand(m, 1, 3, generator=g).to(device), None, 10, iteration=0)
    return gmap


@cuda
def test_merge_pass_on_cuda_matches_the_cpu_within_a_small_memory_peak() -> None:
    """The merge on a CUDA map: the same merges and merged Gaussians as on the CPU, and no
    workspace spike (cuSOLVER's batched eigh once took 1.38 GB for 2663 pairs)."""
    from memgs_ros.core.merge.voxel_merge import MergeConfig, merge_pass

    on_cpu, on_cuda = _pair_map("cpu"), _pair_map("cuda")
    torch.cuda.synchronize()
    start = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    got = merge_pass(on_cuda, MergeConfig(), 10, 1)
    torch.cuda.synchronize()
    peak_mb = (torch.cuda.max_memory_allocated() - start) / 2**20
    ref = merge_pass(on_cpu, MergeConfig(), 10, 1)
    assert ref.n_merged == got.n_merged == 3000
    assert torch.equal(got.removed_ids.cpu(), ref.removed_ids)
    for name in ("means", "log_scales", "quats_wxyz"):
        torch.testing.assert_close(getattr(on_cuda, name).detach().cpu(), getattr(on_cpu, name).detach(),
                                   atol=1e-5, rtol=1e-5, msg=name)
    assert peak_mb < 32, f"merge pass peak {peak_mb:.1f} MB above the map"

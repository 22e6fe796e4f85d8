"""The mapper's training step stays on its device: a full step (render, loss with SSIM,
backward, Adam, densification, voxel merge) with each backend, with no numpy or numba round
trip inside it.

On the CPU the step runs the path a GPU gets (torch compositor and torch SSIM, numba switched
off); where CUDA is present the same checks run on it with the torch fallback and, where
installed, gsplat (these are skipped on machines without a GPU).
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator

import pytest
import torch
from frame_seeds import grid_seeds
from test_mapping import _full_res_loss

from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.mapping.mapper import GaussianMapper, MappingConfig
from memgs_ros.core.merge.voxel_merge import MergeConfig
from memgs_ros.core.raster.gsplat_backend import gsplat_available
from memgs_ros.io.synthetic import SyntheticSpec, generate_frames

CASES = [
    pytest.param("cpu", "torch", id="cpu-torch"),
    pytest.param("cuda", "torch", id="cuda-torch",
                 marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")),
    pytest.param("cuda", "gsplat", id="cuda-gsplat",
                 marks=pytest.mark.skipif(not (torch.cuda.is_available() and gsplat_available()),
                                          reason="no CUDA device or gsplat not installed")),
]


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(generate_frames(SyntheticSpec(width=64, height=48, n_frames=30, seed=1)))[::10]


@contextlib.contextmanager
def no_host_round_trip() -> Iterator[list[str]]:
    """Fail on any tensor -> numpy or numpy -> tensor conversion, and on the compiled (numba)
    kernels of the rasterizer and SSIM, inside the block."""
    from memgs_ros.core.metrics import _ssim_numba
    from memgs_ros.core.raster import _composite_kernels

    calls: list[str] = []

    def refuse(name: str):  # noqa: ANN202
        def fn(*_: object, **__: object) -> None:
            calls.append(name)
            raise AssertionError(f"{name} inside a training step")
        return fn

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(torch.Tensor, "numpy", refuse("Tensor.numpy"))
        mp.setattr(torch, "from_numpy", refuse("torch.from_numpy"))
        mp.setattr(torch.Tensor, "__array__", refuse("Tensor.__array__"))
        for mod in (_ssim_numba, _composite_kernels):
            for name in dir(mod):
                if callable(getattr(mod, name)) and not name.startswith("_") and hasattr(getattr(mod, name), "py_func"):
                    mp.setattr(mod, name, refuse(f"{mod.__name__}.{name}"))
        yield calls


@pytest.mark.parametrize("device,backend", CASES)
def test_training_step_stays_on_device(frames: list[Frame], device: str, backend: str,
                                       request: pytest.FixtureRequest) -> None:
    if device == "cpu":
        request.getfixturevalue("numba_off")  # the branches a GPU takes
    cfg = MappingConfig(min_keyframes=3, pyramid_uses_per_level=2, raster_backend=backend,
                        densify_start_iter=20, densify_interval=20, merge_start_iter=30, merge_interval=30,
                        merge_stop_iter=10_000, densify_grad_threshold=1e-7)
    # A wide gradient gate and big voxels, so that this tiny map has pairs to merge.
    mapper = GaussianMapper(cfg, device=device, merge_cfg=MergeConfig(tau=1e3, voxel_size_m=0.2, min_age_iters=0))
    for i, f in enumerate(frames):
        p, c = grid_seeds(f)
        mapper.add_keyframe(i, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)
    n0 = len(mapper.gmap)
    loss0 = _full_res_loss(mapper)
    densified = merged = 0
    with no_host_round_trip() as calls:
        for _ in range(60):
            stats = mapper.step()
            assert stats is not None
            densified += stats.densified
            merged += stats.merged_removed
    assert calls == []
    loss1 = _full_res_loss(mapper)
    assert loss1 < 0.8 * loss0, (loss0, loss1)
    assert densified > 0 and merged > 0, (densified, merged, n0, len(mapper.gmap))
    g = mapper.gmap
    for name in ("means", "quats_wxyz", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        assert getattr(g, name).device.type == device, name
    for kf in mapper.keyframes.all():
        assert kf.image.device.type == device
    # Leaving the device happens once, when the map is published.
    records = mapper.snapshot()
    assert len(records) == len(g)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_session_reports_the_cuda_memory_figure(frames: list[Frame]) -> None:
    """The evaluation's memory column on a GPU is the mapper's torch.cuda.max_memory_allocated,
    reported by the session's status (and so in the mapper's stats gauges)."""
    from memgs_ros.core.mapper_service.session import MappingSession
    from memgs_ros.core.mapping.keyframes import KeyframeInput

    cfg = MappingConfig(min_keyframes=2, pyramid_uses_per_level=2, merge_enabled=False, densify_start_iter=10_000)
    s = MappingSession(cfg, "cuda", free_running=False)
    try:
        for i, f in enumerate(frames):
            p, c = grid_seeds(f)
            s.insert_keyframe(KeyframeInput(1000 + i, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)).result(60)
        s.train(5).result(60)
        st = s.status
        assert st.cuda_max_allocated is not None and st.cuda_max_allocated > 0
        assert st.gauges()["cuda_max_allocated"] == st.cuda_max_allocated
        assert st.cuda_max_allocated <= torch.cuda.max_memory_allocated()
    finally:
        s.close()

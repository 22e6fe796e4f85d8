"""Losses, keyframe schedule and the mapper: training improves the map, poses matter, deltas."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from frame_seeds import grid_seeds

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.view import Undistorter, view_preparation
from memgs_ros.core.mapping.keyframes import KeyframeStore, make_keyframe
from memgs_ros.core.mapping.losses import depth_l1_loss, isotropic_loss, mapping_loss, photometric_loss
from memgs_ros.core.mapping.mapper import GaussianMapper, MappingConfig
from memgs_ros.core.metrics import ssim as ssim_module
from memgs_ros.core.runtime.cpu import numba_available
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.io.synthetic import SyntheticSpec, generate_frames

# ----------------------------------------------------------------------------- losses


def test_photometric_loss_hand_values() -> None:
    a = torch.zeros(3, 16, 16)
    b = torch.full((3, 16, 16), 0.25)
    loss, l1, s = photometric_loss(a, a.clone())
    assert float(l1) == 0.0 and float(s) == pytest.approx(1.0, abs=1e-6) and float(loss) == pytest.approx(0.0, abs=1e-6)
    loss, l1, s = photometric_loss(a, b, ssim_lambda=0.2)
    assert float(l1) == pytest.approx(0.25)
    assert float(loss) == pytest.approx(0.8 * 0.25 + 0.2 * (1 - float(s)), rel=1e-6)
    # Constant images: SSIM = (2 mu1 mu2 + C1) / (mu1^2 + mu2^2 + C1) at interior pixels; here mu1 = 0.
    assert float(s) < 0.05


def test_isotropic_and_depth_losses_hand_values() -> None:
    log_s = torch.log(torch.tensor([[1.0, 2.0, 3.0], [2.0, 2.0, 2.0]]))
    # Row 0: mean 2, |s - 2| = 1, 0, 1 -> mean over 6 entries = 2/6.
    assert float(isotropic_loss(log_s)) == pytest.approx(2.0 / 6.0)
    assert float(isotropic_loss(torch.zeros(0, 3))) == 0.0
    rd = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    td = torch.tensor([[1.5, float("nan")], [0.0, 2.0]])  # only (0,0) and (1,1) valid
    assert float(depth_l1_loss(rd, td)) == pytest.approx((0.5 + 2.0) / 2)
    assert float(depth_l1_loss(rd, torch.zeros(2, 2))) == 0.0


def test_mapping_loss_combines_terms_and_backpropagates() -> None:
    torch.manual_seed(0)
    img = torch.rand(3, 12, 12, requires_grad=True)
    gt = torch.rand(3, 12, 12)
    log_s = torch.log(torch.tensor([[1.0, 2.0, 3.0]])).requires_grad_()
    d = torch.full((12, 12), 2.0, requires_grad=True)
    total, terms = mapping_loss(img, gt, log_s, d, torch.ones(12, 12), ssim_lambda=0.2, iso_weight=1.0,
                                depth_weight=0.5)
    assert terms["depth"] == pytest.approx(1.0) and terms["iso"] == pytest.approx(2.0 / 3.0)
    assert float(total.detach()) == pytest.approx(terms["photometric"] + terms["iso"] + 0.5 * terms["depth"], rel=1e-6)
    total.backward()
    assert img.grad is not None and log_s.grad is not None and float(d.grad.abs().sum()) > 0
    _, terms0 = mapping_loss(img, gt, log_s, d, torch.ones(12, 12), depth_weight=0.0)
    assert terms0["depth"] == 0.0


def test_masked_losses_ignore_invalid_pixels() -> None:
    torch.manual_seed(1)
    gt = torch.rand(3, 16, 16)
    img = gt.clone()
    mask = torch.ones(16, 16, dtype=torch.bool)
    mask[:, :4] = False
    img[:, :, :4] = 1.0 - gt[:, :, :4]  # wrong only where the mask is off
    _, l1, _ = photometric_loss(img, gt, mask=mask)
    assert float(l1) == 0.0
    _, l1_all, _ = photometric_loss(img, gt)
    assert float(l1_all) > 0.05
    # Masked SSIM is the mean of the SSIM map over valid pixels (the wrong band still enters
    # the 11x11 windows of nearby valid pixels, so it is below 1 but above the unmasked mean).
    _, _, s_m = photometric_loss(img, gt, mask=mask)
    _, _, s_all = photometric_loss(img, gt)
    assert float(s_all) < float(s_m) < 1.0
    rd = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    td = torch.tensor([[1.5, 5.0], [0.0, 2.0]])
    dm = torch.tensor([[True, False], [True, True]])
    assert float(depth_l1_loss(rd, td, dm)) == pytest.approx((0.5 + 2.0) / 2)
    img = (gt * 0.5).requires_grad_()  # wrong everywhere now
    total, _ = mapping_loss(img, gt, torch.zeros(1, 3), ssim_lambda=0.0, iso_weight=0.0, mask=mask)
    total.backward()
    assert float(img.grad[:, :, :4].abs().sum()) == 0.0  # no L1 gradient reaches masked pixels
    assert float(img.grad[:, :, 4:].abs().sum()) > 0.0


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_photometric_loss_same_on_every_ssim_path(masked: bool, dtype: torch.dtype,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """The loss and its gradient w.r.t. the render agree between SSIM's numba path, its torch
    path and a loss written out with the plain 2-D twin (float32: 1e-6 of the value, 1e-5 of the
    largest gradient entry; float64: 1e-12)."""
    pytest.importorskip("numba")
    if not numba_available():
        pytest.skip("numba is disabled here (MEMGS_DISABLE_NUMBA)")
    g = torch.Generator().manual_seed(3)
    gt = torch.rand(3, 37, 53, generator=g, dtype=dtype)
    render = (0.6 * gt + 0.4 * torch.rand(3, 37, 53, generator=g, dtype=dtype)).requires_grad_(True)
    mask = (torch.rand(37, 53, generator=g) > 0.3) if masked else None

    def run() -> tuple[torch.Tensor, torch.Tensor]:
        render.grad = None
        loss, _, _ = photometric_loss(render, gt, ssim_lambda=0.2, mask=mask)
        loss.backward()
        return loss.detach(), render.grad.clone()

    loss_numba, grad_numba = run()
    with monkeypatch.context() as m:
        m.setattr(ssim_module, "_use_numba", lambda a: False)
        loss_torch, grad_torch = run()
    w = torch.ones(37, 53, dtype=dtype) if mask is None else mask.to(dtype)
    n = 3 * w.sum()
    render.grad = None
    ref = (0.8 * ((render - gt).abs() * w).sum() / n
           + 0.2 * (1.0 - (ssim_module._ssim_map(render, gt) * w).sum() / n))
    ref.backward()
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    scale = float(render.grad.abs().max())
    for loss, grad in ((loss_numba, grad_numba), (loss_torch, grad_torch)):
        assert float((loss - ref.detach()).abs()) <= 0.1 * tol * float(ref.detach())
        assert float((grad - render.grad).abs().max()) <= tol * scale
    if mask is not None:  # masked pixels still get SSIM gradient through their neighbours' windows
        assert float(grad_numba[:, ~mask].abs().max()) > 0


def test_undistortion_mask_and_keyframe_levels() -> None:
    cam = PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0, (0.3, -0.9, 0.0, 0.0, 1.1))
    # The mapper's undistortion zooms to the region with source pixels: no border to mask.
    mask = view_preparation(cam).valid_mask
    assert mask is not None and mask.shape == (48, 64) and mask.dtype == bool and mask.all()
    assert view_preparation(PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0)).valid_mask is None
    m = GaussianMapper(MappingConfig(min_keyframes=1))
    rgb = np.full((48, 64, 3), 128, np.uint8)
    m.add_keyframe(0, 0, np.eye(4), rgb, np.full((48, 64), 2.0, np.float32), cam)
    kf = m.keyframes.get(0)
    assert torch.equal(kf.valid_mask, torch.from_numpy(mask))
    assert kf.camera == Undistorter(cam).camera_undistorted and kf.camera.fx > cam.fx
    assert float(kf.depth_m.min()) == 2.0  # every pixel has its depth
    # Without the zoom the corners have no source pixel; keyframe levels respect such a mask:
    # a coarse pixel is valid only when all the fine pixels it covers are.
    border = torch.from_numpy(Undistorter(cam, crop_to_valid=False).valid_mask)
    assert bool(border[24, 32]) and not bool(border.all())
    kf2 = make_keyframe(1, 0, np.eye(4), torch.full((3, 48, 64), 0.5), None, cam.undistorted(), valid_mask=border)
    assert [tuple(lv.valid_mask.shape) for lv in kf2.levels] == [(6, 8), (12, 16), (24, 32), (48, 64)]
    assert int(kf2.levels[2].valid_mask.sum()) <= int(border.sum()) // 4
    m2 = GaussianMapper(MappingConfig(min_keyframes=1, mask_invalid_pixels=False))
    m2.add_keyframe(0, 0, np.eye(4), rgb, None, cam)
    assert m2.keyframes.get(0).valid_mask is None


def test_seed_opacity_applies_to_new_seeds_only() -> None:
    cam = PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0)
    rgb = np.full((24, 32, 3), 100, np.uint8)
    pts = np.random.default_rng(0).uniform(-1, 1, (20, 3)) + [0, 0, 3]
    m = GaussianMapper(MappingConfig(min_keyframes=1, seed_opacity=0.5, seed_coverage=False))
    assert m.add_keyframe(0, 0, np.eye(4), rgb, None, cam, pts, np.full((20, 3), 0.4)) == 20
    assert torch.allclose(m.gmap.opacities(), torch.full((20, 1), 0.5), atol=1e-6)
    with torch.no_grad():
        m.gmap.opacity_logits.fill_(3.0)  # trained rows keep their value when a keyframe arrives
    m.add_keyframe(1, 1, np.eye(4), rgb, None, cam, pts + 0.5, np.full((20, 3), 0.4))
    assert torch.allclose(m.gmap.opacity_logits[:20], torch.full((20, 1), 3.0))
    assert torch.allclose(m.gmap.opacities()[20:], torch.full((20, 1), 0.5), atol=1e-6)
    d = GaussianMapper(MappingConfig(min_keyframes=1))
    d.add_keyframe(0, 0, np.eye(4), rgb, None, cam, pts, np.full((20, 3), 0.4))
    assert torch.allclose(d.gmap.opacities(), torch.full((20, 1), 0.1), atol=1e-6)  # 3DGS default
    with pytest.raises(ConfigError, match="seed_opacity"):
        MappingConfig(seed_opacity=1.0)


# ---------------------------------------------------------------------- keyframe store


def _kf(kf_id: int, w: int = 64, h: int = 48) -> object:
    cam = PinholeCamera(w, h, 50.0, 50.0, w / 2, h / 2)
    return make_keyframe(kf_id, kf_id * 10, np.eye(4), torch.rand(3, h, w), torch.ones(h, w), cam)


def test_keyframe_pyramid_levels() -> None:
    kf = _kf(0)
    assert [lv.factor for lv in kf.levels] == [0.125, 0.25, 0.5, 1.0]
    assert [tuple(lv.image.shape) for lv in kf.levels] == [(3, 6, 8), (3, 12, 16), (3, 24, 32), (3, 48, 64)]
    assert kf.levels[0].camera.width == 8 and torch.equal(kf.levels[-1].image, kf.image)
    assert tuple(kf.levels[1].depth_m.shape) == (12, 16)


def test_keyframe_storage_is_compact_and_exact() -> None:
    # Colour is kept as uint8 (what it came from), depth as float16, the pyramid made per draw:
    # the levels equal those of the float32 image, and 320x240 costs < 0.5 MB (issue: 1.5 MB).
    h, w = 240, 320
    cam = PinholeCamera(w, h, 260.0, 260.0, w / 2, h / 2)
    rgb = torch.randint(0, 256, (3, h, w), dtype=torch.uint8)
    depth = torch.rand(h, w) * 4.0 + 0.5
    depth[:10] = float("nan")
    mask = torch.ones(h, w, dtype=torch.bool)
    mask[:, :3] = False
    kf = make_keyframe(0, 0, np.eye(4), rgb, depth, cam, valid_mask=mask)
    assert kf.rgb.dtype == torch.uint8 and kf.depth_half.dtype == torch.float16
    assert kf.nbytes == 3 * h * w + 2 * h * w + h * w <= 1.5e6
    image = rgb.float() / 255.0
    assert torch.equal(kf.image, image)
    d = kf.depth_m
    assert float(d[:10].abs().max()) == 0.0  # invalid depth is stored as 0
    assert torch.allclose(d[10:], depth[10:], rtol=1e-3)  # float16: 11 significant bits
    lv = kf.level(1)
    ref = torch.nn.functional.interpolate(image[None], size=(60, 80), mode="area")[0]
    assert torch.equal(lv.image, ref) and lv.valid_mask is not None and not bool(lv.valid_mask[:, 0].any())
    assert kf.level(kf.n_levels - 1).camera == cam
    # A float image in [0, 1] is stored rounded to uint8.
    kf2 = make_keyframe(1, 0, np.eye(4), image, None, cam)
    assert torch.equal(kf2.rgb, rgb) and kf2.depth_m is None
    with pytest.raises(DataError, match="image must be"):
        make_keyframe(1, 0, np.eye(4), torch.rand(3, 10, 10), None, kf.camera)


def test_view_schedule_budgets_and_coarse_to_fine() -> None:
    store = KeyframeStore(new_keyframe_budget=2, uses_per_level=2, seed=3)
    store.add(_kf(0))
    store.add(_kf(1))
    first = [store.next_view() for _ in range(4)]
    # Budget 2 each: the first 4 draws use each keyframe exactly twice.
    assert sorted(v.keyframe.kf_id for v in first) == [0, 0, 1, 1]
    # Then every keyframe gets +1: the next 2 draws are one of each.
    nxt = [store.next_view() for _ in range(2)]
    assert sorted(v.keyframe.kf_id for v in nxt) == [0, 1]
    # 3 uses each so far with 2 uses per level: level sequence for kf 0 is 1/8, 1/8, 1/4, ...
    factors = [v.level.factor for v in first + nxt if v.keyframe.kf_id == 0]
    assert factors == [0.125, 0.125, 0.25]
    assert store.level_index(0) == 1
    for _ in range(40):
        store.next_view()
    assert store.level_index(0) == 3  # full resolution once the pyramid is done


def test_store_update_pose_replaces_keyframe_and_validates() -> None:
    store = KeyframeStore()
    store.add(_kf(4))
    T = np.eye(4)
    T[0, 3] = 1.5
    store.update_pose(4, T)
    assert store.get(4).T_wc[0, 3] == 1.5
    with pytest.raises(DataError, match="no keyframe with id 9"):
        store.get(9)
    with pytest.raises(DataError, match="already"):
        store.add(_kf(4))


# ------------------------------------------------------------------------- mapper


@pytest.fixture(scope="module")
def tiny_frames() -> list[Frame]:
    spec = SyntheticSpec(width=64, height=48, n_frames=30, seed=1)
    return list(generate_frames(spec))[::10]  # 3 keyframes


def _mapper(frames: list[Frame], **overrides: object) -> GaussianMapper:
    cfg = MappingConfig(**{"min_keyframes": 3, "pyramid_uses_per_level": 2, "merge_enabled": False,
                           "densify_start_iter": 10_000, **overrides})
    m = GaussianMapper(cfg)
    for i, f in enumerate(frames):
        p, c = grid_seeds(f)
        m.add_keyframe(i, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)
    return m


def _psnr(m: GaussianMapper, frames: list[Frame]) -> float:
    vals = []
    for f in frames:
        out = m.render(f.T_wc_gt, f.camera)
        gt = torch.from_numpy(f.rgb).permute(2, 0, 1).float() / 255.0
        vals.append(-10.0 * math.log10(float(((out.color.clamp(0, 1) - gt) ** 2).mean())))
    return float(np.mean(vals))


def _full_res_loss(m: GaussianMapper) -> float:
    """The training loss summed over every keyframe at full resolution (per-step losses mix
    pyramid levels, so they are not comparable over time)."""
    total = 0.0
    for kf in m.keyframes.all():
        out = m.render(kf.T_wc, kf.camera)
        _, terms = mapping_loss(out.color, kf.image, m.gmap.log_scales.detach(), out.depth, kf.depth_m,
                                depth_weight=m.cfg.depth_weight)
        total += terms["total"]
    return total


def test_training_lowers_loss_and_raises_psnr(tiny_frames: list[Frame]) -> None:
    m = _mapper(tiny_frames)
    psnr0, loss0 = _psnr(m, tiny_frames), _full_res_loss(m)
    stats = [m.step() for _ in range(30)]
    psnr1, loss1 = _psnr(m, tiny_frames), _full_res_loss(m)
    assert psnr1 > psnr0 + 2.0, (psnr0, psnr1)
    assert loss1 < 0.8 * loss0, (loss0, loss1)
    assert m.iteration == 30 and [s.iteration for s in stats] == list(range(1, 31))


def test_not_ready_until_min_keyframes(tiny_frames: list[Frame]) -> None:
    m = _mapper(tiny_frames[:2])
    assert not m.ready and m.step() is None
    with pytest.raises(ConfigError, match="needs 3 keyframes, has 2"):
        m.train(1, progress=False)
    # The final iterations of a run that ended with fewer keyframes train on what there is.
    st = m.step(final=True)
    assert st is not None and m.iteration == 1
    assert _mapper([]).step(final=True) is None  # nothing to train on


def test_pose_update_changes_training(tiny_frames: list[Frame]) -> None:
    a, b, c = (_mapper(tiny_frames) for _ in range(3))
    T = tiny_frames[0].T_wc_gt.copy()
    T[:3, 3] += [0.2, 0.0, 0.0]
    c.update_keyframe_pose(0, T)
    assert np.array_equal(c.keyframes.get(0).T_wc, T)
    for m in (a, b, c):
        for _ in range(6):
            m.step()
    # Same inputs train identically (so the difference below is the pose, not noise) ...
    assert torch.equal(a.gmap.means, b.gmap.means) and torch.equal(a.gmap.sh_dc, b.gmap.sh_dc)
    # ... and the moved keyframe changes what the map learns.
    assert not torch.equal(a.gmap.sh_dc, c.gmap.sh_dc)


def test_densify_clones_small_and_splits_large() -> None:
    cam = PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0)
    m = GaussianMapper(MappingConfig(min_keyframes=1, merge_enabled=False, scene_extent=1.0,
                                     prune_min_age_iters=0, prune_opacity=0.01))
    g = m.gmap
    m.add_keyframe(0, 0, np.eye(4), np.zeros((24, 32, 3), np.uint8), None, cam)
    means = torch.tensor([[0.0, 0, 2], [0.5, 0, 2], [0.0, 0.5, 2]])
    log_s = torch.log(torch.tensor([[0.005] * 3, [0.1, 0.05, 0.02], [0.1] * 3]))
    quats = torch.tensor([[1.0, 0, 0, 0]] * 3)
    g.add(means, log_s, quats, torch.zeros(3, 1), torch.zeros(3, 1, 3), None, torch.tensor([4, 5, 6]), 0)
    g.densify_grad_sum[:] = torch.tensor([1.0, 1.0, 1e-6])
    g.densify_count[:] = 1
    added, removed = m.densify_and_prune()
    # Row 0 (small) cloned, row 1 (large) split into 2, row 2 (low gradient) untouched.
    assert (added, removed) == (3, 1)
    assert g.ids.tolist() == [0, 2, 3, 4, 5]
    assert g.keyframe_ids.tolist() == [4, 6, 4, 5, 5]
    assert torch.equal(g.means[2], means[0])
    assert torch.allclose(g.scales()[3:], torch.tensor([0.1, 0.05, 0.02]) / 1.6)
    assert float((g.means[3:].detach() - means[1]).norm(dim=1).max()) < 0.6
    assert float(g.densify_grad_sum.abs().sum()) == 0.0


def test_merge_hook_called_on_schedule(tiny_frames: list[Frame]) -> None:
    calls = []

    class Result:
        removed_ids = torch.tensor([1, 2])
        added_ids = torch.tensor([999])

    def fake_merge(gmap, cfg, newest, iteration):  # noqa: ANN001, ANN202
        calls.append((gmap is m.gmap, cfg, newest, iteration))
        return Result()

    cfg = MappingConfig(min_keyframes=3, merge_enabled=True, merge_start_iter=2, merge_interval=2,
                        merge_stop_iter=4, densify_start_iter=10_000)
    m = GaussianMapper(cfg, merge_fn=fake_merge, merge_cfg="mcfg")
    for i, f in enumerate(tiny_frames):
        p, c = grid_seeds(f, 8)
        m.add_keyframe(i, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)
    stats = [m.step() for _ in range(6)]
    assert calls == [(True, "mcfg", 2, 2), (True, "mcfg", 2, 4)]
    assert [s.merged_removed for s in stats] == [0, 2, 0, 2, 0, 0]
    assert stats[1].merged_added == 1


def test_distorted_keyframe_is_undistorted_and_scaled() -> None:
    cam = PinholeCamera(40, 30, 35.0, 35.0, 20.0, 15.0, (0.2, -0.1, 0.0, 0.0, 0.0))
    rgb = np.random.default_rng(0).integers(0, 255, (30, 40, 3), dtype=np.uint8)
    depth = np.full((30, 40), 2.0, np.float32)
    m = GaussianMapper(MappingConfig(min_keyframes=1, resolution_scale=0.5))
    m.add_keyframe(0, 0, np.eye(4), rgb, depth, cam)
    kf = m.keyframes.get(0)
    assert not kf.camera.has_distortion
    assert (kf.camera.width, kf.camera.height) == (20, 15) and kf.camera == Undistorter(cam).camera_undistorted.scaled(0.5)
    assert tuple(kf.image.shape) == (3, 15, 20) and float(kf.image.max()) <= 1.0
    with pytest.raises(DataError, match="rgb must be uint8"):
        m.add_keyframe(1, 0, np.eye(4), rgb[:, :10], depth, cam)


def test_config_refuses_bad_values() -> None:
    with pytest.raises(ConfigError, match="ssim_lambda"):
        MappingConfig(ssim_lambda=1.5)
    with pytest.raises(ConfigError, match="unknown mapping parameter"):
        MappingConfig.from_dict({"lr_mean": 1.0})
    assert MappingConfig.from_dict({"background": [1, 1, 1]}).background == (1.0, 1.0, 1.0)
    assert replace(MappingConfig(), depth_weight=0.0).depth_weight == 0.0


def test_max_keyframes_drops_the_most_redundant_never_the_newest() -> None:
    cam = PinholeCamera(16, 12, 10.0, 10.0, 8.0, 6.0)
    m = GaussianMapper(MappingConfig(min_keyframes=1, max_keyframes=3))
    rgb = np.zeros((12, 16, 3), np.uint8)
    for i, x in enumerate([0.0, 1.0, 1.01, 2.0, 3.0]):
        T = np.eye(4)
        T[0, 3] = x
        m.add_keyframe(i, i, T, rgb, None, cam, np.array([[x, 0.0, 2.0]]), np.full((1, 3), 0.5))
    # 1 and 2 sit 1 cm apart: the first goes; then 2 (0.99 m from 3) goes before 0 (1.01 m).
    assert m.keyframes.ids() == [0, 3, 4] and m.keyframes_dropped == 2
    assert len(m.gmap) == 5  # Gaussians of dropped keyframes stay
    # Rotation counts too: a keyframe turned 90 degrees at the same place is not redundant.
    m2 = GaussianMapper(MappingConfig(min_keyframes=1, max_keyframes=2))
    turned = np.eye(4)
    turned[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
    shifted = np.eye(4)
    shifted[0, 3] = 0.2
    for i, T in enumerate([np.eye(4), turned, shifted]):
        m2.add_keyframe(i, i, T, rgb, None, cam)
    assert m2.keyframes.ids() == [1, 2]
    m2.step()  # training draws only the kept keyframes
    assert not m2.update_keyframe_pose(0, np.eye(4))  # a dropped keyframe's refined pose is ignored
    assert m2.update_keyframe_pose(1, np.eye(4))
    with pytest.raises(ConfigError, match="max_keyframes"):
        MappingConfig(max_keyframes=-1)


def test_a_new_keyframe_is_drawn_next() -> None:
    """A keyframe is trained at the first step after its insertion, however many wait in the store
    (a long flight's keyframe waited for half of it before)."""
    store = KeyframeStore(new_keyframe_budget=2, uses_per_level=2, seed=0)
    for k in range(20):
        store.add(_kf(k))
    for _ in range(7):
        store.next_view()
    store.add(_kf(99))
    assert store.next_view().keyframe.kf_id == 99


def test_seeds_go_only_where_the_map_lacks_gaussians(tiny_frames: list[Frame]) -> None:
    """The same view inserted again after training seeds (almost) nothing: the map already explains
    it; without the coverage test it doubles the map."""
    f = tiny_frames[0]
    p, c = grid_seeds(f)
    for coverage, most_added in ((True, 0.1 * len(p)), (False, len(p))):
        m = GaussianMapper(MappingConfig(min_keyframes=1, merge_enabled=False, densify_start_iter=10_000,
                                         seed_opacity=0.5, seed_coverage=coverage, seed_coverage_age_s=0.0))
        assert m.add_keyframe(0, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c) == len(p)
        for _ in range(30):
            m.step()
        added = m.add_keyframe(1, f.stamp_ns + 1, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)
        assert added <= most_added, (coverage, added, len(p))
        assert m.seeds_covered == len(p) - added


def test_the_newest_keyframes_gaussians_do_not_count_as_coverage(tiny_frames: list[Frame]) -> None:
    """The surface the last seconds' keyframes seeded is still being trained: a keyframe beside
    them seeds as without the coverage test (its detail is not hidden by their blobs)."""
    f = tiny_frames[0]
    p, c = grid_seeds(f)
    m = GaussianMapper(MappingConfig(min_keyframes=1, merge_enabled=False, densify_start_iter=10_000,
                                     seed_opacity=0.5, seed_coverage_age_s=5.0))
    m.add_keyframe(0, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)
    for _ in range(30):
        m.step()
    assert m.add_keyframe(1, f.stamp_ns + 4_000_000_000, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c) == len(p)
    assert m.add_keyframe(2, f.stamp_ns + 6_000_000_000, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c) < 0.1 * len(p)


def test_a_surface_trained_long_enough_counts_as_coverage_however_recent(tiny_frames: list[Frame]) -> None:
    """A flight that turns back over what it saw seconds ago: the surface is recent by the clock
    but trained by the iterations since (seed_coverage_trained_iters), and the revisit seeds little."""
    f = tiny_frames[0]
    p, c = grid_seeds(f)

    def revisit(trained_iters: int, steps: int) -> int:
        m = GaussianMapper(MappingConfig(min_keyframes=1, merge_enabled=False, densify_start_iter=10_000,
                                         seed_opacity=0.5, seed_coverage_age_s=5.0,
                                         seed_coverage_trained_iters=trained_iters))
        m.add_keyframe(0, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)
        for _ in range(steps):
            m.step()
        return m.add_keyframe(1, f.stamp_ns + 1_000_000_000, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)

    assert revisit(0, 30) == len(p)  # by age only: one second old, not settled
    assert revisit(30, 29) == len(p)  # one iteration short
    assert revisit(30, 30) < 0.1 * len(p)


def test_uncovered_seeds_by_opacity_and_depth() -> None:
    from memgs_ros.core.mapping.coverage import uncovered_seeds

    cam = PinholeCamera(8, 6, 10.0, 10.0, 3.5, 2.5)
    alpha = torch.ones(6, 8)
    alpha[:, :4] = 0.2  # the left half thin
    depth = 2.0 * alpha  # alpha-blended: the surface at 2 m everywhere
    pts = np.array([[0.5, 0.0, 2.0],    # right half, on the surface: explained
                    [0.5, 0.0, 1.5],    # right half, in front of the surface: new
                    [0.5, 0.0, 2.5],    # behind it: hidden by what the map shows
                    [-0.5, 0.0, 2.0],   # left half: thin
                    [5.0, 0.0, 2.0],    # outside the image
                    [0.5, 0.0, -2.0]])  # behind the camera
    got = uncovered_seeds(pts, np.eye(4), cam, alpha, depth, alpha_max=0.5, depth_abs_m=0.05, depth_rel=0.05)
    assert got.tolist() == [False, True, False, True, False, False]
    assert uncovered_seeds(np.zeros((0, 3)), np.eye(4), cam, alpha, depth, 0.5, 0.05, 0.05).shape == (0,)


def test_a_retired_keyframe_hands_its_gaussians_to_the_nearest_kept_one() -> None:
    """Culled by the tracker: its view leaves training, its Gaussians follow the nearest keyframe's
    loop corrections from then on."""
    cam = PinholeCamera(16, 12, 10.0, 10.0, 8.0, 6.0)
    rgb = np.zeros((12, 16, 3), np.uint8)
    m = GaussianMapper(MappingConfig(min_keyframes=1, seed_coverage=False))
    for i, x in enumerate([0.0, 1.0, 1.05]):
        T = np.eye(4)
        T[0, 3] = x
        m.add_keyframe(i, i, T, rgb, None, cam, np.array([[x, 0.0, 2.0], [x, 0.1, 2.0]]), np.full((2, 3), 0.5))
    assert m.retire_keyframes([2, 7]) == (1, 2)  # 7: unknown, ignored
    assert m.keyframes.ids() == [0, 1] and m.keyframes_retired == 1
    assert (m.gmap.keyframe_ids == 1).sum() == 4  # 1.05 m: keyframe 1 is its nearest
    T1 = np.eye(4)
    T1[0, 3], T1[1, 3] = 1.0, 0.5
    assert m.correct_keyframes({1: T1}) == (1, 4)  # the handed-on Gaussians move with keyframe 1
    assert torch.allclose(m.gmap.means[m.gmap.keyframe_ids == 1][:, 1].sort().values,
                          torch.tensor([0.5, 0.5, 0.6, 0.6]))


def test_merges_run_every_few_keyframes_in_flight(tiny_frames: list[Frame]) -> None:
    """A live mapper reaches merge_every_keyframes long before merge_start_iter."""
    calls = []

    class Result:
        removed_ids = torch.tensor([1])
        added_ids = torch.tensor([999])

    def fake_merge(gmap, cfg, newest, iteration):  # noqa: ANN001, ANN202
        calls.append(iteration)
        return Result()

    cfg = MappingConfig(min_keyframes=1, merge_enabled=True, merge_start_iter=10_000, merge_every_keyframes=2,
                        merge_keyframes_min_iters=3, densify_start_iter=10_000, seed_coverage=False)
    m = GaussianMapper(cfg, merge_fn=fake_merge, merge_cfg="mcfg")
    for i, f in enumerate(tiny_frames[:2]):
        p, c = grid_seeds(f, 8)
        m.add_keyframe(i, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)
    for _ in range(5):
        m.step()
    assert calls == [3]  # two keyframes came, and 3 iterations since the (virtual) last pass
    for _ in range(5):
        m.step()
    assert calls == [3]  # no keyframe since
    f = tiny_frames[2]
    p, c = grid_seeds(f, 8)
    for i in (2, 3):
        m.add_keyframe(i, f.stamp_ns + i, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)
    m.step()
    assert calls == [3, 11] and m.merge.passes == 2


def test_a_revisits_keyframe_opens_densification_only_for_what_it_adds(tiny_frames: list[Frame]) -> None:
    """densify_window_iters in proportion to the share of a keyframe's seeds the map lacked: a new
    view opens the whole window (the map densifies), the same view again, whose seeds the trained
    map explains, opens none (only its few seeds are added)."""
    f = tiny_frames[0]
    p, c = grid_seeds(f)
    m = GaussianMapper(MappingConfig(min_keyframes=1, merge_enabled=False, seed_opacity=0.5, seed_coverage_age_s=0.0,
                                     densify_start_iter=1, densify_interval=1, densify_window_iters=2,
                                     densify_grad_threshold=0.0, prune_opacity=0.0))
    seeded = m.add_keyframe(0, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)
    for _ in range(3):
        m.step()
    opened = len(m.gmap)
    assert opened > seeded  # a new view: densified inside its window
    for _ in range(27):
        m.step()
    assert len(m.gmap) == opened  # the window closed
    added = m.add_keyframe(1, f.stamp_ns + 1, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)
    assert added <= 0.1 * len(p)
    for _ in range(5):
        m.step()
    assert len(m.gmap) == opened + added  # a revisit: its seeds, no densification

"""Per-keyframe exposure compensation: fits a real gain/bias, stays near identity, never reaches renders."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from frame_seeds import grid_seeds

from memgs_ros.core.mapping.exposure import ExposureCompensation
from memgs_ros.core.mapping.mapper import GaussianMapper, MappingConfig
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.io.synthetic import SyntheticSpec, generate_frames


def test_starts_at_identity_and_fits_a_gain_and_bias() -> None:
    torch.manual_seed(0)
    color = torch.rand(3, 8, 8)
    gain, bias = torch.tensor([1.2, 0.9, 1.0]), torch.tensor([0.05, -0.02, 0.0])
    target = color * gain.view(3, 1, 1) + bias.view(3, 1, 1)
    exp = ExposureCompensation(lr=0.01, reg_weight=0.0)
    out, reg = exp.apply(7, color)
    assert torch.equal(out, color) and float(reg.detach()) == 0.0 and exp.get(7) == (0.0,) * 6
    for _ in range(1500):
        out, reg = exp.apply(7, color)
        ((out - target) ** 2).mean().add(reg).backward()
        exp.step()
    a_b = np.array(exp.get(7))
    np.testing.assert_allclose(a_b[:3], (gain - 1).numpy(), atol=0.01)
    np.testing.assert_allclose(a_b[3:], bias.numpy(), atol=0.01)
    assert exp.get(8) == (0.0,) * 6 and 8 not in exp  # another keyframe is untouched


def test_regularisation_pulls_towards_identity() -> None:
    color = torch.full((3, 4, 4), 0.5)
    target = color * 1.5
    fits = []
    for reg_weight in (0.0, 10.0):
        exp = ExposureCompensation(lr=0.01, reg_weight=reg_weight)
        for _ in range(600):
            out, reg = exp.apply(0, color)
            ((out - target).abs().mean() + reg).backward()
            exp.step()
        fits.append(np.abs(exp.get(0)).sum())
    assert fits[1] < 0.5 * fits[0], fits


def test_set_remove_and_bad_values() -> None:
    exp = ExposureCompensation()
    exp.set(3, (0.1, 0.2, 0.3, -0.1, 0.0, 0.05))
    assert exp.get(3) == pytest.approx((0.1, 0.2, 0.3, -0.1, 0.0, 0.05))
    exp.remove(3)
    assert 3 not in exp and len(exp) == 0
    with pytest.raises(DataError, match="6 finite"):
        exp.set(1, (0.0, float("nan"), 0, 0, 0, 0))
    with pytest.raises(DataError, match="lr > 0"):
        ExposureCompensation(lr=0.0)
    with pytest.raises(ConfigError, match="exposure_lr"):
        MappingConfig(exposure_lr=-1.0)


def test_mapper_trains_corrections_but_renders_the_map_alone() -> None:
    frames = list(generate_frames(SyntheticSpec(width=64, height=48, n_frames=30, seed=1)))[::10]
    cfg = MappingConfig(min_keyframes=3, pyramid_uses_per_level=1, merge_enabled=False, densify_start_iter=10_000,
                        exposure_compensation=True, exposure_lr=0.05)
    m = GaussianMapper(cfg)
    for i, f in enumerate(frames):
        rgb = f.rgb
        if i == 1:  # one over-exposed keyframe: the others agree on the scene's colours
            rgb = np.clip(rgb.astype(np.float32) * 1.3 + 10, 0, 255).astype(np.uint8)
        p, c = grid_seeds(f)
        m.add_keyframe(i, f.stamp_ns, f.T_wc_gt, rgb, f.depth_m, f.camera, p, c)
    for _ in range(90):
        m.step()
    # Brighter = larger gain and bias; the corrections stay centred on zero (the map keeps the
    # keyframes' average exposure).
    brightening = {k: sum(m.exposure.get(k)) for k in range(3)}
    assert brightening[1] > max(brightening[0], brightening[2]) + 0.2, brightening
    assert sum(brightening.values()) == pytest.approx(0.0, abs=1e-5)
    # Renders (evaluation, published views) ignore the corrections.
    kf = m.keyframes.get(1)
    before = m.render(kf.T_wc, kf.camera).color
    m.exposure.set(1, (1.0, 1.0, 1.0, 0.5, 0.5, 0.5))
    assert torch.equal(m.render(kf.T_wc, kf.camera).color, before)
    # Off: no corrections at all.
    assert GaussianMapper(MappingConfig()).exposure is None  # off by default

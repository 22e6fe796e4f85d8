"""Mapper checkpoints: exact round trip, resumable training, atomic writes, clear errors."""
from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.mapping import checkpoint
from memgs_ros.core.mapping.mapper import GaussianMapper, MappingConfig
from memgs_ros.errors import DataError
from memgs_ros.io.synthetic import SyntheticSpec, generate_frames

CAM_DIST = PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0, (0.1, -0.05, 0.0, 0.0, 0.0))


def _cfg() -> MappingConfig:
    return MappingConfig(min_keyframes=2, pyramid_uses_per_level=1, densify_start_iter=4, densify_interval=4,
                         merge_enabled=False, sh_up_interval=5, max_sh_degree=1, seed=3, exposure_compensation=True)


def _trained() -> GaussianMapper:
    frames = list(generate_frames(SyntheticSpec(width=64, height=48, n_frames=20, seed=2)))[::10]
    m = GaussianMapper(_cfg())
    for i, f in enumerate(frames):
        v, u = np.mgrid[2:48:4, 2:64:4]
        d = f.depth_m[v.ravel(), u.ravel()]
        p = f.camera.backproject(u.ravel(), v.ravel(), d) @ f.T_wc_gt[:3, :3].T + f.T_wc_gt[:3, 3]
        m.add_keyframe(i, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, f.rgb[v.ravel(), u.ravel()] / 255.0)
    # A keyframe from a distorted camera, so the valid mask and the zoomed camera travel too.
    rgb = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    m.add_keyframe(2, 99, frames[0].T_wc_gt, rgb, None, CAM_DIST)
    for _ in range(12):
        m.step()
    return m


def _records_equal(a, b) -> bool:  # noqa: ANN001
    return all(np.array_equal(getattr(a, f), getattr(b, f))
               for f in ("ids", "xyz", "f_dc", "f_rest", "opacity", "scale", "rot"))


def test_round_trip_restores_map_keyframes_and_training(tmp_path: Path) -> None:
    m = _trained()
    assert m.gmap.active_sh_degree == 1 and len(m.gmap) > 100
    ck = m.state_dict({"seq": 41, "stamps": {"10": 0}})
    path = checkpoint.save(ck, tmp_path / "ck.npz")
    assert path.exists() and not list(tmp_path.glob(".*tmp"))
    back = checkpoint.load(path)
    assert back.extra == {"seq": 41, "stamps": {"10": 0}} and back.iteration == 12

    r = GaussianMapper(_cfg())
    r.load_state_dict(back)
    assert _records_equal(r.snapshot(), m.snapshot())
    assert torch.equal(r.gmap.keyframe_ids, m.gmap.keyframe_ids)
    assert torch.equal(r.gmap.created_iter, m.gmap.created_iter)
    assert r.iteration == 12 and r.gmap.active_sh_degree == 1
    assert r.keyframes.ids() == m.keyframes.ids() and r.scene_extent == pytest.approx(m.scene_extent)
    for a, b in zip(m.keyframes.all(), r.keyframes.all()):
        assert a.stamp_ns == b.stamp_ns and a.camera == b.camera and np.array_equal(a.T_wc, b.T_wc)
        assert torch.allclose(a.image, b.image, atol=1e-6)  # images came from uint8: exact
        assert (a.depth_m is None) == (b.depth_m is None) and (a.depth_m is None or torch.equal(a.depth_m, b.depth_m))
        assert (a.valid_mask is None) == (b.valid_mask is None)
        assert len(a.levels) == len(b.levels)
        assert r.exposure.get(a.kf_id) == pytest.approx(m.exposure.get(a.kf_id), abs=1e-7)
        # Its training schedule travels: a restored keyframe is drawn at the level it had reached,
        # not again from the coarsest as a new one (a continued map's first ~400 iterations were).
        assert r.keyframes.uses(a.kf_id) == m.keyframes.uses(a.kf_id) > 0
        assert r.keyframes.level_index(a.kf_id) == m.keyframes.level_index(a.kf_id)
    assert any(v != 0.0 for v in m.exposure.get(0))  # training moved the corrections; they travel
    # Same renders, and training goes on; new ids start in a fresh block above every old id.
    T = m.keyframes.get(0).T_wc
    assert torch.allclose(m.render(T, m.keyframes.get(0).camera).color, r.render(T, r.keyframes.get(0).camera).color)
    assert r.gmap.next_id == checkpoint.ID_BLOCK > m.gmap.next_id
    for _ in range(8):
        r.step()
    assert r.iteration == 20
    new_ids = r.gmap.ids[r.gmap.ids >= checkpoint.ID_BLOCK]
    assert new_ids.numel() > 0  # densification added Gaussians with new-block ids
    with pytest.raises(DataError, match="empty mapper"):
        r.load_state_dict(back)


def test_empty_mapper_round_trips(tmp_path: Path) -> None:
    m = GaussianMapper(_cfg())
    back = checkpoint.load(checkpoint.save(m.state_dict(), tmp_path / "e.npz"))
    r = GaussianMapper(_cfg())
    r.load_state_dict(back)
    assert len(r.gmap) == 0 and len(r.keyframes) == 0 and r.iteration == 0


def test_failed_write_keeps_the_previous_checkpoint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    m = _trained()
    path = checkpoint.save(m.state_dict({"n": 1}), tmp_path / "ck.npz")
    before = path.read_bytes()

    def boom(*_a, **_k):  # noqa: ANN002, ANN003, ANN202
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(OSError, match="disk full"):
        checkpoint.save(m.state_dict({"n": 2}), path)
    assert path.read_bytes() == before and checkpoint.load(path).extra == {"n": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ck.npz"]  # no temporary left behind


def test_corrupt_truncated_and_foreign_files_are_data_errors(tmp_path: Path) -> None:
    path = checkpoint.save(_trained().state_dict(), tmp_path / "ck.npz")
    data = path.read_bytes()
    cases = {
        "truncated.npz": data[: len(data) // 2],
        "garbage.npz": b"not a zip at all" * 10,
        "empty.npz": b"",
    }
    for name, blob in cases.items():
        (tmp_path / name).write_bytes(blob)
        with pytest.raises(DataError, match=name):
            checkpoint.load(tmp_path / name)
    with pytest.raises(DataError, match="no such mapper checkpoint"):
        checkpoint.load(tmp_path / "missing.npz")
    # An archive of the wrong kind, and one whose arrays would need unpickling.
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(DataError, match="other.npz"):
        checkpoint.load(tmp_path / "other.npz")
    with zipfile.ZipFile(path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    obj = np.empty(1, dtype=object)
    obj[0] = {"x": 1}
    with zipfile.ZipFile(tmp_path / "pickled.npz", "w") as z:
        for n, b in members.items():
            if n != "xyz.npy":
                z.writestr(n, b)
        with z.open("xyz.npy", "w") as f:
            np.lib.format.write_array(f, obj, allow_pickle=True)
    with pytest.raises(DataError, match="pickled.npz"):
        checkpoint.load(tmp_path / "pickled.npz")

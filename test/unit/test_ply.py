"""3DGS PLY: standard header, exact round trip, atomic write, clear errors on bad files."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from memgs_ros.core.gaussians.gaussian_map import GaussianRecords
from memgs_ros.core.map_io.ply import PLY_PROPERTIES, ids_sidecar_path, load_ply, save_ply
from memgs_ros.errors import DataError


def _records(n: int, seed: int = 0) -> GaussianRecords:
    rng = np.random.default_rng(seed)
    return GaussianRecords.from_arrays(
        ids=np.arange(n, dtype=np.int64) * 3 + 5, xyz=rng.normal(size=(n, 3)), f_dc=rng.normal(size=(n, 3)),
        f_rest=rng.normal(size=(n, 45)), opacity=rng.normal(size=n), scale=rng.normal(size=(n, 3)) - 3,
        rot=rng.normal(size=(n, 4)))


def _header(path: Path) -> list[str]:
    raw = path.read_bytes()
    return raw[: raw.index(b"end_header\n")].decode("ascii").splitlines()


def test_header_has_the_62_standard_properties_in_order(tmp_path: Path) -> None:
    p = save_ply(_records(4), tmp_path / "map.ply")
    lines = _header(p)
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert "element vertex 4" in lines
    props = [ln.split() for ln in lines if ln.startswith("property")]
    assert len(props) == 62 and all(t == "float" for _, t, _ in props)
    names = [n for _, _, n in props]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert tuple(names) == PLY_PROPERTIES
    raw = p.read_bytes()
    assert len(raw) == raw.index(b"end_header\n") + 11 + 4 * 62 * 4


def test_round_trip_is_bitwise_exact_with_ids(tmp_path: Path) -> None:
    rec = _records(50)
    p = save_ply(rec, tmp_path / "sub" / "map.ply")
    back = load_ply(p)
    for f in ("ids", "xyz", "f_dc", "f_rest", "opacity", "scale", "rot"):
        a, b = getattr(rec, f), getattr(back, f)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), f
    # No temp files left behind.
    assert sorted(x.name for x in p.parent.iterdir()) == ["map.ply", "map.ply.ids.npy"]


def test_empty_map_and_missing_sidecar(tmp_path: Path) -> None:
    p = save_ply(GaussianRecords.empty(), tmp_path / "e.ply")
    assert len(load_ply(p)) == 0
    p2 = save_ply(_records(3), tmp_path / "n.ply", write_ids=False)
    assert not ids_sidecar_path(p2).exists()
    assert load_ply(p2).ids.tolist() == [0, 1, 2]


def _write_custom(path: Path, names: list[str], types: list[str], rows: np.ndarray, fmt: str = "binary_little_endian") -> None:
    endian = "<" if fmt == "binary_little_endian" else ">"
    code = {"float": "f4", "double": "f8", "uchar": "u1"}
    dt = np.dtype([(n, endian + code[t]) for n, t in zip(names, types)])
    arr = np.zeros(rows.shape[0], dtype=dt)
    for i, n in enumerate(names):
        arr[n] = rows[:, i]
    head = ["ply", f"format {fmt} 1.0", "element vertex %d" % rows.shape[0]]
    head += [f"property {t} {n}" for n, t in zip(names, types)] + ["end_header"]
    path.write_bytes(("\n".join(head) + "\n").encode() + arr.tobytes())


def test_load_any_order_doubles_extra_props_and_degree0(tmp_path: Path) -> None:
    names = ["rot_3", "rot_2", "rot_1", "rot_0", "scale_2", "scale_1", "scale_0", "opacity", "red",
             "f_dc_2", "f_dc_1", "f_dc_0", "z", "y", "x"]
    types = ["double"] * 8 + ["uchar"] + ["float"] * 6
    rows = np.arange(2 * len(names), dtype=np.float64).reshape(2, -1)
    rows[:, 8] = 7
    p = tmp_path / "odd.ply"
    _write_custom(p, names, types, rows, fmt="binary_big_endian")
    rec = load_ply(p)
    assert rec.xyz[1].tolist() == [29.0, 28.0, 27.0]
    assert rec.rot[0].tolist() == [3.0, 2.0, 1.0, 0.0]
    assert rec.opacity.tolist() == [7.0, 22.0]
    assert np.all(rec.f_rest == 0)


def test_truncated_corrupt_and_non_3dgs_files_raise_data_error_naming_the_file(tmp_path: Path) -> None:
    p = save_ply(_records(10), tmp_path / "t.ply", write_ids=False)
    raw = p.read_bytes()
    p.write_bytes(raw[:-7])
    with pytest.raises(DataError, match=r"t\.ply: truncated"):
        load_ply(p)
    bad = tmp_path / "garbage.ply"
    bad.write_bytes(b"\x00\x01 not a ply")
    with pytest.raises(DataError, match=r"garbage\.ply: not a PLY"):
        load_ply(bad)
    nohead = tmp_path / "nohead.ply"
    nohead.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    with pytest.raises(DataError, match=r"nohead\.ply: .*end_header"):
        load_ply(nohead)
    mesh = tmp_path / "mesh.ply"
    _write_custom(mesh, ["x", "y", "z"], ["float"] * 3, np.zeros((2, 3)))
    with pytest.raises(DataError, match=r"mesh\.ply: not a 3DGS PLY.*f_dc_0"):
        load_ply(mesh)
    ascii_ply = tmp_path / "a.ply"
    ascii_ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nend_header\n")
    with pytest.raises(DataError, match="ascii"):
        load_ply(ascii_ply)
    with pytest.raises(DataError, match="missing.ply"):
        load_ply(tmp_path / "missing.ply")


def test_failed_write_keeps_the_previous_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import memgs_ros.core.map_io.ply as ply_mod

    p = save_ply(_records(2), tmp_path / "m.ply", write_ids=False)
    before = p.read_bytes()

    def failing_fsync(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ply_mod.os, "fsync", failing_fsync)
    with pytest.raises(OSError):
        save_ply(_records(3), p, write_ids=False)
    assert p.read_bytes() == before
    assert [x.name for x in tmp_path.iterdir()] == ["m.ply"]

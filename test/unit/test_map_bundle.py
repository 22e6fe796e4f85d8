"""Map bundles on disk (core/map_io/bundle.py): a save is all or nothing, a bundle is never
overwritten, and a bundle that does not fit is refused with one line naming the field or file."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from memgs_ros.core.map_io.bundle import (
    LATEST,
    MANIFEST,
    MAPPER_FILE,
    PLY_FILE,
    TRACKER_FILE,
    BundleError,
    Manifest,
    check_bundle,
    commit_bundle,
    new_staging,
    resolve_bundle,
)

CAMERA = {"width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0, "dist": [0.0] * 5}
ROOT = Path(__file__).resolve().parents[2]


def _manifest() -> Manifest:
    return Manifest(0, CAMERA, "rgbd", 5000.0, 3, "map_optical", 10, 2, 100, "test", "now")


def _save(root: Path, payload: bytes = b"x" * 1000, name: str | None = None) -> Path:
    staging = new_staging(root)
    for f in (PLY_FILE, TRACKER_FILE, MAPPER_FILE):
        (staging / f).write_bytes(payload + f.encode())
    return commit_bundle(staging, _manifest(), name)


def test_a_save_is_a_new_folder_and_latest_points_at_it(tmp_path: Path) -> None:
    a = _save(tmp_path, name="flight")
    b = _save(tmp_path, name="flight")  # the same name again: a new folder, the first untouched
    assert a.name == "flight" and b.name == "flight-2"
    assert os.readlink(tmp_path / LATEST) == "flight-2" and resolve_bundle(tmp_path) == b
    folder, m = check_bundle(tmp_path, CAMERA, 5000.0, "rgbd")
    assert folder == b and m.keyframes == 2 and set(m.files) == {PLY_FILE, TRACKER_FILE, MAPPER_FILE}
    assert m.bytes == sum((b / f).stat().st_size for f in m.files)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".staging")]  # renamed, not copied


@pytest.mark.parametrize("change, match", [
    (lambda b: _edit(b, camera={**CAMERA, "fx": 60.0}), "camera.fx 60.00 .this source: 50.00"),
    (lambda b: _edit(b, camera={**CAMERA, "width": 640}), "camera.width 640"),
    (lambda b: _edit(b, depth_scale=1000.0), "depth_scale 1000"),
    (lambda b: _edit(b, tracker_mode="mono"), "mono tracker"),
    (lambda b: _edit(b, format_version=2), "format_version 2"),
    (lambda b: (b / PLY_FILE).write_bytes(b"x" * 10), "map.ply is 10 bytes, the manifest says"),
    (lambda b: (b / TRACKER_FILE).write_bytes(b"y" * 1000 + b"tracker.npz"), "tracker.npz does not match its SHA-256"),
    (lambda b: (b / MAPPER_FILE).unlink(), "mapper.npz is missing"),
    (lambda b: (b / MANIFEST).write_text("{"), "manifest.json is unreadable"),
    (lambda b: (b / MANIFEST).unlink(), "no manifest.json"),
])
def test_a_bundle_that_does_not_fit_is_refused_naming_why(tmp_path: Path, change, match: str) -> None:  # noqa: ANN001
    b = _save(tmp_path / "maps")
    change(b)
    with pytest.raises(BundleError, match=match) as err:
        check_bundle(b, CAMERA, 5000.0, "rgbd")
    assert "\n" not in str(err.value)


def _edit(bundle: Path, **fields: object) -> None:
    m = json.loads((bundle / MANIFEST).read_text())
    m.update(fields)
    (bundle / MANIFEST).write_text(json.dumps(m))


_DIES = textwrap.dedent("""
    import os, signal, sys
    from pathlib import Path
    import memgs_ros.core.map_io.bundle as bundle
    root, where = Path(sys.argv[1]), sys.argv[2]
    def die(*a, **k):
        os.kill(os.getpid(), signal.SIGKILL)
    if where == "rename":
        os.rename = die  # killed with every file and the manifest staged, before the bundle gets its name
    else:
        bundle._digest = die  # killed while hashing the staged files
    staging = bundle.new_staging(root)
    for f in (bundle.PLY_FILE, bundle.TRACKER_FILE, bundle.MAPPER_FILE):
        (staging / f).write_bytes(b"z" * 100)
    bundle.commit_bundle(staging, bundle.Manifest(0, {}, "rgbd", 1.0, 0, "m", 0, 0, 0, "", ""))
""")


@pytest.mark.parametrize("where", ["rename", "hashing"])
def test_a_save_killed_half_way_leaves_the_previous_bundle_and_nothing_that_loads(tmp_path: Path, where: str) -> None:
    first = _save(tmp_path)
    before = {p.name: p.read_bytes() for p in first.iterdir()}
    proc = subprocess.run([sys.executable, "-c", _DIES, str(tmp_path), where], cwd=ROOT, check=False,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == -9
    assert resolve_bundle(tmp_path) == first and {p.name: p.read_bytes() for p in first.iterdir()} == before
    left = [p for p in tmp_path.iterdir() if p.name not in (first.name, LATEST)]
    assert len(left) == 1 and left[0].name.startswith(".staging-")  # hidden, and refused by name
    with pytest.raises(BundleError, match="unfinished save"):
        check_bundle(left[0])
    _save(tmp_path)  # the next save clears the dead one's staging folder
    assert not left[0].exists()

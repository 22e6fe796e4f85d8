"""The one atomic write: whole file or the old one, ordinary permissions, no temporary left."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from memgs_ros.core.runtime.atomic import atomic_write


def test_atomic_write_replaces_whole_with_umask_permissions_and_cleans_up(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "map.bin"
    old = os.umask(0o022)
    try:
        atomic_write(path, lambda f: f.write(b"first"))
    finally:
        os.umask(old)
    assert path.read_bytes() == b"first" and os.stat(path).st_mode & 0o777 == 0o644  # not mkstemp's 0600

    def fail(f) -> None:  # noqa: ANN001
        f.write(b"half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(path, fail)
    assert path.read_bytes() == b"first" and os.listdir(path.parent) == ["map.bin"]

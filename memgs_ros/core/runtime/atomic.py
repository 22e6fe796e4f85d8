"""The one atomic file write: nothing a user saved is ever left half written."""
from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import BinaryIO


def atomic_write(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Write ``path`` through ``write(file)`` into a temporary file in the same folder, fsync, then
    os.replace it onto ``path``: readers see the old file or the whole new one; on any error the
    temporary file is removed and the old file is untouched. The file gets the ordinary
    permissions the umask gives (not mkstemp's 0600)."""
    atomic_write_all([(path, write)])


def atomic_write_all(files: Sequence[tuple[Path, Callable[[BinaryIO], object]]]) -> None:
    """:func:`atomic_write` for files that belong together (a PLY and its ids sidecar): every
    temporary file is written and fsynced before the first rename, so a write that fails (disk
    full half-way) replaces none of them; the renames then follow in order."""
    tmps: list[tuple[Path, Path]] = []
    try:
        for path, write in files:
            path = Path(path)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
            tmps.append((tmp, path))
            with open(tmp, "xb") as f:  # "x": never another writer's temporary file
                write(f)
                f.flush()
                os.fsync(f.fileno())
        for tmp, path in tmps:
            os.replace(tmp, path)
    except BaseException:
        for tmp, _ in tmps:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        raise

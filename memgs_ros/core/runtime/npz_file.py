"""The one archive format for saved state (the mapper's checkpoint, the tracker's map): a NumPy
``.npz`` of named arrays with a JSON header, written atomically and read back whole, every way it
can be unreadable reported as one DataError naming the file."""
from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from memgs_ros.core.runtime.atomic import atomic_write
from memgs_ros.errors import DataError

HEADER = "header"  # the array holding the JSON header's UTF-8 bytes


def write_npz(path: str | os.PathLike[str], header: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> Path:
    """Write ``header`` (JSON-able) and ``arrays`` to ``path`` atomically; returns the path."""
    path = Path(path)
    if HEADER in arrays:
        raise ValueError(f"an array may not be named {HEADER!r}")
    payload = {HEADER: np.frombuffer(json.dumps(dict(header)).encode(), np.uint8), **arrays}
    atomic_write(path, lambda f: np.savez(f, **payload))  # type: ignore[arg-type]  # numpy's stub types **kwds as bool
    return path


def read_npz(path: str | os.PathLike[str], what: str) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(header, arrays) of a file of :func:`write_npz`; DataError naming the file as ``what`` (e.g.
    "mapper checkpoint") when it is missing or not such an archive."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            header = json.loads(bytes(z[HEADER]).decode())
            arrays = {k: z[k] for k in z.files if k != HEADER}
    except FileNotFoundError as err:
        raise DataError(f"{path}: no such {what}") from err
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, UnicodeDecodeError) as err:
        raise DataError(f"{path}: not a readable {what} ({type(err).__name__}: {err})") from err
    if not isinstance(header, dict):
        raise DataError(f"{path}: not a readable {what} (its header is not a JSON object)")
    return header, arrays

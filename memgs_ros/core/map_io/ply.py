"""The map on disk: the INRIA 3DGS PLY layout (reference section 10), written atomically.

``save_ply`` writes exactly the 62 standard float32 vertex properties, in the standard order
``x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2 rot_0..3``, binary little-endian, so
common splat viewers open the file. Gaussian ids are not a PLY property (an extra property would
be a gamble with third-party loaders): they go to a sidecar ``<path>.ids.npy`` (int64 [N], same
row order), written atomically before the PLY. ``load_ply`` reads the sidecar when it is present
and matches the vertex count; otherwise ids are 0..N-1.

``load_ply`` parses the header properly: any property order, float or double properties, extra
properties ignored, ``binary_little_endian``/``binary_big_endian``. Anything else (ASCII, a
missing 3DGS property, a truncated body) raises ``DataError`` naming the file.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np

from memgs_ros.core.gaussians.records import PLY_F_REST, GaussianRecords
from memgs_ros.core.runtime.atomic import atomic_write_all
from memgs_ros.errors import DataError

logger = logging.getLogger(__name__)

PLY_PROPERTIES: tuple[str, ...] = (
    ("x", "y", "z", "nx", "ny", "nz")
    + tuple(f"f_dc_{i}" for i in range(3))
    + tuple(f"f_rest_{i}" for i in range(PLY_F_REST))
    + ("opacity",)
    + tuple(f"scale_{i}" for i in range(3))
    + tuple(f"rot_{i}" for i in range(4))
)
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_MAX_HEADER_BYTES = 1 << 20


def ids_sidecar_path(path: str | os.PathLike[str]) -> Path:
    """Where the ids of the Gaussians in ``path`` are kept: ``<path>.ids.npy``."""
    return Path(str(path) + ".ids.npy")


def records_to_vertex_array(records: GaussianRecords) -> np.ndarray:
    """The records as one float32 [N, 62] array in PLY property order (normals zero)."""
    n = len(records)
    out = np.zeros((n, len(PLY_PROPERTIES)), dtype=np.float32)
    out[:, 0:3] = records.xyz
    out[:, 6:9] = records.f_dc
    out[:, 9:54] = records.f_rest
    out[:, 54] = records.opacity
    out[:, 55:58] = records.scale
    out[:, 58:62] = records.rot
    return out


def save_ply(records: GaussianRecords, path: str | os.PathLike[str], write_ids: bool = True) -> Path:
    """Write ``records`` as a standard 3DGS PLY at ``path`` (atomically); returns the path.

    With ``write_ids`` the ids go to the ``<path>.ids.npy`` sidecar. Both files are written in
    full before either replaces its old one (``atomic_write_all``): a disk that fills up half-way
    leaves the previous pair, never a new sidecar beside the old PLY (whose rows it would
    mislabel). Only a crash between the two renames leaves a sidecar that may not match (the
    loader ignores one whose length differs).
    """
    path = Path(path)
    body = records_to_vertex_array(records).astype("<f4", copy=False)
    header = "\n".join(
        ["ply", "format binary_little_endian 1.0", "comment memgs_ros 3DGS map",
         f"element vertex {len(records)}"]
        + [f"property float {name}" for name in PLY_PROPERTIES]
        + ["end_header"]
    ) + "\n"
    files: list[tuple[Path, Callable[[BinaryIO], object]]] = []
    if write_ids:
        files.append((ids_sidecar_path(path),
                      lambda f: np.save(f, np.ascontiguousarray(records.ids, dtype=np.int64))))
    files.append((path, lambda f: (f.write(header.encode("ascii")), f.write(body.tobytes()))))
    atomic_write_all(files)
    return path


def _parse_header(path: Path, raw: bytes) -> tuple[int, int, np.dtype, int]:
    """(header length in bytes, vertex count, vertex dtype, bytes of elements before vertex)."""
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") and not raw.startswith(b"ply\r\n"):
        raise DataError(f"{path}: not a PLY file (no 'ply' magic line)")
    if end < 0:
        raise DataError(f"{path}: PLY header has no end_header line (truncated or corrupt)")
    header_len = end + len(b"end_header\n")
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1] if len(tok) > 1 else None
        elif tok[0] == "element" and len(tok) == 3:
            try:
                count = int(tok[2])
            except ValueError as err:
                raise DataError(f"{path}: bad element line {line!r}") from err
            if count < 0:
                raise DataError(f"{path}: negative element count in {line!r}")
            elements.append((tok[1], count, []))
        elif tok[0] == "property":
            if not elements:
                raise DataError(f"{path}: property before any element: {line!r}")
            if len(tok) >= 2 and tok[1] == "list":
                raise DataError(f"{path}: list property {line!r} is not supported in a 3DGS PLY")
            if len(tok) != 3 or tok[1] not in _PLY_TYPES:
                raise DataError(f"{path}: bad property line {line!r}")
            elements[-1][2].append((tok[2], tok[1]))
        else:
            raise DataError(f"{path}: unexpected header line {line!r}")
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise DataError(f"{path}: PLY format {fmt!r} is not supported (binary little/big endian only)")
    endian = "<" if fmt == "binary_little_endian" else ">"
    offset = 0
    for name, count, props in elements:
        names = [p for p, _ in props]
        if len(set(names)) != len(names):
            dup = sorted({p for p in names if names.count(p) > 1})
            raise DataError(f"{path}: element '{name}' has property {', '.join(dup)} more than once")
        dtype = np.dtype([(p, endian + _PLY_TYPES[t]) for p, t in props])
        if name == "vertex":
            return header_len, count, dtype, offset
        offset += count * dtype.itemsize
    raise DataError(f"{path}: PLY has no vertex element")


def load_ply(path: str | os.PathLike[str]) -> GaussianRecords:
    """Read a 3DGS PLY into ``GaussianRecords`` (float32; ids from the sidecar or 0..N-1).

    f_rest properties missing from a lower-SH-degree file are zeros; every other 3DGS
    property (position, f_dc_0..2, opacity, scale_0..2, rot_0..3) must be present.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise DataError(f"Could not read PLY {path}: {err.strerror or err}") from err
    header_len, n, dtype, offset = _parse_header(path, raw[:_MAX_HEADER_BYTES])
    names = set(dtype.names or ())
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
                "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [p for p in required if p not in names]
    if missing:
        raise DataError(f"{path}: not a 3DGS PLY, vertex properties missing: {', '.join(missing)}")
    need = header_len + offset + n * dtype.itemsize
    if len(raw) < need:
        raise DataError(f"{path}: truncated, {n} vertices need {need} bytes but the file has {len(raw)}")
    v = np.frombuffer(raw, dtype=dtype, count=n, offset=header_len + offset)
    col = lambda *ps: np.stack([v[p].astype(np.float32) for p in ps], axis=1)  # noqa: E731
    f_rest = np.zeros((n, PLY_F_REST), dtype=np.float32)
    for i in range(PLY_F_REST):
        if f"f_rest_{i}" in names:
            f_rest[:, i] = v[f"f_rest_{i}"]
    ids = np.arange(n, dtype=np.int64)
    sidecar = ids_sidecar_path(path)
    if sidecar.exists():
        try:
            side = np.load(sidecar, allow_pickle=False)  # never unpickle a user's file
        except (OSError, ValueError, EOFError) as err:
            raise DataError(f"Could not read Gaussian ids {sidecar}: {err}") from err
        if not isinstance(side, np.ndarray):
            raise DataError(f"{sidecar}: not a .npy array of Gaussian ids")
        if side.shape == (n,) and np.issubdtype(side.dtype, np.integer):
            ids = side.astype(np.int64)
        else:
            # A PLY edited elsewhere keeps a stale sidecar: the PLY wins, ids become 0..N-1.
            logger.warning("%s: %s %s ids do not fit the %d vertices of %s; using 0..%d", sidecar, side.shape,
                           side.dtype, n, path.name, n - 1)
    return GaussianRecords.from_arrays(
        ids, col("x", "y", "z"), col("f_dc_0", "f_dc_1", "f_dc_2"), f_rest,
        v["opacity"].astype(np.float32), col("scale_0", "scale_1", "scale_2"),
        col("rot_0", "rot_1", "rot_2", "rot_3"))

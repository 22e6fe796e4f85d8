"""The seed cloud on ``memgs/keyframe/seeds``: x, y, z (world), rgb (float32-packed
0x00RRGGBB, the PCL/RViz convention) and source (0 keypoint, 1 Patch-Grid sample)."""
from __future__ import annotations

import numpy as np

from memgs_ros.core.map_io.map_delta import pack_rgb8, unpack_rgb
from memgs_ros.errors import MessageError

SEED_DTYPE = np.dtype([("x", np.float32), ("y", np.float32), ("z", np.float32), ("rgb", np.float32),
                       ("source", np.uint8)])
SEED_FIELDS = ("x", "y", "z", "rgb")


def pack_rgb(colors: np.ndarray) -> np.ndarray:
    """Colours [S, 3] in [0, 1] -> [S] float32 whose bits are 0x00RRGGBB."""
    return pack_rgb8(np.clip(np.rint(np.asarray(colors, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8))


def encode_seeds(points_w: np.ndarray, colors: np.ndarray, source: np.ndarray) -> np.ndarray:
    """points_w [S, 3], colors [S, 3] in [0, 1], source [S] -> structured [S] of SEED_DTYPE."""
    out = np.zeros(len(points_w), dtype=SEED_DTYPE)
    out["x"], out["y"], out["z"] = np.asarray(points_w, dtype=np.float32).T
    out["rgb"] = pack_rgb(colors)
    out["source"] = source
    return out


def decode_seeds(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Structured seed rows -> (points_w [S, 3] float32, colors [S, 3] float32); finite rows only."""
    names = rows.dtype.names or ()
    missing = [n for n in SEED_FIELDS if n not in names]
    if missing:
        raise MessageError(f"seed cloud lacks fields {missing}")
    pts = np.stack([rows["x"], rows["y"], rows["z"]], axis=1).astype(np.float32)
    keep = np.all(np.isfinite(pts), axis=1)
    return pts[keep], unpack_rgb(rows["rgb"][keep]).astype(np.float32) / 255.0

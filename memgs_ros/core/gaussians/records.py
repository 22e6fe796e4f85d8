"""``GaussianRecords``: N Gaussians as plain numpy arrays, named as the INRIA 3DGS PLY properties.

Its own module without torch, so that the processes that only hold, send and save the map (the
merger, PLY and delta tools) do not load torch (~200 MB resident) to do it.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from memgs_ros.errors import DataError

__all__ = ["PLY_F_REST", "SH_C0", "GaussianRecords", "base_rgb8"]

PLY_F_REST = 45  # 15 higher-order coefficients x 3 channels (SH degree 3), always written
# The zeroth real spherical harmonic Y_0^0 = 1 / (2 sqrt(pi)): a Gaussian's view-independent colour is
# 0.5 + SH_C0 f_dc (3DGS). Defined here, in a module without torch, for every user.
SH_C0 = 0.28209479177387814


def base_rgb8(f_dc: np.ndarray) -> np.ndarray:  # [N, 3] -> [N, 3]
    """The view-independent colour of N Gaussians as 8-bit RGB: round(255 clip(0.5 + SH_C0 f_dc, 0, 1)).

    f_dc: [N, 3] SH DC coefficients (read as float32). Returns [N, 3] uint8."""
    f = np.asarray(f_dc, dtype=np.float32)
    return np.rint(np.clip(0.5 + SH_C0 * f, 0.0, 1.0) * 255.0).astype(np.uint8)


@dataclass(frozen=True, eq=False)
class GaussianRecords:
    """N Gaussians as plain numpy arrays, fields named as the 3DGS PLY properties.

    ids: [N] int64, unique map ids.
    xyz: [N, 3] float32 world positions.
    f_dc: [N, 3] float32 SH DC coefficients.
    f_rest: [N, 45] float32 higher SH coefficients, channel-major (R 1..15, G 1..15, B 1..15);
        always 45, zeros beyond the map's SH degree.
    opacity: [N] float32 opacity logit.
    scale: [N, 3] float32 log standard deviations.
    rot: [N, 4] float32 quaternion, w first, unnormalised.
    """

    ids: np.ndarray
    xyz: np.ndarray
    f_dc: np.ndarray
    f_rest: np.ndarray
    opacity: np.ndarray
    scale: np.ndarray
    rot: np.ndarray

    def __post_init__(self) -> None:
        n = int(np.asarray(self.ids).shape[0])
        want = {"ids": (n,), "xyz": (n, 3), "f_dc": (n, 3), "f_rest": (n, PLY_F_REST),
                "opacity": (n,), "scale": (n, 3), "rot": (n, 4)}
        for f in fields(self):
            arr = getattr(self, f.name)
            if not isinstance(arr, np.ndarray) or arr.shape != want[f.name]:
                got = getattr(arr, "shape", type(arr).__name__)
                raise DataError(f"GaussianRecords.{f.name} must be an array of shape {want[f.name]}, got {got}")

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays (236 B a Gaussian with the ids)."""
        return sum(getattr(self, f.name).nbytes for f in fields(self))

    @staticmethod
    def empty() -> GaussianRecords:
        """Zero Gaussians."""
        return GaussianRecords.from_arrays(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                                           np.zeros((0, PLY_F_REST)), np.zeros(0), np.zeros((0, 3)),
                                           np.zeros((0, 4)))

    @staticmethod
    def from_arrays(ids: np.ndarray, xyz: np.ndarray, f_dc: np.ndarray, f_rest: np.ndarray,
                    opacity: np.ndarray, scale: np.ndarray, rot: np.ndarray) -> GaussianRecords:
        """Build records casting to the canonical dtypes (ids int64, everything else float32)."""
        f32 = lambda a: np.ascontiguousarray(np.asarray(a, dtype=np.float32))  # noqa: E731
        return GaussianRecords(np.ascontiguousarray(np.asarray(ids, dtype=np.int64)), f32(xyz), f32(f_dc),
                               f32(f_rest), f32(opacity), f32(scale), f32(rot))

    def select(self, index: np.ndarray) -> GaussianRecords:
        """Rows picked by a bool mask [N] or an index array [M]."""
        return GaussianRecords(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    @staticmethod
    def concat(parts: list[GaussianRecords]) -> GaussianRecords:
        """Rows of several records, in order."""
        if not parts:
            return GaussianRecords.empty()
        return GaussianRecords(**{f.name: np.concatenate([getattr(p, f.name) for p in parts])
                                  for f in fields(GaussianRecords)})

"""A loop closure's rigid corrections applied to the Gaussians the corrected keyframes created."""
from __future__ import annotations

import numpy as np
import torch

from memgs_ros.core.gaussians.gaussian_map import GaussianMap
from memgs_ros.core.geometry.poses import rotmat_to_quat_wxyz_torch

__all__ = ["move_with_keyframes"]


def move_with_keyframes(gmap: GaussianMap, kf_ids: list[int],  # [K] sorted ascending
                        D: np.ndarray,  # [K, 4, 4] world-frame corrections, T_new inv(T_old)
                        ) -> int:
    """Move every Gaussian of ``gmap`` created by keyframe ``kf_ids[k]`` by ``D[k]`` in place: mean
    -> R_D mean + t_D, rotation -> R_D rotation; their Adam moments restart (the old ones point the
    wrong way). Higher SH bands are not rotated (view-dependent colour of a moved Gaussian is
    re-learnt). One pass over the map. Returns the number of Gaussians moved."""
    ids = torch.tensor(kf_ids, dtype=torch.int64, device=gmap.device)  # [K]
    D_t = torch.as_tensor(D, dtype=torch.float32, device=gmap.device)  # [K, 4, 4]
    pos = torch.searchsorted(ids, gmap.keyframe_ids).clamp_max(len(ids) - 1)  # [N]
    rows = torch.nonzero(ids[pos] == gmap.keyframe_ids).reshape(-1)  # [M]
    which = pos[rows]  # [M] index into the corrections
    if rows.numel():
        with torch.no_grad():
            R, t = D_t[which, :3, :3], D_t[which, :3, 3]  # [M, 3, 3], [M, 3]
            gmap.means[rows] = (R @ gmap.means[rows][..., None])[..., 0] + t
            q_D = rotmat_to_quat_wxyz_torch(D_t[:, :3, :3])  # [K, 4]
            gmap.quats_wxyz[rows] = quat_multiply_wxyz(q_D[which], gmap.quats_wxyz[rows])
        gmap.reset_rows(rows, moments=True, accumulators=False)
    return int(rows.numel())


def quat_multiply_wxyz(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # [N, 4] or [4], [N, 4] -> [N, 4]
    """Hamilton product a * b of unit quaternions (w, x, y, z): rotation b, then a."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)

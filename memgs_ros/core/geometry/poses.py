"""Rigid-body geometry: poses as 4x4 matrices, quaternions, interpolation.

Conventions: ``T_wc`` maps camera coordinates to world (camera-in-world, as on the
wire); ``T_cw`` is its inverse. Quaternion order is always in the name: ``xyzw``
(ROS, TUM files) or ``wxyz`` (Gaussian parameters, PLY files).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # torch is imported only by the torch helpers, so light nodes start fast
    import torch


def quat_xyzw_to_rotmat(q_xyzw: np.ndarray) -> np.ndarray:
    """Unit or unnormalised quaternions [..., 4] (x, y, z, w) to rotation matrices [..., 3, 3];
    ValueError for a zero quaternion. scipy's ``Rotation.from_quat(q).as_matrix()`` products in its
    order: the same bits (its reference in the tests).

    numpy, not scipy: a node's executor decodes poses with it, and a first scipy import there beside
    a worker importing scipy's linear algebra (numba's compile does) stopped a resumed mapper with
    Python's import _DeadlockError; the light nodes (merger, sampler) need no scipy either."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n == 0):
        raise ValueError("a zero quaternion has no rotation")
    x, y, z, w = np.moveaxis(q / n, -1, 0)
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    rows = [x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw),
            2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw),
            2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2]
    return np.stack(rows, axis=-1).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] to unit quaternions [..., 4] (x, y, z, w), w >= 0.

    Shepperd's method, one matrix in Python floats (~7 us; scipy's ``Rotation.from_matrix`` spent
    ~0.1 ms, and the tracker converts a few poses every frame). Matrices slightly off SO(3)
    (products of rotations) give the normalised quaternion; ``test_poses`` checks it against scipy.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (3, 3):  # one matrix: numpy's per-call overhead would dominate
        return np.array(quat_xyzw_of(*R.ravel().tolist()))
    m = R.reshape(-1, 9)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m.T
    # The largest of four candidate denominators keeps the division well conditioned.
    cand = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    k = cand.argmax(-1)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(cand, k[:, None], -1)[:, 0], 1e-300))
    opts = np.stack([
        np.stack([(m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, s / 4], -1),
        np.stack([s / 4, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s], -1),
        np.stack([(m01 + m10) / s, s / 4, (m12 + m21) / s, (m02 - m20) / s], -1),
        np.stack([(m02 + m20) / s, (m12 + m21) / s, s / 4, (m10 - m01) / s], -1),
    ], 1)  # [N, 4 candidates, 4]
    q = opts[np.arange(len(k)), k]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[:, 3:4] < 0, -q, q)
    return q.reshape(R.shape[:-2] + (4,))


def quat_xyzw_of(m00: float, m01: float, m02: float, m10: float, m11: float, m12: float,
                   m20: float, m21: float, m22: float) -> tuple[float, float, float, float]:
    """``rotmat_to_quat_xyzw`` of one matrix given by its entries, in Python floats (the same cases):
    for callers that hold the entries already (message encoders, ~2 us against ~7 via an array)."""
    cand = (1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22)
    k = max(range(4), key=cand.__getitem__)
    s = 2.0 * math.sqrt(max(cand[k], 1e-300))
    if k == 0:
        q = ((m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, s / 4)
    elif k == 1:
        q = (s / 4, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s)
    elif k == 2:
        q = ((m01 + m10) / s, s / 4, (m12 + m21) / s, (m02 - m20) / s)
    else:
        q = ((m02 + m20) / s, (m12 + m21) / s, s / 4, (m10 - m01) / s)
    n = math.sqrt(sum(c * c for c in q)) * (-1.0 if q[3] < 0 else 1.0)
    return q[0] / n, q[1] / n, q[2] / n, q[3] / n


def rotmat_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] to rotation vectors [..., 3] (axis times angle in [0, pi])."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (3, 3):
        x, y, z, w1 = quat_xyzw_of(*R.ravel().tolist())
        n1 = math.sqrt(x * x + y * y + z * z)
        f1 = 2.0 / max(w1, 1e-300) if n1 < 1e-12 else 2.0 * math.atan2(n1, w1) / n1
        return np.array((x * f1, y * f1, z * f1))
    q = rotmat_to_quat_xyzw(R)
    v, w = q[..., :3], q[..., 3]
    n = np.linalg.norm(v, axis=-1)
    # angle / sin(angle / 2) = 2 atan2(n, w) / n, which tends to 2 / w as n -> 0.
    small = n < 1e-12
    f = np.where(small, 2.0 / np.maximum(w, 1e-300), 2.0 * np.arctan2(n, w) / np.where(small, 1.0, n))
    return v * f[..., None]


def pose_from_tq(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """Translation [3] and quaternion [4] (x, y, z, w) to a 4x4 pose."""
    T = np.eye(4)
    T[:3, :3] = quat_xyzw_to_rotmat(np.asarray(q_xyzw))
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def pose_to_tq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4x4 pose to (translation [3], quaternion [4] x, y, z, w)."""
    T = np.asarray(T, dtype=np.float64)
    return T[:3, 3].copy(), rotmat_to_quat_xyzw(T[:3, :3])


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform [..., 4, 4] without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3:4]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3:4] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def pose_distances(T_wc: np.ndarray,  # [4, 4]
                   others: np.ndarray,  # [K, 4, 4]
                   rotation_weight_m: float = 0.5) -> np.ndarray:  # [K]
    """Distance of the pose ``T_wc`` to each of ``others``: translation in metres + ``rotation_weight_m``
    per radian of relative rotation (``nearest_pose_distance``'s measure)."""
    T, Ts = np.asarray(T_wc, dtype=np.float64), np.asarray(others, dtype=np.float64).reshape(-1, 4, 4)
    trans = np.linalg.norm(Ts[:, :3, 3] - T[:3, 3], axis=-1)
    rel = np.einsum("ba,kbc->kac", T[:3, :3], Ts[:, :3, :3])  # R^T R_k
    angle = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
    return trans + rotation_weight_m * angle


def nearest_pose_distance(T_wc: np.ndarray, rotation_weight_m: float = 0.5) -> np.ndarray:
    """For each pose, the distance to its nearest other pose.

    T_wc: [K, 4, 4]. Distance = translation in metres + ``rotation_weight_m`` per radian of
    relative rotation. Returns [K] (inf when K == 1): the smallest value marks the most
    redundant pose, the one a capped keyframe store can drop at least cost in coverage.
    """
    T = np.asarray(T_wc, dtype=np.float64)
    trans = np.linalg.norm(T[:, None, :3, 3] - T[None, :, :3, 3], axis=-1)
    rel = np.einsum("iba,jbc->ijac", T[:, :3, :3], T[:, :3, :3])  # R_i^T R_j
    angle = np.arccos(np.clip((np.trace(rel, axis1=2, axis2=3) - 1.0) / 2.0, -1.0, 1.0))
    dist = trans + rotation_weight_m * angle
    np.fill_diagonal(dist, np.inf)
    return dist.min(axis=1)


def interpolate_poses(stamps_ns: np.ndarray, poses: np.ndarray, query_ns: np.ndarray,
                      max_gap_ns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Interpolate poses at query times: linear in translation, slerp in rotation.

    stamps_ns: [M] increasing; poses: [M, 4, 4]; query_ns: [Q].
    Returns (poses [Q, 4, 4], valid [Q] bool). A query outside [stamps[0], stamps[-1]],
    or between two samples further apart than ``max_gap_ns``, is invalid (identity).
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    q = np.asarray(query_ns, dtype=np.int64)
    out = np.tile(np.eye(4), (len(q), 1, 1))
    if len(stamps) == 0:
        return out, np.zeros(len(q), dtype=bool)
    valid = (q >= stamps[0]) & (q <= stamps[-1])
    idx = np.clip(np.searchsorted(stamps, q, side="right") - 1, 0, len(stamps) - 1)
    nxt = np.minimum(idx + 1, len(stamps) - 1)
    if max_gap_ns is not None:
        valid &= (stamps[nxt] - stamps[idx]) <= max_gap_ns
    if not valid.any():
        return out, valid
    if len(stamps) == 1:
        out[valid] = poses[0]
        return out, valid
    t_s = (stamps - stamps[0]).astype(np.float64) * 1e-9
    qs = (q[valid] - stamps[0]).astype(np.float64) * 1e-9
    from scipy.spatial.transform import Rotation, Slerp

    rot = Slerp(t_s, Rotation.from_matrix(poses[:, :3, :3]))(qs).as_matrix()
    i0, i1 = idx[valid], nxt[valid]
    span = np.maximum(t_s[i1] - t_s[i0], 1e-12)
    w = np.clip((qs - t_s[i0]) / span, 0.0, 1.0)[:, None]
    trans = (1 - w) * poses[i0, :3, 3] + w * poses[i1, :3, 3]
    out[valid, :3, :3] = rot
    out[valid, :3, 3] = trans
    return out, valid


def quat_wxyz_to_rotmat_torch(q_wxyz: torch.Tensor) -> torch.Tensor:
    """Quaternions [N, 4] (w, x, y, z; normalised here) to rotation matrices [N, 3, 3]."""
    import torch

    q = q_wxyz / q_wxyz.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat_wxyz_torch(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] to unit quaternions [N, 4] (w, x, y, z), w >= 0."""
    import torch

    m = R.reshape(-1, 9)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m.unbind(-1)
    # Shepperd's method: pick the largest of four candidate denominators for stability.
    cand = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    k = cand.argmax(-1)
    s = torch.sqrt(cand.gather(-1, k[:, None]).squeeze(-1).clamp_min(1e-12)) * 2
    q = torch.empty(m.shape[0], 4, dtype=R.dtype, device=R.device)
    opts = [
        torch.stack([s / 4, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s], -1),
        torch.stack([(m21 - m12) / s, s / 4, (m01 + m10) / s, (m02 + m20) / s], -1),
        torch.stack([(m02 - m20) / s, (m01 + m10) / s, s / 4, (m12 + m21) / s], -1),
        torch.stack([(m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, s / 4], -1),
    ]
    for i, o in enumerate(opts):
        q = torch.where((k == i)[:, None], o, q)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.reshape(R.shape[:-2] + (4,))

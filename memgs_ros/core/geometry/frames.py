"""REP-103/105 frames around the SLAM world.

The tracker's world (``W``, published as the ``world_frame``, default ``map_optical``) is the first
camera's optical frame: x right, y down, z forward. A robot wants ``map`` z-up (REP-103: x
forward, y left, z up), anchored at the body's first pose, and the body (``base_link``) rather
than the camera. With ``E = T_base_optical`` (the camera's optical frame in the body; from its
mount and the fixed optical rotation) the two relate by constant transforms:

    T_map_W = E                      (the first body pose is the map's origin)
    T_map_base(t) = E @ T_W_cam(t) @ E^-1

so every message in ``W`` stays valid and TF carries ``map -> W`` as a static transform.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["OPTICAL_IN_BODY", "FrameConvention", "FrameError", "MountWait", "mount_transform", "rpy_to_rotmat"]

# Columns: the optical frame's x (right), y (down), z (forward) in a REP-103 body (x fwd, y left, z up).
OPTICAL_IN_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class FrameError(ValueError):
    """A frame parameter that cannot describe a rigid mount (the message names it)."""


def rpy_to_rotmat(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Fixed-axis roll (x), pitch (y), yaw (z), as URDF and tf2 read them: R = Rz Ry Rx. [3, 3]."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def mount_transform(xyz_rpy: Sequence[float]) -> np.ndarray:
    """The optical frame in the body [4, 4], from the camera's mount in the body as
    ``[x, y, z, roll, pitch, yaw]`` (metres, radians; the camera's own REP-103 frame, x along the
    lens, as a URDF joint gives it). All zeros: a forward-looking camera at the body's origin."""
    v = [float(x) for x in xyz_rpy]
    if len(v) != 6 or not all(math.isfinite(x) for x in v):
        raise FrameError(f"camera_mount_xyz_rpy: 6 finite numbers [x, y, z, roll, pitch, yaw], got {list(xyz_rpy)}")
    E = np.eye(4)
    E[:3, :3] = rpy_to_rotmat(*v[3:]) @ OPTICAL_IN_BODY
    E[:3, 3] = v[:3]
    return E


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


class FrameConvention:
    """The constant transforms between the SLAM world and REP-105's ``map``/``base_link``."""

    def __init__(self, T_base_optical: np.ndarray) -> None:
        E = np.asarray(T_base_optical, np.float64)
        if E.shape != (4, 4) or not np.allclose(E[:3, :3] @ E[:3, :3].T, np.eye(3), atol=1e-6):
            raise FrameError("T_base_optical must be a rigid [4, 4] transform")
        self.T_base_optical = E
        self.T_optical_base = np.linalg.inv(E)

    @property
    def T_map_world(self) -> np.ndarray:
        """``W`` in ``map`` [4, 4]: the static transform TF carries as ``map -> world_frame``."""
        return self.T_base_optical

    def base_in_map(self, T_wc: np.ndarray) -> np.ndarray:
        """The body's pose in ``map`` [4, 4] from the camera's in ``W`` [4, 4]."""
        return self.T_base_optical @ T_wc @ self.T_optical_base

    def covariance_in_map(self, cov_w: np.ndarray, T_wc: np.ndarray) -> np.ndarray:
        """The camera pose's covariance [6, 6] (x y z roll pitch yaw, perturbations in ``W``) as the
        body pose's in ``map``: rotated into ``map``, with the lever arm from camera to body
        moving the position by the rotation's uncertainty."""
        R = self.T_base_optical[:3, :3]
        lever_w = T_wc[:3, :3] @ self.T_optical_base[:3, 3]  # camera -> body offset, in W
        J = np.zeros((6, 6))
        J[:3, :3] = R
        J[:3, 3:] = -R @ _skew(lever_w)
        J[3:, 3:] = R
        return J @ np.asarray(cov_w, np.float64) @ J.T


class MountWait:
    """When the camera's mount in the body is settled, before the first body pose goes out (the map
    is anchored by it): from TF as soon as TF has it, else from the parameters once ``wait_ns`` has
    passed since it was first asked. ``settled`` from the start where nothing is to be waited for."""

    def __init__(self, wait_ns: int, settled: bool) -> None:
        self.wait_ns, self.settled = wait_ns, settled
        self._asked_ns: int | None = None

    def settle(self, now_ns: int, from_tf: np.ndarray | None) -> str | None:
        """"tf" or "parameters" when this call settles the mount (``from_tf``: TF's [4, 4], None
        while TF has none); None while it waits, or when it was settled before."""
        if self.settled:
            return None
        self._asked_ns = now_ns if self._asked_ns is None else self._asked_ns
        if from_tf is None and now_ns - self._asked_ns < self.wait_ns:
            return None
        self.settled = True
        return "tf" if from_tf is not None else "parameters"

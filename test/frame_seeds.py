"""Test support: seed points for a synthetic frame (not a test module)."""
from __future__ import annotations

import numpy as np

from memgs_ros.core.geometry.frame import Frame


def grid_seeds(f: Frame, step: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """World points [M, 3] and colours [M, 3] in [0, 1] at every ``step``-th pixel with valid depth
    (ground-truth pose)."""
    cam = f.camera
    v, u = np.mgrid[step // 2: cam.height: step, step // 2: cam.width: step]
    u, v = u.ravel(), v.ravel()
    d = f.depth_m[v, u]
    ok = np.isfinite(d) & (d > 0)
    p_c = cam.backproject(u[ok], v[ok], d[ok])
    return p_c @ f.T_wc_gt[:3, :3].T + f.T_wc_gt[:3, 3], f.rgb[v[ok], u[ok]] / 255.0

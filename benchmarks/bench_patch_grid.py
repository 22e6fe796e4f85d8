"""Patch-Grid sample and seed counts per keyframe on a real TUM sequence, with ORB keypoints.

    python benchmarks/bench_patch_grid.py [--tum DIR] [--camera fr1] [--stride 10] [--features 1000] \
        [--out results/bench_patch_grid.json]

Every ``stride``-th frame plays a keyframe: ORB keypoints (cv2.ORB_create(features)) detected
on the raw image and undistorted; colour/depth undistorted; keypoint depth read from the
undistorted depth image. Prints mean [min, max] per frame of: keypoints, PG samples at 80 and
50 px, RGB-D seeds (keypoints with depth, PG samples with valid depth), and monocular PG seeds
(depth from the nearest keypoint with depth) for several radii; timing of the sampling.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import cv2
import numpy as np
from _common import TUM_HELP, tum_path_or_exit, write_results

from memgs_ros.core.geometry.camera import TUM_CAMERAS, TUM_DEPTH_FACTORS
from memgs_ros.core.geometry.view import undistort_uv, undistorter_for, view_preparation
from memgs_ros.core.sampling import PatchGridConfig, patch_grid_uv, seeds_mono, seeds_rgbd

RADII_PX = (1.0, 20.0, 30.0, 50.0, 80.0)


def _list(path: Path) -> tuple[np.ndarray, list[str]]:
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return np.array([float(r[0]) for r in rows]), [r[1] for r in rows]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tum", type=Path, default=None, help=TUM_HELP)
    p.add_argument("--camera", default="fr1", choices=sorted(TUM_CAMERAS))
    p.add_argument("--stride", type=int, default=10)
    p.add_argument("--features", type=int, default=1000)
    p.add_argument("--out", type=Path, default=Path("results/bench_patch_grid.json"))
    args = p.parse_args()
    args.tum = tum_path_or_exit(p, args.tum)
    cam, factor = TUM_CAMERAS[args.camera], TUM_DEPTH_FACTORS[args.camera]
    ts_rgb, f_rgb = _list(args.tum / "rgb.txt")
    ts_d, f_d = _list(args.tum / "depth.txt")
    orb = cv2.ORB_create(args.features)
    rows, t_rgbd = [], []
    for i in range(0, len(f_rgb), args.stride):
        j = int(np.argmin(np.abs(ts_d - ts_rgb[i])))
        bgr = cv2.imread(str(args.tum / f_rgb[i]))
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        depth = cv2.imread(str(args.tum / f_d[j]), cv2.IMREAD_UNCHANGED).astype(np.float32) / factor
        kps = orb.detect(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), None)
        # Undistorted in K, then into the prepared (cropped) view, as the sampler node does.
        uv = undistorter_for(cam).from_pinhole_uv(undistort_uv(np.array([k.pt for k in kps]).reshape(-1, 2), cam))
        view = view_preparation(cam)
        rgb_u, depth_u = view(rgb, depth)
        cam_u = view.camera
        pix = np.floor(uv + 0.5).astype(int)
        ok = (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0) & (pix[:, 1] < cam.height)
        kd = np.full(len(uv), np.nan)
        kd[ok] = depth_u[pix[ok, 1], pix[ok, 0]]
        cfg80, cfg50 = PatchGridConfig(grid_size=80), PatchGridConfig(grid_size=50)
        t = time.perf_counter()
        s = seeds_rgbd(rgb_u, depth_u, cam_u, np.eye(4), i, uv, kd, cfg80)
        t_rgbd.append(time.perf_counter() - t)
        row = {"frame": i, "keypoints": len(kps),
               "pg80_samples": len(patch_grid_uv(uv, cam.width, cam.height, 80, 8, 5, 30, cfg80.rng_for(i))),
               "pg50_samples": len(patch_grid_uv(uv, cam.width, cam.height, 50, 8, 5, 30, cfg50.rng_for(i))),
               "rgbd_keypoint_seeds": s.n_keypoint, "rgbd_pg_seeds": s.n_patch_grid}
        for r in RADII_PX:
            m = seeds_mono(rgb_u, cam_u, np.eye(4), i, uv, kd, PatchGridConfig(grid_size=50, max_px_dist=r))
            row[f"mono50_pg_seeds_r{r:g}px"] = m.n_patch_grid
        rows.append(row)
    print(f"{len(rows)} keyframes (every {args.stride}th of {len(f_rgb)}), mean [min, max] per keyframe:")
    for key in rows[0]:
        if key == "frame":
            continue
        v = np.array([r[key] for r in rows])
        print(f"  {key:28s} {v.mean():7.1f} [{v.min()}, {v.max()}]")
    print(f"  seeds_rgbd time              {statistics.median(t_rgbd) * 1e3:7.2f} ms median")
    write_results(args.out, {"rows": rows, "seeds_rgbd_median_ms": statistics.median(t_rgbd) * 1e3})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Bytes the mapper keeps per training keyframe, and what making a pyramid level per draw costs.

    python benchmarks/bench_keyframe_bytes.py [--source TUM_FOLDER] [--scale 0.5] [--runs 200]

Prepares keyframes exactly as the mapper does (``GaussianMapper.prepare_keyframe``: undistort,
resize to the mapping scale, valid-pixel mask) from a TUM folder (default: the shared fr1/rpy
head) or, without one, from a synthetic 640x480 frame, and prints the tensor bytes per keyframe
in the compact storage (uint8 colour, float16 depth, bool mask; the pyramid is made per draw)
beside the float32 layout with a stored pyramid that the mapper used before. Also times
``TrainingKeyframe.level`` (the per-draw cost that replaced the stored pyramid).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from _common import TUM_HELP, TumNotFound, tum_path, write_results

from memgs_ros.core.mapping.keyframes import TrainingKeyframe
from memgs_ros.core.mapping.mapper import GaussianMapper, MappingConfig
from memgs_ros.core.runtime.cpu import configure_cpu_runtime


def float32_layout_bytes(kf: TrainingKeyframe) -> int:
    """Bytes of the previous layout: float32 colour and depth, bool mask, at every pyramid level."""
    total = 0
    for f in kf.factors:
        cam = kf.camera.scaled(f) if f != 1.0 else kf.camera
        px = cam.width * cam.height
        total += 3 * 4 * px + (4 * px if kf.depth_half is not None else 0) + (px if kf.valid_mask is not None else 0)
    return total


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default=None, help=TUM_HELP + "; without one, a synthetic frame")
    ap.add_argument("--scale", type=float, default=0.5, help="mapping.resolution_scale")
    ap.add_argument("--frames", type=int, default=5, help="keyframes to prepare")
    ap.add_argument("--runs", type=int, default=200, help="timed level() calls per level")
    ap.add_argument("--out", default="results/bench_keyframe_bytes.json")
    args = ap.parse_args(argv)
    configure_cpu_runtime()
    try:
        tum = tum_path(args.source)
    except TumNotFound as err:
        print(f"{err}: a synthetic frame instead")
        tum = None
    if tum is not None:
        from memgs_ros.io.tum import TumFolder

        frames = list(TumFolder(tum, max_frames=args.frames))
        name = tum.name
    else:
        from memgs_ros.io.synthetic import SyntheticSpec, generate_frames

        frames = list(generate_frames(SyntheticSpec(width=640, height=480, n_frames=args.frames)))
        name = "synthetic 640x480"
    mapper = GaussianMapper(MappingConfig(resolution_scale=args.scale))
    kfs = [mapper.prepare_keyframe(i, f.stamp_ns, f.T_wc_gt if f.T_wc_gt is not None else np.eye(4), f.rgb,
                                   f.depth_m, f.camera) for i, f in enumerate(frames)]
    kf = kfs[0]
    compact = int(np.median([k.nbytes for k in kfs]))
    before = float32_layout_bytes(kf)
    times = []
    for i in range(kf.n_levels):
        t = []
        for _ in range(args.runs):
            t0 = time.perf_counter()
            kf.level(i)
            t.append(time.perf_counter() - t0)
        times.append(1e3 * float(np.median(t)))
    print(f"{name}: {frames[0].camera.width}x{frames[0].camera.height} source, keyframes at scale {args.scale:g} "
          f"= {kf.camera.width}x{kf.camera.height}")
    print(f"  bytes per keyframe (compact: uint8 colour, float16 depth, bool mask): {compact} "
          f"({compact / 2**20:.3f} MiB)")
    print(f"  bytes per keyframe before (float32, stored 4-level pyramid):          {before} "
          f"({before / 2**20:.3f} MiB, {before / compact:.1f}x)")
    print("  level() per draw, median ms (coarse to fine): " + ", ".join(f"{t:.3f}" for t in times))
    write_results(args.out, {"source": name, "scale": args.scale, "size": [kf.camera.width, kf.camera.height],
                             "bytes_per_keyframe": compact, "bytes_per_keyframe_float32_pyramid": before,
                             "level_ms_median": times})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

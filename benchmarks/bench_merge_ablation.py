"""Ablation: voxel merging on vs off in real mapping (ground-truth poses, same seed).

For each input (synthetic room and/or a TUM folder), every ``--kf-every``-th frame becomes a
keyframe with its ground-truth pose; seeds come from Patch-Grid sampling (RGB-D) around ORB
keypoints (OpenCV, 500 features, depth read from the depth image), as the keyframe sampler
does. Two ``GaussianMapper`` runs train on the same keyframes with the same seed, one with
merging, one whose merge passes merge nothing (same schedule: the mapper skips densification in
merge iterations, so a plain merge_enabled=False run would densify more often and confound the
comparison), for ``--iters`` iterations at ``--resolution-scale``. Reported per run:
Gaussians, ``GaussianMap.memory_bytes()`` (params + grads + Adam), mean PSNR over the
keyframes (rendered at the training resolution), merges done, wall time. The merge
schedule is compressed for a CPU budget (``--merge-start``, ``--merge-interval``,
``--merge-stop``; paper/released: start ~1000, every 1000-3000, stop with densification); keep
``--merge-stop`` a few hundred iterations before ``--iters`` so merged Gaussians get re-optimised.

Each (input, merge on/off) runs in its own subprocess (fair memory, no shared allocator state).
Prints a table, writes JSON (default results/bench_merge_ablation.json).

    python benchmarks/bench_merge_ablation.py --inputs synthetic:w=160,h=120,n=60,seed=0 tum --iters 1500
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

from _common import TUM_ENV, tum_path_or_exit, uptime, write_results


def _no_merge(gmap, cfg, newest_keyframe_id: int, iteration: int):  # -> MergeResult
    """A merge pass that merges nothing (the "off" arm of the ablation)."""
    import torch

    from memgs_ros.core.merge.voxel_merge import MergeResult

    empty = torch.zeros(0, dtype=torch.int64, device=gmap.device)
    return MergeResult(empty, empty, 0, 0, 0, 0)


def run_one(args: argparse.Namespace) -> dict:
    import cv2
    import numpy as np
    import torch

    from memgs_ros.core.geometry.view import view_preparation
    from memgs_ros.core.mapping.mapper import GaussianMapper, MappingConfig
    from memgs_ros.core.merge.voxel_merge import MergeConfig
    from memgs_ros.core.metrics.image import psnr
    from memgs_ros.core.runtime.cpu import configure_cpu_runtime
    from memgs_ros.core.sampling import seeds_rgbd
    from memgs_ros.io.sources import open_source

    configure_cpu_runtime(torch_threads=args.threads)
    torch.manual_seed(args.seed)
    src = open_source(args.input, max_frames=args.max_frames)
    view = view_preparation(src.camera)  # full size: seeds back-project at source resolution
    cam_u = view.camera
    orb = cv2.ORB_create(500)
    merge_on = args.merge == "on"
    mcfg = MappingConfig(
        merge_enabled=merge_on, merge_start_iter=args.merge_start, merge_interval=args.merge_interval,
        merge_stop_iter=args.merge_stop, densify_start_iter=args.densify_start,
        densify_stop_iter=args.densify_stop, resolution_scale=args.resolution_scale,
        min_keyframes=1, seed=args.seed, max_sh_degree=args.sh_degree)
    merge_cfg = MergeConfig(tau=args.tau, window_keyframes=args.window, voxel_size_m=args.voxel_size)
    # "off" keeps the merge schedule with a pass that merges nothing: the mapper skips
    # densification in merge iterations, so both runs densify at exactly the same iterations
    if not merge_on and args.off_arm == "disabled":
        # The system's own switch (mapping.merge_enabled=false): merge slots densify instead.
        mapper = GaussianMapper(mcfg, merge_cfg=merge_cfg)
    else:
        mapper = GaussianMapper(replace(mcfg, merge_enabled=True), merge_fn=None if merge_on else _no_merge,
                                merge_cfg=merge_cfg)
    n_kf = 0
    for k, frame in enumerate(src):
        if k % args.kf_every or frame.T_wc_gt is None or frame.depth_m is None:
            continue
        rgb_u, depth_u = view(frame.rgb, frame.depth_m)
        gray = cv2.cvtColor(rgb_u, cv2.COLOR_RGB2GRAY)
        kps = orb.detect(gray, None)
        uv = np.array([kp.pt for kp in kps], dtype=np.float64).reshape(-1, 2)
        px = np.clip(np.round(uv).astype(np.int64), 0, [cam_u.width - 1, cam_u.height - 1])
        kd = depth_u[px[:, 1], px[:, 0]].astype(np.float64) if len(px) else np.zeros(0)
        kd = np.where(np.isfinite(kd) & (kd > 0), kd, np.nan)
        seeds = seeds_rgbd(rgb_u, depth_u, cam_u, frame.T_wc_gt, n_kf, uv, kd)
        # the mapper undistorts its own copy; seeds come from the undistorted pixels as the sampler's do
        mapper.add_keyframe(n_kf, frame.stamp_ns, frame.T_wc_gt, frame.rgb, frame.depth_m, frame.camera,
                            seeds.points_w, seeds.colors)
        n_kf += 1
    n_seeded = len(mapper.gmap)
    merges = []
    seen = None
    t0 = time.perf_counter()
    for _ in range(args.iters):
        st = mapper.step()
        r = mapper.merge.last
        if st is not None and r is not None and r is not seen:  # a pass ran in this step
            seen = r
            merges.append({"iteration": st.iteration, "n_candidates": r.n_candidates, "n_pairs": r.n_pairs,
                           "n_merged": r.n_merged, "seconds": r.timings.get("total", 0.0),
                           "gaussians_after": st.num_gaussians})
    train_s = time.perf_counter() - t0
    psnrs = []
    for kf in mapper.keyframes.all():
        out = mapper.render_keyframe(kf.kf_id)
        psnrs.append(psnr(out.color.clamp(0, 1), kf.image))
    mem = mapper.gmap.memory_bytes()
    return {"input": args.input, "merge": args.merge, "keyframes": n_kf, "seeded": n_seeded,
            "gaussians": len(mapper.gmap), "memory_bytes": mem.total, "param_bytes": mem.params,
            "psnr_keyframes": float(np.mean(psnrs)), "train_s": train_s, "merges": merges,
            "merged_total": int(sum(m["n_merged"] for m in merges))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", nargs="+", default=["synthetic:w=160,h=120,n=60,seed=0"],
                    help=f"synthetic specs or TUM folders; 'tum': ${TUM_ENV}, else the shared fr1/rpy head")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--kf-every", type=int, default=5)
    ap.add_argument("--iters", type=int, default=1500)
    ap.add_argument("--resolution-scale", type=float, default=1.0)
    ap.add_argument("--sh-degree", type=int, default=3)
    ap.add_argument("--densify-start", type=int, default=100)
    ap.add_argument("--densify-stop", type=int, default=1200)
    ap.add_argument("--merge-start", type=int, default=400)
    ap.add_argument("--merge-interval", type=int, default=400)
    ap.add_argument("--merge-stop", type=int, default=1200)
    ap.add_argument("--tau", type=float, default=1e-3)
    ap.add_argument("--window", type=int, default=50)
    ap.add_argument("--voxel-size", type=float, default=0.01)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--off-arm", choices=("noop", "disabled"), default="noop",
                    help="noop: 'off' keeps the merge schedule with passes that merge nothing (densification "
                         "identical in both arms); disabled: mapping.merge_enabled=false, the system switch "
                         "(merge slots densify instead, as in the released code)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("results/bench_merge_ablation.json"))
    ap.add_argument("--input", help=argparse.SUPPRESS)
    ap.add_argument("--merge", choices=("on", "off"), help=argparse.SUPPRESS)
    ap.add_argument("--child-out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.input is not None:  # child process: one run
        res = run_one(args)
        write_results(args.child_out, res)
        return 0

    args.inputs = [str(tum_path_or_exit(ap, flag="a folder in --inputs")) if inp == "tum" else inp for inp in args.inputs]
    load = uptime()
    rows = []
    passthrough = []
    for k, v in vars(args).items():
        if k in ("inputs", "out", "input", "merge", "child_out") or v is None:
            continue
        passthrough += [f"--{k.replace('_', '-')}", str(v)]
    args.out.parent.mkdir(parents=True, exist_ok=True)  # the children's files go beside it
    for inp in args.inputs:
        for merge in ("off", "on"):
            child = args.out.with_suffix(f".{len(rows)}.child.json")
            cmd = [sys.executable, __file__, "--input", inp, "--merge", merge, "--child-out", str(child)] + passthrough
            print(f"running {inp} merge={merge} ...", flush=True)
            subprocess.run(cmd, check=True)
            rows.append(json.loads(child.read_text()))
            child.unlink()
            r = rows[-1]
            print(f"  gaussians {r['gaussians']}, memory {r['memory_bytes'] / 1e6:.2f} MB, "
                  f"PSNR {r['psnr_keyframes']:.2f} dB, merged {r['merged_total']}, {r['train_s']:.0f} s", flush=True)
    print(f"\n{'input':<48} {'merge':<5} {'kf':>3} {'gaussians':>9} {'mem MB':>8} {'PSNR dB':>8} {'merged':>7}")
    for r in rows:
        print(f"{r['input'][-48:]:<48} {r['merge']:<5} {r['keyframes']:>3} {r['gaussians']:>9} "
              f"{r['memory_bytes'] / 1e6:>8.2f} {r['psnr_keyframes']:>8.2f} {r['merged_total']:>7}")
    summary = []
    for a, b in zip(rows[0::2], rows[1::2]):
        s = {"input": a["input"], "gaussians_reduction": 1 - b["gaussians"] / max(a["gaussians"], 1),
             "memory_reduction": 1 - b["memory_bytes"] / max(a["memory_bytes"], 1),
             "psnr_delta_db": b["psnr_keyframes"] - a["psnr_keyframes"]}
        summary.append(s)
        print(f"{a['input'][-48:]}: Gaussians -{100 * s['gaussians_reduction']:.1f} %, memory "
              f"-{100 * s['memory_reduction']:.1f} %, PSNR {s['psnr_delta_db']:+.2f} dB "
              f"(target: >= 15 % fewer, PSNR within 0.1 dB)")
    print(f"uptime: {load}")
    write_results(args.out, {"args": {k: str(v) for k, v in vars(args).items()}, "runs": rows,
                             "summary": summary, "uptime": load})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

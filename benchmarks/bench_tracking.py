"""Benchmark the feature tracker: per-frame time and ATE on synthetic and real TUM sequences.

    python benchmarks/bench_tracking.py [--out results/bench_tracking.json] [--tum PATH]
        [--cases synth,synth_noisy,tum,mono,speed] [--n-frames N] [--plot results/traj.png]

Cases:
  synth        synthetic 640x480 noiseless RGB-D (target ATE <= 1 cm)
  synth_noisy  synthetic with depth noise 1 cm and 5 % holes (target <= 2 cm)
  tum          real fr1/rpy (target <= 3 cm, no frame lost), with BA in its thread
  tum_nothread same sequence with local BA run inline and excluded from timing: pure track() cost
  mono         synthetic monocular: initialised within 30 frames, Sim(3) ATE <= 3 % of path length
  pingpong     real fr1/rpy played --repeat times forward and back (a long flight over one room) with
               the tum_fr1 config's keyframe rule, BA inline: keyframes inserted and kept, ATE of each pass
               after one alignment (a revisit should neither add keyframes nor lose accuracy); with
               --flip-backward-readout the backward passes are read bottom to top (readout -0.02 s)
               by decree instead of by the tracker's own check (frontend/readout.py): a replayed
               rolling-shutter sequence played backward shows its rows in the wrong order
  perturbed    real fr1/rpy as a realsense-layout bag carries it (depth in whole millimetres), with the
               tum_fr1 keyframe rule and BA inline (what `memgs run` lockstep tracks, ATE for ATE):
               raw, colour through JPEG at 95 and 90 (image_transport's ``compressed``, the project's
               encoder and decoder), and --draws runs with +-1 grey level of uniform noise on every
               channel (seeds 1..N): how far a change no one can see moves the ATE, the yardstick
               for a compressed bag's ATE
Accuracy: ATE (RMSE after SE(3)/Sim(3) alignment) and RPE over one frame (RMSE of the translation
and rotation error of each consecutive pair's relative motion: the frame-to-frame jitter).
Per-frame time: median and p95 of track(); with threaded BA that includes competition for the
2 cores (BA holds the GIL part of the time); the 'pure' figure times track() alone.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path
from types import SimpleNamespace

# One BLAS thread: a threaded GEMM on 2 cores shared with other work stalls (measured 460 ms vs 1 ms).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from _common import TUM_HELP, tum_path_or_exit, write_results  # noqa: E402

from memgs_ros.core.metrics.trajectory import ate, path_length_m, rpe  # noqa: E402
from memgs_ros.core.tracking import TrackerConfig, TrackingState, make_tracker  # noqa: E402
from memgs_ros.io.repeat import RepeatClock  # noqa: E402

# The Kinect v1 colour camera's rolling shutter, as config/tum_fr*.yaml sets it for the node.
TUM_READOUT_S = 0.02


def _frames(source: str, n_frames: int | None, noise: float = 0.0, holes: float = 0.0) -> tuple[list, object]:
    if source == "synthetic":
        from memgs_ros.io.synthetic import SyntheticSpec, generate_frames

        spec = SyntheticSpec(width=640, height=480, n_frames=n_frames or 120, seed=0,
                             depth_noise_std_m=noise, hole_fraction=holes)
        return list(generate_frames(spec)), spec.camera
    from memgs_ros.io.tum import TumFolder

    folder = TumFolder(source, max_frames=n_frames)
    return list(folder), folder.camera


def run_case(name: str, frames: list, camera: object, cfg: TrackerConfig, sim3: bool = False,
             pure_timing: bool = False, pace: bool = False, passes: RepeatClock | None = None,
             flip_backward_readout: bool = False) -> dict:
    """Track every frame; returns the numbers for the JSON (and the trajectories for a plot).

    pace: hand frames over no faster than their stamps, as a live camera would; otherwise the
    next frame follows at once, and the threaded local BA lands more frames late the faster
    track() is (a monocular run depends on that). passes: the clock of a repeated source: the ATE
    of each pass is reported too (one alignment over all).
    """
    tracker = make_tracker(cfg, camera)
    times, cpu, proc, states, est, stamps, n_inl = [], [], [], [], [], [], []
    n_kf = 0
    flip_frames: list[int] = []
    cov_trace: list[tuple[float, int]] = []  # (position covariance trace m^2, inliers) of tracked frames
    first_ok = None
    ba_inline_s = 0.0
    wall0, stamp0 = time.perf_counter(), frames[0].stamp_ns if frames else 0
    for k, f in enumerate(frames):
        if pace:
            wait = (f.stamp_ns - stamp0) * 1e-9 - (time.perf_counter() - wall0)
            if wait > 0:
                time.sleep(wait)
        if flip_backward_readout and passes is not None:
            backward = passes.backward(int(passes.pass_of(np.array([f.stamp_ns]))[0]))
            tracker.readout.auto = False  # an experiment: each pass's direction known, not checked
            tracker.readout.sign = -1 if backward else 1
        t0, c0, p0 = time.perf_counter(), time.thread_time(), time.process_time()
        res = tracker.track(f)
        dt, dc, dp = time.perf_counter() - t0, time.thread_time() - c0, time.process_time() - p0
        if pure_timing and res.keyframe is not None:
            # Local BA ran inline inside track(); take it out so the number is track() alone.
            dt -= tracker.ba_time_s - ba_inline_s
            dc -= tracker.ba_time_s - ba_inline_s
            dp -= tracker.ba_time_s - ba_inline_s
            ba_inline_s = tracker.ba_time_s
        times.append(dt)
        cpu.append(dc)
        proc.append(dp)
        states.append(res.state.value)
        n_inl.append(res.n_inliers)
        if res.pose_cov is not None:
            cov_trace.append((float(np.trace(res.pose_cov[:3, :3])), res.n_inliers))
        n_kf += res.keyframe is not None
        if (ro := getattr(tracker, "readout", None)) is not None and ro.flips > len(flip_frames):
            flip_frames.append(k)  # the rolling shutter's direction flipped at this frame
        if res.T_wc is not None and first_ok is None and res.state == TrackingState.OK:
            first_ok = k
        if res.T_wc is not None:
            est.append(res.T_wc)
            stamps.append(f.stamp_ns)
    kept = len(tracker.map.keyframes) if hasattr(tracker, "map") else None
    culled = int(getattr(tracker, "keyframes_culled", 0))
    tracker.close()
    gt_st = np.array([f.stamp_ns for f in frames if f.T_wc_gt is not None])
    gt_T = np.array([f.T_wc_gt for f in frames if f.T_wc_gt is not None])
    out: dict = {"case": name, "n_frames": len(frames), "n_keyframes": n_kf,
                 "map_keyframes_kept": kept, "keyframes_culled": culled,
                 "n_ok": states.count("ok"), "n_recently_lost": states.count("recently_lost"),
                 "n_lost": states.count("lost"), "n_not_initialized": states.count("not_initialized"),
                 "first_ok_frame": first_ok, "readout_flip_frames": flip_frames,
                 "time_ms_median": 1e3 * float(np.median(times)),
                 "time_ms_p95": 1e3 * float(np.percentile(times, 95)),
                 "time_ms_median_after_init": 1e3 * float(np.median(times[(first_ok or 0) + 1:] or times)),
                 # CPU time of the calling thread inside track(): what the frame costs when the
                 # machine is not shared (wall time above includes waiting for a core).
                 "cpu_ms_median": 1e3 * float(np.median(cpu)), "cpu_ms_p95": 1e3 * float(np.percentile(cpu, 95)),
                 # Process CPU (all threads: OpenCV's worker threads too); honest only without the
                 # BA thread, i.e. for the pure-timing case.
                 "proc_cpu_ms_median": 1e3 * float(np.median(proc)) if pure_timing else None,
                 "proc_cpu_ms_p95": 1e3 * float(np.percentile(proc, 95)) if pure_timing else None,
                 "inliers_median": float(np.median(n_inl)), "ba_runs": tracker.ba_runs,
                 "ba_refused": int(getattr(tracker, "ba_refused", 0)),
                 "ba_time_s": tracker.ba_time_s, "pure_track_timing": pure_timing, "paced": pace}
    if len(cov_trace) >= 3:
        from scipy.stats import spearmanr

        tr, inl = np.array(cov_trace).T
        # the odometry's covariance means something: larger where fewer points held the pose
        out["cov_pos_sd_cm_median"] = 100 * float(np.sqrt(np.median(tr)))
        out["cov_spearman_vs_inverse_inliers"] = float(spearmanr(tr, 1.0 / np.maximum(inl, 1)).statistic)
    if len(est) >= 3:
        r = ate(np.array(stamps), np.array(est), gt_st, gt_T, sim3=sim3)
        out.update(ate_rmse_m=r.rmse_m, ate_max_m=r.max_m, ate_rot_rmse_deg=r.rotation_rmse_deg,
                   ate_n_matched=r.n_matched, sim3_scale=r.alignment.s)
        # Frame-to-frame jitter: relative pose error over one frame (scaled like the ATE for mono).
        e = rpe(np.array(stamps), np.array(est), gt_st, gt_T, delta=1, scale=r.alignment.s)
        out.update(rpe1_trans_rmse_m=e.trans_rmse_m, rpe1_rot_rmse_deg=e.rot_rmse_deg,
                   rpe1_trans_median_m=e.trans_median_m, rpe1_n_pairs=e.n_pairs)
        plen = path_length_m(gt_T)
        out["gt_path_length_m"] = plen
        out["ate_percent_of_path"] = 100.0 * r.rmse_m / plen if plen > 0 else None
        out["_traj"] = (r.alignment.apply(np.array(est)[r.est_index, :3, 3]), gt_T[r.gt_index, :3, 3])
        if passes is not None:
            which = passes.pass_of(r.stamps_ns)
            out["ate_pass_cm"] = [100 * float(np.sqrt(np.mean(r.errors_m[which == p] ** 2)))
                                  if (which == p).any() else None for p in range(passes.passes)]
    return out


def perturbed_frames(frames: list, kind: str) -> list:
    """The head as a realsense-layout bag would give it: depth rounded to whole millimetres (16UC1),
    and ``kind``: "raw", "jpegQ" (colour encoded at quality Q and decoded as the tracker does),
    "noiseS" (+-1 grey level, uniform, every channel; seed S), or "jpegQ+noiseS" (both, in that order:
    the same noise as "noiseS" on the decoded JPEG)."""
    if "+" in kind:
        first, rest = kind.split("+", 1)
        return perturbed_frames(perturbed_frames(frames, first), rest)
    import dataclasses

    from memgs_ros.core.geometry.view import depth_to_metres, metres_to_units
    from memgs_ros.io.bag_writer import RS_DEPTH_SCALE, compress_rgb
    from memgs_ros.io.image_decoding import decode_compressed_rgb

    def mm(d: np.ndarray | None) -> np.ndarray | None:  # through the bag's 16UC1, as the writer and tracker do
        return None if d is None else depth_to_metres(metres_to_units(d, RS_DEPTH_SCALE), RS_DEPTH_SCALE)

    rng = np.random.default_rng(int(kind[5:])) if kind.startswith("noise") else None
    out = []
    for f in frames:
        rgb = f.rgb
        if kind.startswith("jpeg"):
            fmt, data = compress_rgb(rgb, int(kind[4:]))
            rgb = decode_compressed_rgb(SimpleNamespace(format=fmt, data=data))
        elif rng is not None:
            rgb = np.clip(rgb.astype(np.int16) + rng.integers(-1, 2, rgb.shape), 0, 255).astype(np.uint8)
        out.append(dataclasses.replace(f, rgb=rgb, depth_m=mm(f.depth_m)))
    return out


def pure_timing_case(r: dict) -> bool:
    return bool(r.get("pure_track_timing")) and r.get("proc_cpu_ms_median") is not None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="results/bench_tracking.json")
    ap.add_argument("--tum", default=None, help=TUM_HELP)
    ap.add_argument("--cases", default="synth,synth_noisy,tum,tum_nothread,mono")
    ap.add_argument("--n-frames", type=int, default=None, help="limit every sequence (default: all / 120 synthetic)")
    ap.add_argument("--repeat", type=int, default=5, help="pingpong: passes forward and back")
    ap.add_argument("--repeat-forward", action="store_true", help="pingpong: every pass forward")
    ap.add_argument("--flip-backward-readout", action="store_true",
                    help="pingpong: read the shutter bottom to top on the backward passes (the case list)")
    ap.add_argument("--draws", type=int, default=11, help="perturbed: runs with +-1 grey level of noise")
    ap.add_argument("--paired", action="store_true",
                    help="perturbed: also JPEG 95 with each draw's noise, and JPEG 95 against raw over the pairs "
                         "(the compression's own effect, apart from the track's spread)")
    ap.add_argument("--pace", action="store_true",
                    help="feed frames at their recorded rate (live camera) instead of back to back")
    ap.add_argument("--plot", default=None, help="save a trajectory PNG (top view) here")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a TrackerConfig field for every case (repeatable)")
    args = ap.parse_args(argv)
    overrides: dict[str, object] = {}
    for item in args.set:
        key, _, value = item.partition("=")
        kind = type(getattr(TrackerConfig(), key))
        overrides[key] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)

    def config(**kw: object) -> TrackerConfig:
        return TrackerConfig(**{**kw, **overrides})  # type: ignore[arg-type]

    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    if any(c.startswith("tum") or c in ("pingpong", "perturbed") for c in cases):
        args.tum = str(tum_path_or_exit(ap, args.tum))
    results = []
    cache: dict[str, tuple[list, object]] = {}

    def get(key: str, *a: object) -> tuple[list, object]:
        if key not in cache:
            t0 = time.perf_counter()
            cache[key] = _frames(*a)  # type: ignore[arg-type]
            print(f"loaded {key}: {len(cache[key][0])} frames in {time.perf_counter() - t0:.1f} s", flush=True)
        return cache[key]

    for case in cases:
        if case == "synth":
            fr, cam = get("synth", "synthetic", args.n_frames)
            results.append(run_case(case, fr, cam, config(), pace=args.pace))
        elif case == "synth_noisy":
            fr, cam = get("synth_noisy", "synthetic", args.n_frames, 0.01, 0.05)
            results.append(run_case(case, fr, cam, config(), pace=args.pace))
        elif case == "tum":
            fr, cam = get("tum", args.tum, args.n_frames)
            results.append(run_case(case, fr, cam, config(rolling_shutter_readout_s=TUM_READOUT_S),
                                    pace=args.pace))
        elif case == "tum_nothread":
            fr, cam = get("tum", args.tum, args.n_frames)
            results.append(run_case(case, fr, cam, config(ba_threaded=False, rolling_shutter_readout_s=TUM_READOUT_S),
                                    pure_timing=True))
        elif case == "tum_noba":
            fr, cam = get("tum", args.tum, args.n_frames)
            results.append(run_case(case, fr, cam, config(ba_enabled=False, rolling_shutter_readout_s=TUM_READOUT_S)))
        elif case == "pingpong":
            from memgs_ros.io.sources import open_source

            src = open_source(args.tum, max_frames=args.n_frames, repeat=args.repeat,
                              repeat_forward=args.repeat_forward)
            fr = list(src)
            results.append(run_case(case, fr, src.camera, config(ba_threaded=False, keyframe_max_frames=10,
                                                                 rolling_shutter_readout_s=TUM_READOUT_S),
                                    passes=src.clock,
                                    flip_backward_readout=args.flip_backward_readout))
        elif case == "perturbed":
            fr, cam = get("tum", args.tum, args.n_frames)
            kinds = ["raw", "jpeg95", "jpeg90", *(f"noise{k}" for k in range(1, args.draws + 1)),
                     *(f"jpeg95+noise{k}" for k in range(1, args.draws + 1) if args.paired)]
            for kind in kinds:
                results.append(run_case(f"perturbed:{kind}", perturbed_frames(fr, kind), cam,
                                        config(ba_threaded=False, keyframe_max_frames=10,
                                               rolling_shutter_readout_s=TUM_READOUT_S)))
                r = results[-1]
                print(f"perturbed {kind:>8}: ATE {100 * r['ate_rmse_m']:.3f} cm, ok {r['n_ok']}/{r['n_frames']}, "
                      f"local BAs refused {r['ba_refused']}", flush=True)
            ate_of = {r["case"].split(":", 1)[1]: 100 * r["ate_rmse_m"]
                      for r in results if r["case"].startswith("perturbed:")}
            noise = sorted(v for k, v in ate_of.items() if k.startswith("noise"))
            if noise:
                print(f"perturbed: +-1 grey level, {len(noise)} draws: ATE median {float(np.median(noise)):.3f} cm, "
                      f"range {noise[0]:.3f}-{noise[-1]:.3f}, quartiles {np.percentile(noise, 25):.3f}-"
                      f"{np.percentile(noise, 75):.3f}; raw {ate_of['raw']:.3f}, JPEG 95 {ate_of['jpeg95']:.3f} "
                      f"(above {sum(v < ate_of['jpeg95'] for v in noise)} of {len(noise)} draws), "
                      f"JPEG 90 {ate_of['jpeg90']:.3f}", flush=True)
            if args.paired and noise:
                raw_n = np.array([ate_of[f"noise{k}"] for k in range(1, args.draws + 1)])
                jpeg_n = np.array([ate_of[f"jpeg95+noise{k}"] for k in range(1, args.draws + 1)])
                paired = {"draws": int(args.draws), "raw_median_cm": float(np.median(raw_n)),
                          "jpeg95_median_cm": float(np.median(jpeg_n)),
                          "median_difference_cm": float(np.median(jpeg_n) - np.median(raw_n)),
                          "median_paired_difference_cm": float(np.median(jpeg_n - raw_n)),
                          "jpeg95_worse_in": int((jpeg_n > raw_n).sum())}
                results[-1]["jpeg95_against_raw_paired"] = paired
                print(f"perturbed: JPEG 95 against raw, {args.draws} paired draws (the same noise on both): ATE "
                      f"median {paired['jpeg95_median_cm']:.3f} against {paired['raw_median_cm']:.3f} cm "
                      f"({paired['median_difference_cm']:+.3f}), median paired difference "
                      f"{paired['median_paired_difference_cm']:+.3f} cm, JPEG worse in "
                      f"{paired['jpeg95_worse_in']} of {args.draws}", flush=True)
            continue
        elif case == "mono":
            fr, cam = get("synth", "synthetic", args.n_frames)
            mono = [type(f)(f.stamp_ns, f.rgb, None, f.camera, f.T_wc_gt) for f in fr]
            results.append(run_case(case, mono, cam, config(mode="mono"), sim3=True, pace=args.pace))
        else:
            print(f"unknown case {case!r}", file=sys.stderr)
            return 2
        r = results[-1]
        print(f"{r['case']:>13}: ATE {100 * r.get('ate_rmse_m', float('nan')):6.2f} cm  "
              f"RPE1 {100 * r.get('rpe1_trans_rmse_m', float('nan')):5.2f} cm "
              f"{r.get('rpe1_rot_rmse_deg', float('nan')):5.2f} deg  "
              f"track median {r['time_ms_median']:6.1f} ms p95 {r['time_ms_p95']:6.1f} ms "
              f"(cpu {r['cpu_ms_median']:5.1f} / {r['cpu_ms_p95']:5.1f}"
              + (f", process {r['proc_cpu_ms_median']:5.1f} / {r['proc_cpu_ms_p95']:5.1f}" if pure_timing_case(r) else "")
              + ")  "
              f"ok {r['n_ok']}/{r['n_frames']} lost {r['n_lost']} kf {r['n_keyframes']} "
              f"(kept {r['map_keyframes_kept']}) BA {r['ba_runs']} ({r['ba_time_s']:.1f} s)"
              + (" per pass " + " ".join(f"{v:.2f}" for v in r["ate_pass_cm"]) if r.get("ate_pass_cm") else "")
              + (f" readout flipped at frames {r['readout_flip_frames']}" if r["readout_flip_frames"] else "")
              + (f" covariance: position sd {r['cov_pos_sd_cm_median']:.2f} cm (median), Spearman vs 1/inliers "
                 f"{r['cov_spearman_vs_inverse_inliers']:.2f}" if "cov_spearman_vs_inverse_inliers" in r else ""),
              flush=True)

    print()
    print(f"{'case':>13} | {'ATE cm':>7} | {'RPE1 cm':>7} | {'RPE1 deg':>8} | {'%path':>6} | {'med ms':>7} | {'p95 ms':>7} | {'cpu med':>7} | {'cpu p95':>7} | {'ok':>5} | {'lost':>4} | {'1st ok':>6} | {'KFs':>4}")
    for r in results:
        pct = r.get("ate_percent_of_path")
        print(f"{r['case']:>13} | {100 * r.get('ate_rmse_m', float('nan')):7.2f} | "
              f"{100 * r.get('rpe1_trans_rmse_m', float('nan')):7.3f} | {r.get('rpe1_rot_rmse_deg', float('nan')):8.3f} | "
              f"{pct if pct is None else round(pct, 2)!s:>6} | {r['time_ms_median']:7.1f} | "
              f"{r['time_ms_p95']:7.1f} | {r['cpu_ms_median']:7.1f} | {r['cpu_ms_p95']:7.1f} | {r['n_ok']:>5} | {r['n_lost']:>4} | {r['first_ok_frame']!s:>6} | "
              f"{r['n_keyframes']:>4}")
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} cores")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        with_traj = [r for r in results if "_traj" in r]
        fig, axes = plt.subplots(1, max(1, len(with_traj)), figsize=(5 * max(1, len(with_traj)), 5))
        for ax, r in zip(np.atleast_1d(axes), with_traj):
            e, g = r["_traj"]
            ax.plot(g[:, 0], g[:, 1], "k-", label="ground truth")
            ax.plot(e[:, 0], e[:, 1], "r-", label="tracked (aligned)")
            ax.set_title(f"{r['case']}: ATE {100 * r['ate_rmse_m']:.2f} cm")
            ax.set_aspect("equal")
            ax.legend()
        Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.plot, dpi=100)
    for r in results:
        r.pop("_traj", None)
    write_results(args.out, {
        "benchmark": "tracking", "overrides": {k: str(v) for k, v in overrides.items()}, "results": results,
        "loadavg": load, "cpu_count": os.cpu_count(),
        "python": platform.python_version(), "stamp_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    })
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

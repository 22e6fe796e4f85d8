"""Benchmark: maps that outlive a flight (map bundles): continue a saved map, localise in it, refuse bad ones.

    python benchmarks/bench_map_bundle.py [--tum DIR] [--out results/bench_map_bundle.json]
    python benchmarks/bench_map_bundle.py --skip-live --skip-bad      # the lockstep figures alone
    python benchmarks/bench_map_bundle.py --table docs/data/map_bundle.json   # the README's table

On the head of fr1/rpy (200 frames, config ``tum_fr1``), each a real ``memgs run`` (node processes
over DDS, lockstep unless said):

- **one session**: all 200 frames (the baseline);
- **session 1**: frames 0-119, which saves a bundle (``OUT/maps``);
- **session 2**: frames 80-199 with ``--map`` session 1's bundle, restamped 1000 s later (a later
  flight: stamps never repeat), which continues the map and saves a new bundle;
- **localize**: all 200 frames, restamped, ``--map`` the one session's bundle ``--mode localize``;
- **live session 2**: session 2 again with ``--realtime`` (2 cores: frames the tracker posed).

Printed: frames session 2 took to relocalise; ATE of both sessions' trajectories under **one**
SE(3) alignment to the ground truth (the one session's own); PSNR of each final map rendered at
all 200 ground-truth poses brought into the map by that alignment (rotation fitted to the
orientations, as the ATE's rotation error is), and Gaussians; localize's posed frames, ATE,
keyframes and Gaussians added, tracker CPU a frame (against the one session's); the time from
reading a bundle to the first relocalised pose (tracker, in this process, kernels warm) and to
a mapper state in memory; the bundle's size beside its PLY's; bad bundles (another camera,
another format version, a truncated PLY, a truncated tracker map) each given to ``memgs run
--map`` (one line, exit 2, no file changed); SIGKILLs at random moments of a save (the previous
bundle and ``latest`` intact, nothing half saved that loads).

Run nothing else meanwhile (one benchmark at a time).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ (not a package): _common
from _common import ROOT, TUM_HELP, run_memgs, tum_path_or_exit, uptime, write_results  # noqa: E402

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

OFFSET_NS = 1000 * 10**9  # session 2 flies 1000 s after session 1
S1, S2 = (0, 120), (80, 200)


def tum_slice(src: Path, out: Path, first: int, end: int, offset_ns: int = 0) -> Path:
    """A TUM folder of ``src``'s frames [first, end) (its associated frames), stamps moved by
    ``offset_ns``; images by link, ground truth carried."""
    from memgs_ros.io.tum import TumFolder, format_stamp, parse_stamp_ns

    stamps = TumFolder(src).frame_stamps()
    lo, hi = int(stamps[first]), int(stamps[min(end, len(stamps)) - 1])
    out.mkdir(parents=True)
    for d in ("rgb", "depth"):
        (out / d).symlink_to((src / d).resolve())
    for name, margin in (("rgb.txt", 0), ("depth.txt", 30_000_000), ("groundtruth.txt", 500_000_000)):
        lines = []
        for line in (src / name).read_text().splitlines():
            if line.startswith("#") or not line.strip():
                lines.append(line)
                continue
            stamp, rest = line.split(maxsplit=1)
            t = parse_stamp_ns(stamp)
            if lo - margin <= t <= hi + margin and (name != "rgb.txt" or lo <= t <= hi):
                lines.append(f"{format_stamp(t + offset_ns)} {rest}")
        (out / name).write_text("\n".join(lines) + "\n")
    return out


def _poses(run_dir: Path, offset_ns: int = 0) -> tuple[np.ndarray, np.ndarray]:
    from memgs_ros.io.tum import read_trajectory

    s, T = read_trajectory(run_dir / "trajectory.txt")
    return s - offset_ns, T


def one_alignment(sessions: list[tuple[np.ndarray, np.ndarray]], gt_s: np.ndarray, gt_T: np.ndarray
                  ) -> tuple[float, np.ndarray]:
    """(RMSE in m of every session's poses under one SE(3) alignment, the 4x4 map -> ground truth):
    positions fit the translation, orientations the rotation (rpy turns in place)."""
    from memgs_ros.core.metrics.trajectory import align_rotations, align_umeyama, associate

    p_est, p_gt, R_est, R_gt = [], [], [], []
    for s, T in sessions:
        ia, ib = associate(s, gt_s, 20_000_000)
        p_est.append(T[ia, :3, 3])
        p_gt.append(gt_T[ib, :3, 3])
        R_est.append(T[ia, :3, :3])
        R_gt.append(gt_T[ib, :3, :3])
    pe, pg = np.concatenate(p_est), np.concatenate(p_gt)
    a = align_umeyama(pe, pg)
    rmse = float(np.sqrt(np.mean(np.sum((a.apply(pe) - pg) ** 2, axis=1))))
    R = align_rotations(np.concatenate(R_est), np.concatenate(R_gt))
    A = np.eye(4)
    A[:3, :3] = R
    A[:3, 3] = pg.mean(0) - R @ pe.mean(0)
    return rmse, A


def psnr_at_gt(ply: Path, tum: Path, A: np.ndarray, run_dir: Path) -> float:
    """Mean PSNR of the map in ``ply`` rendered at every ground-truth pose of ``tum`` brought into
    the map by ``A`` (map -> ground truth), against the frames (as ``memgs eval`` prepares them)."""
    from memgs_ros.core.geometry.poses import invert_pose
    from memgs_ros.core.metrics.trajectory import associate
    from memgs_ros.evaluation.runs import _ground_truth_images, score_map
    from memgs_ros.io.tum import TumFolder
    from memgs_ros.orchestration.run_files import configured_camera, read_params

    params = read_params(run_dir)
    mapper = params.get("mapper", {})
    scale = float(mapper.get("mapping.resolution_scale", 1.0))
    background = tuple(float(v) for v in mapper.get("mapping.background", (0.0, 0.0, 0.0)))  # as memgs eval
    stamps, images, camera, _, mask = _ground_truth_images(str(tum), 0, scale, configured_camera(params))
    gt_s, gt_T = TumFolder(tum).ground_truth()
    ia, ib = associate(stamps, gt_s, 20_000_000)
    poses = invert_pose(A) @ gt_T[ib]
    quality, _, _ = score_map(ply, {"gt": (stamps[ia], poses)}, stamps, images, camera, background=background,
                              use_lpips=False, progress=False, valid_mask=mask)
    psnr = quality["gt"].psnr_db
    assert psnr is not None
    return float(psnr)


def _files(root: Path) -> dict[str, tuple[int, str]]:
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and not p.is_symlink():
            out[str(p.relative_to(root))] = (p.stat().st_size, hashlib.sha256(p.read_bytes()).hexdigest())
    return out


def bad_bundles(good: Path, work: Path, source: Path) -> list[dict[str, Any]]:
    """Each damaged copy of ``good`` given to ``memgs run --map``: its lines, exit code, files changed."""
    from memgs_ros.core.map_io.bundle import MANIFEST, PLY_FILE, TRACKER_FILE

    def edit_manifest(b: Path, **fields: Any) -> None:
        m = json.loads((b / MANIFEST).read_text())
        for k, v in fields.items():
            if k == "fx":
                m["camera"]["fx"] = v
            else:
                m[k] = v
        (b / MANIFEST).write_text(json.dumps(m))

    def truncate(b: Path, name: str) -> None:
        data = (b / name).read_bytes()
        (b / name).write_bytes(data[: len(data) // 2])

    cases = {"another camera": lambda b: edit_manifest(b, fx=300.0),
             "another format version": lambda b: edit_manifest(b, format_version=99),
             "truncated PLY": lambda b: truncate(b, PLY_FILE),
             "truncated tracker map": lambda b: truncate(b, TRACKER_FILE)}
    rows = []
    for name, damage in cases.items():
        b = work / name.replace(" ", "_")
        shutil.copytree(good, b)
        damage(b)
        before = _files(b)
        out = work / f"run_{b.name}"
        r = run_memgs(["run", "--bag", source, "--config", "tum_fr1", "--map", b], out)
        errors = [ln for ln in r.output.splitlines() if "error" in ln.lower()]
        rows.append({"case": name, "returncode": r.returncode, "lines": errors,
                     "files_changed": sum(1 for k, v in _files(b).items() if before.get(k) != v)
                     + len(set(before) - set(_files(b))), "nodes_started": (out / "logs").exists()
                     and any((out / "logs").glob("tracker*"))})
    return rows


_SAVER = textwrap.dedent("""
    import shutil, sys
    from pathlib import Path
    from memgs_ros.core.map_io.bundle import MANIFEST, commit_bundle, new_staging, read_manifest
    from memgs_ros.core.map_io.ply import load_ply, save_ply
    good, root = Path(sys.argv[1]), Path(sys.argv[2])
    while True:  # saves back to back until killed
        staging = new_staging(root)
        for name in ("tracker.npz", "mapper.npz"):
            shutil.copy(good / name, staging / name)
        save_ply(load_ply(good / "map.ply"), staging / "map.ply")
        commit_bundle(staging, read_manifest(good))
""")


def kills_during_save(good: Path, work: Path, trials: int) -> dict[str, Any]:
    """SIGKILL a process saving bundles back to back at ``trials`` random moments; after each,
    every visible bundle must load whole and ``latest`` must name one."""
    from memgs_ros.core.map_io.bundle import LATEST, check_bundle

    root = work / "kill_root"
    root.mkdir()
    shutil.copytree(good, root / "first")
    os.symlink("first", root / LATEST)
    rng = np.random.default_rng(0)
    bad, staged, saved = 0, 0, set()
    for _ in range(trials):
        proc = subprocess.Popen([sys.executable, "-c", _SAVER, str(good), str(root)], cwd=ROOT,
                                env={**os.environ, "PYTHONPATH": str(ROOT)})
        time.sleep(float(rng.uniform(1.0, 4.0)))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        latest = os.readlink(root / LATEST)
        for d in root.iterdir():
            if d.name.startswith("."):
                staged += 1
                continue
            try:
                check_bundle(d)
            except Exception:  # noqa: BLE001 - counted: a visible bundle that does not load
                bad += 1
            else:
                if d.name not in ("first", LATEST):
                    saved.add(d.name)
                if d.name not in ("first", LATEST, latest):
                    shutil.rmtree(d)  # checked: the disk need not hold every save
    latest_ok = True
    try:
        check_bundle(root)
    except Exception:  # noqa: BLE001
        latest_ok = False
    shutil.rmtree(root)
    return {"trials": trials, "bundles_saved_and_checked": len(saved), "visible_that_fail": bad,
            "latest_loads": latest_ok, "unfinished_staging_seen": staged}


def load_time(bundle: Path, tum2: Path) -> dict[str, float]:
    """Seconds from reading the bundle to the first relocalised pose (tracker, kernels warm), and
    to the mapper's state in memory."""
    from memgs_ros.core.mapping.checkpoint import load as load_checkpoint
    from memgs_ros.core.map_io.bundle import MAPPER_FILE, TRACKER_FILE, check_bundle
    from memgs_ros.core.tracking import TrackerConfig, make_tracker, warm_up
    from memgs_ros.core.tracking.map_io import read_tracker_map
    from memgs_ros.io.sources import open_source
    from memgs_ros.orchestration.run_files import _load_config, config_path

    warm_up()
    config = _load_config(config_path("tum_fr1"))
    tracker_params = next(v for k, v in config.items() if str(k).rsplit("/", 1)[-1] == "tracker")["ros__parameters"]
    cfg = TrackerConfig(**{k[len("tracker."):]: v for k, v in tracker_params.items() if k.startswith("tracker.")},
                        ba_threaded=True)
    src = open_source(str(tum2), default_camera=None)
    frames = iter(src)
    first = next(frames)
    t0 = time.perf_counter()
    b, _ = check_bundle(bundle)
    t_check = time.perf_counter() - t0
    m = read_tracker_map(b / TRACKER_FILE)
    with make_tracker(cfg, first.camera) as t:
        t.load_map(m)
        r = t.track(first)
        while r.T_wc is None:
            r = t.track(next(frames))
        t_pose = time.perf_counter() - t0
    t1 = time.perf_counter()
    load_checkpoint(b / MAPPER_FILE)
    return {"check_s": round(t_check, 2), "first_pose_s": round(t_pose, 2),
            "mapper_state_s": round(time.perf_counter() - t1, 2), "relocalized_after": t.relocalized_after}


def table(r: dict[str, Any]) -> str:
    """The README's table of one result (``--table``)."""
    one, two, loc, b, ld = r["one_session"], r["two_sessions"], r["localize"], r["bundle"], r["load"]
    d_psnr = two["psnr_gt_db"] - one["psnr_gt_db"]
    rows = [
        "| figure | one session, frames 0-199 | two sessions: 0-119, then 80-199 with `--map` | asked |",
        "|---|---|---|---|",
        f"| frames of session 2 before its first pose (relocalised) | - | {two['relocalized_after_frames']} | <= 10 |",
        f"| ATE, one SE(3) alignment over every pose | {one['ate_cm']:.2f} cm | {two['ate_cm']:.2f} cm | <= 1.5 cm |",
        f"| PSNR of the final map at all 200 ground-truth poses | {one['psnr_gt_db']:.2f} dB | "
        f"{two['psnr_gt_db']:.2f} dB ({d_psnr:+.2f}) | >= -0.3 dB |",
        f"| Gaussians | {one['gaussians'] / 1000:.1f}k | {two['gaussians'] / 1000:.1f}k "
        f"({two['gaussians'] / one['gaussians']:.2f}x; session 1 {two['session1_gaussians'] / 1000:.1f}k) | <= 1.15x |",
        f"| tracker keyframes | {one['keyframes']} | {two['keyframes_added']} added | - |",
    ]
    if "live_session2" in r:
        lv = r["live_session2"]
        rows.append(f"| session 2 live (`--realtime`, 2 cores): frames posed | - | {lv['tracked_pct']:.1f} % "
                    f"({lv['poses']} of {lv['frames_played']}) | >= 95 % |")
    rows += [
        "",
        "| `--mode localize`, frames 0-199 against the one session's bundle | value | asked |",
        "|---|---|---|",
        f"| frames posed | {loc['posed_pct']:.1f} % | >= 98 % |",
        f"| ATE | {loc['ate_cm']:.2f} cm | <= 1.5 cm |",
        f"| keyframes / Gaussians added | {loc['keyframes_added']} / "
        f"{loc['gaussians'] - loc['bundle_gaussians']} | 0 / 0 |",
        f"| tracker CPU a frame (mapping mode: the one session's) | {loc['tracker_frame_cpu_ms']:.2f} ms "
        f"({one['tracker_frame_cpu_ms']:.2f}) | not above |",
        f"| bundle read to the first relocalised pose (kernels warm) / mapper state in memory | "
        f"{ld['first_pose_s']:.2f} s / {ld['mapper_state_s']:.2f} s | <= 3 s |",
        f"| session 1's bundle on disk: all / its PLY | {b['mb']:.1f} MB / {b['ply_mb']:.1f} MB "
        f"({', '.join(f'{k} {v:.1f}' for k, v in b['files_mb'].items())}) | reported |",
    ]
    if "bad_bundles" in r:
        bad = r["bad_bundles"]
        ok = sum(1 for c in bad if c["returncode"] == 2 and len(c["lines"]) == 1 and not c["files_changed"]
                 and not c["nodes_started"])
        k = r["sigkill_during_save"]
        rows += [f"| bad bundles ({', '.join(c['case'] for c in bad)}): refused before any node, one line, "
                 f"no file changed | {ok} of {len(bad)} | all |",
                 f"| SIGKILL at a random moment of a save ({k['trials']} times): visible bundles that do not load / "
                 f"`latest` loads | {k['visible_that_fail']} of {k['bundles_saved_and_checked']} / "
                 f"{'yes' if k['latest_loads'] else 'no'} | 0 / yes |"]
    return "\n".join(rows) + "\n"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tum", default=None, help=TUM_HELP)
    p.add_argument("--out", type=Path, default=ROOT / "results" / "bench_map_bundle.json")
    p.add_argument("--work", type=Path, default=ROOT / "results" / "bench_map_bundle",
                   help="the runs' folders (replaced unless --reuse)")
    p.add_argument("--skip-live", action="store_true")
    p.add_argument("--skip-bad", action="store_true")
    p.add_argument("--kill-trials", type=int, default=8)
    p.add_argument("--reuse", action="store_true", help="take the runs already finished in --work (scoring again)")
    p.add_argument("--table", type=Path, default=None, metavar="JSON", help="print the README's table of a result")
    args = p.parse_args()
    if args.table is not None:
        print(table(json.loads(args.table.read_text())), end="")
        return 0
    tum = tum_path_or_exit(p, args.tum)
    w, base = args.work, tum.name
    if args.work.exists() and not args.reuse:
        shutil.rmtree(args.work)
    fresh = not (w / f"{base}_s1").exists()
    w.mkdir(parents=True, exist_ok=True)
    s1, s2, whole2 = w / f"{base}_s1", w / f"{base}_s2", w / f"{base}_later"
    if fresh:
        tum_slice(tum, s1, *S1)
        tum_slice(tum, s2, *S2, offset_ns=OFFSET_NS)
        tum_slice(tum, whole2, 0, 200, offset_ns=OFFSET_NS)
    common = ["--config", "tum_fr1"]
    res: dict[str, Any] = {"host": uptime(), "tum": str(tum)}
    runs: dict[str, Any] = {}

    def run(name: str, *extra: Any) -> Any:
        from memgs_ros.orchestration.run_files import SUMMARY_FILE, read_summary

        if args.reuse and (w / name / SUMMARY_FILE).is_file():
            summary = read_summary(w / name)
        else:
            r = run_memgs(["run", *extra, *common], w / name, log=w / f"{name}.log")
            if r.summary is None:
                raise SystemExit(f"{name} failed ({r.returncode}): see {w / f'{name}.log'}")
            summary = r.summary
        runs[name] = {"wall_s": round(summary.wall_s, 1), "frames": summary.frames, "poses": summary.poses,
                      "keyframes": summary.keyframes, "gaussians": summary.gaussians,
                      "relocalizing": summary.relocalizing, "tracker_frame_cpu_ms": summary.tracker_frame_cpu_ms,
                      "bundle": summary.bundle_path}
        print(f"{name}: {runs[name]}", flush=True)
        return summary

    one = run("one_session", "--bag", tum)
    first = run("session1", "--bag", s1)
    bundle = Path(first.bundle_path)
    second = run("session2", "--bag", s2, "--map", bundle)
    loc = run("localize", "--bag", whole2, "--map", one.bundle_path, "--mode", "localize")  # the whole room's map
    from memgs_ros.io.tum import TumFolder

    gt_s, gt_T = TumFolder(tum).ground_truth()
    one_rmse, A_one = one_alignment([_poses(w / "one_session")], gt_s, gt_T)
    two_rmse, A_two = one_alignment([_poses(w / "session1"), _poses(w / "session2", OFFSET_NS)], gt_s, gt_T)
    loc_rmse, _ = one_alignment([_poses(w / "localize", OFFSET_NS)], gt_s, gt_T)
    from memgs_ros.core.map_io.bundle import PLY_FILE, check_bundle

    _, manifest = check_bundle(bundle)
    res.update(
        one_session={"ate_cm": round(100 * one_rmse, 2), "gaussians": one.gaussians, "keyframes": one.keyframes,
                     "psnr_gt_db": round(psnr_at_gt(Path(one.ply_path), tum, A_one, w / "one_session"), 2),
                     "tracker_frame_cpu_ms": one.tracker_frame_cpu_ms},
        two_sessions={"relocalized_after_frames": second.relocalizing, "ate_cm": round(100 * two_rmse, 2),
                      "gaussians": second.gaussians, "session1_gaussians": first.gaussians,
                      "psnr_gt_db": round(psnr_at_gt(Path(second.ply_path), tum, A_two, w / "session2"), 2),
                      "keyframes_added": second.keyframes},
        localize={"posed_pct": round(100 * loc.poses / max(loc.frames, 1), 1), "ate_cm": round(100 * loc_rmse, 2),
                  "keyframes_added": loc.keyframes, "gaussians": loc.gaussians, "bundle_gaussians": one.gaussians,
                  "relocalized_after_frames": loc.relocalizing, "tracker_frame_cpu_ms": loc.tracker_frame_cpu_ms},
        bundle={"path": str(bundle), "mb": round(manifest.bytes / 1e6, 2),
                "ply_mb": round(manifest.files[PLY_FILE]["bytes"] / 1e6, 2),
                "files_mb": {k: round(v["bytes"] / 1e6, 2) for k, v in manifest.files.items()}},
        load=load_time(bundle, s2))
    if not args.skip_live:
        live = run("session2_live", "--bag", s2, "--map", bundle, "--realtime")
        res["live_session2"] = {"tracked_pct": round(100 * live.poses / max(live.frames_played, 1), 1),
                                "frames_played": live.frames_played, "poses": live.poses,
                                "relocalizing": live.relocalizing}
    if not args.skip_bad:
        res["bad_bundles"] = bad_bundles(bundle, w / "bad", s2)
        res["sigkill_during_save"] = kills_during_save(bundle, w, args.kill_trials)
    res["runs"] = runs
    write_results(args.out, res)
    print(table(res), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The node graph end to end: real processes, real DDS, a generated bag replayed in lockstep."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

pytest.importorskip("rclpy", reason="the ROS extra is not installed (pip install -e '.[ros]')")

from memgs_ros.core.gaussians.gaussian_map import GaussianMap  # noqa: E402
from memgs_ros.core.geometry.poses import invert_pose  # noqa: E402
from memgs_ros.core.map_io.ply import load_ply  # noqa: E402
from memgs_ros.core.metrics.image import psnr  # noqa: E402
from memgs_ros.core.metrics.trajectory import ate  # noqa: E402
from memgs_ros.core.raster import rasterize  # noqa: E402
from memgs_ros.io.bag_writer import write_bag  # noqa: E402
from memgs_ros.io.synthetic import generate_frames, parse_spec  # noqa: E402
from memgs_ros.io.tum import read_trajectory  # noqa: E402
from memgs_ros.orchestration.pipeline import RunOptions, run_pipeline  # noqa: E402
from memgs_ros.testing.delta_relay import LOSSY_MERGER, lossy_deltas  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SPEC = "synthetic:w=320,h=240,n=30,seed=3"
# Short, CPU-friendly training: the assertions are about the graph, the quality bounds are
# loose but far above what a broken map gives (an empty or misplaced map renders ~8-12 dB).
FAST = {"mapper.iterations_per_frame": 3, "mapper.final_iterations": 150,
        "mapper.mapping.merge_start_iter": 60, "mapper.mapping.merge_interval": 60}


def _own_ns() -> str:
    """A namespace no other run on this host uses: with the random domain id, a second guard
    against another test run that drew the same domain (the machines are shared)."""
    return f"/memgs_test_{os.getpid()}_{os.urandom(3).hex()}"


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("bag") / "synthetic.mcap"
    write_bag(generate_frames(parse_spec(SPEC)), path)
    return path


def _keyframe_psnr(ply: Path, trajectory: Path, stride: int = 5) -> float:
    """Mean PSNR of the saved map rendered at tracked poses against the source frames."""
    records = load_ply(ply)
    g = GaussianMap.from_records(records, max_sh_degree=3)
    stamps, poses = read_trajectory(trajectory)
    by_stamp = dict(zip(stamps.tolist(), poses))
    values = []
    for i, frame in enumerate(generate_frames(parse_spec(SPEC))):
        if i % stride or frame.stamp_ns not in by_stamp:
            continue
        T_cw = torch.from_numpy(invert_pose(by_stamp[frame.stamp_ns])).float()
        cam = frame.camera.scaled(0.5)  # the mapping resolution
        with torch.no_grad():
            out = rasterize(g.gaussians(), T_cw, cam, sh_degree=3)
        ref = cv2.resize(frame.rgb, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        values.append(psnr(out.color.clamp(0, 1), torch.from_numpy(ref).permute(2, 0, 1).float() / 255))
    return float(np.mean(values))


def test_graph_end_to_end_in_processes(bag: Path, tmp_path: Path, ros_domain_id: int) -> None:
    s = run_pipeline(RunOptions(source=str(bag), config="synthetic", out_dir=tmp_path, namespace=_own_ns(),
                                domain_id=ros_domain_id, overrides=FAST, timeout_s=600), progress=False)
    assert s.frames == 30 and s.poses == 30 and s.lost_frames == 0
    assert 3 <= s.keyframes < 30
    gt_stamps, gt_poses = generate_stamps_and_poses()
    est_stamps, est_poses = read_trajectory(Path(s.trajectory_path))
    err = ate(est_stamps, est_poses, gt_stamps, gt_poses)
    assert err.n_matched == 30 and err.rmse_m < 0.02, err.rmse_m
    assert s.replica_identical and s.gaussians > 1000
    assert Path(s.ply_path).exists() and len(load_ply(s.ply_path)) == s.gaussians
    assert s.render_size == (160, 120) and s.render_std > 10.0
    assert _keyframe_psnr(Path(s.ply_path), Path(s.trajectory_path)) > 20.0
    assert s.delta_messages > 0 and s.delta_bytes > 0
    # Every process's CPU time, from its own last stats.
    assert set(s.cpu_s) == {"tracker", "keyframe_sampler", "mapper", "merger", "player", "runner"}
    assert all(v > 0 for v in s.cpu_s.values())


def generate_stamps_and_poses() -> tuple[np.ndarray, np.ndarray]:
    frames = list(generate_frames(parse_spec(SPEC)))
    return np.array([f.stamp_ns for f in frames]), np.stack([f.T_wc_gt for f in frames])


def test_late_merger_with_dropped_deltas_resyncs(bag: Path, tmp_path: Path, ros_domain_id: int) -> None:
    """The merger process starts 1 s into the replay and a relay drops every 2nd delta on its way: it resyncs from
    snapshots and ends with the mapper's map. (Counted from the replay start: the replay takes
    only ~6 s on an idle machine, and a delay counted from process launch once let the whole run
    finish before the merger came up, leaving nothing to resync; the final iterations send more
    deltas after the replay.)"""
    # 8 iterations a frame: the replay lasts long enough for a few periodic deltas after the late
    # start (no periodic delta leaves during the final iterations: the final flush carries all).
    overrides = {**FAST, "mapper.iterations_per_frame": 8, "mapper.delta_rate_hz": 4.0, **LOSSY_MERGER}
    ns = _own_ns()
    with lossy_deltas(ros_domain_id, ns, every=2) as relay:  # the merger reads the deltas through it
        s = run_pipeline(RunOptions(source=str(bag), config="synthetic", out_dir=tmp_path, domain_id=ros_domain_id,
                                    namespace=ns, overrides=overrides, start_delays_s={"merger": 1.0},
                                    timeout_s=600), progress=False)
    assert relay.dropped >= 1 and relay.forwarded >= 1
    assert s.merger_resyncs >= 1
    assert s.replica_identical, s.replica_max_abs_diff
    assert len(load_ply(s.ply_path)) == s.gaussians


def test_killed_mapper_resumes_from_checkpoint_and_killed_merger_resyncs(bag: Path, tmp_path: Path,
                                                                        ros_domain_id: int) -> None:
    """SIGKILL (no chance to save) the mapper, then the merger, mid-run; both restart at once.
    (More iterations per frame than FAST: the replay must outlast both kills, and with FAST's 3 it
    could end before 12 s on an idle machine, leaving nothing killed.)"""
    overrides = {**FAST, "mapper.iterations_per_frame": 12, "mapper.checkpoint_period_s": 1.0,
                 "merger.save_period_s": 1.0}
    # An earlier run's checkpoint in the folder is set aside (kept), not resumed by this run.
    (tmp_path / "mapper_checkpoint.npz").write_bytes(b"an earlier run")
    s = run_pipeline(RunOptions(source=str(bag), config="synthetic", out_dir=tmp_path, domain_id=ros_domain_id,
                                namespace=_own_ns(), overrides=overrides, kill_after_s={"mapper": 6.0, "merger": 12.0}, timeout_s=600),
                     progress=False)
    assert s.restarts == {"mapper": 1, "merger": 1}
    log = (tmp_path / "logs" / "mapper.log").read_text()
    assert "resumed from" in log, log  # the second life started from the first one's checkpoint
    resumed_n = int(log.split("resumed from")[1].split(":")[1].split()[0])
    assert resumed_n > 1000  # Gaussians in the checkpoint
    assert s.poses == 30 and s.lost_frames == 0
    assert s.replica_identical, s.replica_max_abs_diff
    assert s.gaussians > 1000 and len(load_ply(s.ply_path)) == s.gaussians
    assert (tmp_path / "mapper_checkpoint.npz").exists()
    assert (tmp_path / "mapper_checkpoint.previous.npz").read_bytes() == b"an earlier run"
    [first_life] = (tmp_path / "logs").glob("mapper.killed-*.log")
    assert "resumed from" not in first_life.read_text()  # the first life started a new map
    assert _keyframe_psnr(Path(s.ply_path), Path(s.trajectory_path)) > 18.0


def test_namespaced_instances_do_not_cross_talk(tmp_path: Path, ros_domain_id: int) -> None:
    """Two composed graphs in one ROS domain, each on its own namespace and sequence."""
    procs = {}
    for ns, n in (("/uav_a", 12), ("/uav_b", 20)):
        out = tmp_path / ns.strip("/")
        cmd = [sys.executable, "-m", "memgs_ros", "run", "--bag", f"synthetic:w=128,h=96,n={n},seed=1",
               "--config", "synthetic", "--composed", "--namespace", ns, "--domain-id", str(ros_domain_id),
               "--out", str(out), "--json", str(out / "summary.json"), "--set", "mapper.iterations_per_frame=1",
               "--set", "mapper.mapping.merge_enabled=false", "--timeout", "500"]
        out.mkdir()
        procs[ns] = (n, out, subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                              env=dict(os.environ)))
    for ns, (n, out, p) in procs.items():
        log = p.communicate(timeout=560)[0].decode(errors="replace")
        assert p.returncode == 0, log[-3000:]
        summary = json.loads((out / "summary.json").read_text())
        assert summary["frames"] == n and summary["poses"] == n, (ns, summary)
        assert summary["namespace"] == ns


@pytest.mark.parametrize("strict", [False, True], ids=["skip", "strict"])
def test_a_corrupt_frame_is_skipped_and_counted_or_with_strict_ends_the_run(tmp_path: Path, ros_domain_id: int,
                                                                           strict: bool) -> None:
    """A TUM folder whose 11th colour image is corrupt. By default the frame is skipped: the run
    maps the other 15, exits 0 and its summary counts the skipped frame by kind. With --strict
    the run maps and saves the 10 frames before it, reports the failure (exit 1, one line) and
    does not wait for its timeout."""
    from memgs_ros.io.synthetic import write_tum_folder

    folder = tmp_path / "seq"
    write_tum_folder(generate_frames(parse_spec("synthetic:w=128,h=96,n=16,seed=1")), folder)
    rgb = sorted((folder / "rgb").iterdir())
    rgb[10].write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)  # a header and nothing else
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "memgs_ros", "run", "--bag", str(folder), "--config", "synthetic",
           "--composed", "--domain-id", str(ros_domain_id), "--namespace", _own_ns(), "--out", str(out), "--json",
           str(tmp_path / "summary.json"), "--set", "mapper.iterations_per_frame=1",
           "--set", "mapper.mapping.merge_enabled=false", "--timeout", "400", *(["--strict"] if strict else [])]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    summary = json.loads((tmp_path / "summary.json").read_text())
    if strict:
        assert p.returncode == 1, (p.stdout[-2000:], p.stderr[-3000:])
        assert "failed part-way" in p.stderr and "Traceback" not in p.stderr, p.stderr[-3000:]
        assert summary["source_complete"] is False
        assert summary["frames"] == 10 and summary["poses"] == 10, summary
    else:
        assert p.returncode == 0, (p.stdout[-2000:], p.stderr[-3000:])
        assert summary["source_complete"] is True and summary["skipped_frames"] == {"unreadable_image": 1}, summary
        assert summary["frames"] == 15 and summary["poses"] == 15, summary
        assert "skipped       1 unreadable_image" in p.stdout, p.stdout[-2000:]
    assert summary["gaussians"] > 0 and len(load_ply(Path(summary["ply_path"])).ids) == summary["gaussians"]


def test_a_player_that_ended_cleanly_ends_the_replay_even_if_its_done_message_was_lost(tmp_path: Path) -> None:
    """Under heavy load the latched done message can be lost when the player exits right after
    publishing it: its exit code 0 then ends the wait (after a grace time), instead of --timeout."""
    import time

    from memgs_ros.orchestration import pipeline

    procs = pipeline.NodeProcesses(tmp_path / "p.yaml", "", dict(os.environ), tmp_path)
    procs.procs["bag_player"] = subprocess.Popen([sys.executable, "-c", "import sys; sys.exit(0)"])
    procs.procs["bag_player"].wait()
    assert not pipeline._player_ended_unheard(procs)  # grace time starts now
    assert not pipeline._player_ended_unheard(procs)
    procs.player_exit_seen -= pipeline._DONE_GRACE_S * 1.1  # as if the grace time had passed
    assert pipeline._player_ended_unheard(procs)
    procs.procs["bag_player"] = subprocess.Popen([sys.executable, "-c", "import sys; sys.exit(1)"])
    procs.procs["bag_player"].wait()
    procs.player_exit_seen = time.monotonic() - pipeline._DONE_GRACE_S * 2
    assert not pipeline._player_ended_unheard(procs)  # a failed source is reported by check()


def test_a_kill_waits_until_the_node_has_state_to_lose() -> None:
    """Fault injection kills a mapper only once a checkpoint holds Gaussians (or, never
    checkpointing, once it maps), and a merger once it applied a delta; other nodes at once."""
    from memgs_ros.orchestration.graph_watch import GraphObserver
    from memgs_ros.orchestration.pipeline import _has_state_to_lose

    obs = GraphObserver.__new__(GraphObserver)  # the stats table alone, no rclpy node
    obs.stats, obs._parsed = {}, {}  # each message's values are replaced whole, as the callback does
    assert not _has_state_to_lose(obs, "mapper")  # no stats from it yet
    obs.stats["mapper"] = {"checkpoint_period_s": "1.0", "gaussians": "5000", "checkpoint_gaussians": "0"}
    assert not _has_state_to_lose(obs, "mapper")  # mapping, but its checkpoint is empty
    obs.stats["mapper"] = {**obs.stats["mapper"], "checkpoint_gaussians": "4800"}
    assert _has_state_to_lose(obs, "mapper")
    obs.stats["mapper"] = {"checkpoint_period_s": "0.0", "gaussians": "0"}
    assert not _has_state_to_lose(obs, "mapper")
    obs.stats["mapper"] = {**obs.stats["mapper"], "gaussians": "10"}
    assert _has_state_to_lose(obs, "mapper")
    assert not _has_state_to_lose(obs, "merger")
    obs.stats["merger"] = {"seq": "3"}
    assert _has_state_to_lose(obs, "merger")
    assert _has_state_to_lose(obs, "keyframe_sampler")

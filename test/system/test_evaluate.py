"""``memgs eval`` end to end on a generated sequence: real node processes over DDS, then scoring.

The metric functions (PSNR, SSIM, ATE) are tested by their owners; here: that one short run
yields the JSON with every field, the Markdown table, the PNGs, numbers that are consistent
with the files the run saved, and that the ablation table computes its differences right.
"""
from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("rclpy", reason="the ROS extra is not installed (pip install -e '.[ros]')")

from memgs_ros.cli import main  # noqa: E402
from memgs_ros.core.map_io.ply import load_ply  # noqa: E402
from memgs_ros.evaluation import runs as evaluation  # noqa: E402
from memgs_ros.evaluation.tables import ablation_table  # noqa: E402
from memgs_ros.io.tum import read_trajectory  # noqa: E402

SPEC = "synthetic:w=128,h=96,n=20,seed=0"
TINY = ["--set", "mapper.iterations_per_frame=2", "--set", "mapper.final_iterations=50"]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.mark.ros
@pytest.mark.slow
def test_memgs_eval_end_to_end(tmp_path: Path, ros_domain_id: int) -> None:
    # One run (real processes) serves every check: a second would double the test's time.
    eval_run = tmp_path / "run"
    code = main(["eval", SPEC, "--out", str(eval_run), "--domain-id", str(ros_domain_id), "--timeout", "300", *TINY])
    assert code == 0
    _check_outputs(eval_run)
    _check_round_trip_and_ablation_table(eval_run)


def _check_outputs(eval_run: Path) -> None:
    d = json.loads((eval_run / "eval.json").read_text())
    for key in ("tracking_fps", "mapping_iterations", "mapping_iters_per_s", "gaussians", "frames_quality",
                "keyframes_quality", "trajectory", "memory", "map_samples", "render_size", "resolution_scale"):
        assert key in d, key
    q, k = d["frames_quality"], d["keyframes_quality"]
    # Every tracked frame of the 20 has an exact-stamp ground-truth image; keyframes are a subset.
    stamps, _ = read_trajectory(eval_run / "trajectory.txt")
    assert q["n"] == len(stamps) == d["poses"] > 0
    assert 1 <= k["n"] <= q["n"]
    assert set(k["stamps_ns"]) <= set(q["stamps_ns"])
    # Scores are real numbers in their ranges (an empty or misplaced map renders ~8-12 dB).
    assert 12.0 < q["psnr_db"] < 60.0 and 0.0 < q["ssim"] <= 1.0
    assert q["psnr_db"] == pytest.approx(np.mean(q["psnr_db_per_frame"]))
    assert d["render_size"] == [64, 48] and d["resolution_scale"] == 0.5  # the synthetic config maps at half size
    # Points = rows of the saved PLY; memory: the allocator's peak on CUDA, the mapper's working RSS on CPU.
    assert d["gaussians"] == len(load_ply(eval_run / "map.ply").ids) > 0
    mem = d["memory"]
    assert mem["model_bytes_peak"] > 0
    if torch.cuda.is_available():  # the mapper's device "auto" takes the GPU
        assert mem["mapper_device"].startswith("cuda")
        assert mem["headline_bytes"] == mem["cuda_max_allocated_bytes"] > 0
    else:
        assert mem["mapper_device"] == "cpu" and mem["cuda_max_allocated_bytes"] is None
        # The mapper's peak RSS above its start-up baseline: a few MB at least (keyframes, step
        # buffers), well below the baseline itself (imports and kernels are not working memory).
        assert mem["headline_bytes"] == mem["mapper_working_peak_bytes"] > 0
        assert mem["headline_kind"].startswith("mapper_working_peak_rss")
        assert mem["mapper_rss_baseline_mb"] > 100.0 and mem["headline_bytes"] < mem["mapper_rss_baseline_mb"] * 2**20
        assert mem["accounted_bytes_peak"] >= mem["model_bytes_peak"]
    # Peak RSS per node process: VmHWM, the peak each node reported in the run's stats timeline.
    assert {"tracker", "keyframe_sampler", "mapper", "merger"} <= set(mem["peak_rss_mb"])
    timeline = [json.loads(line) for line in (eval_run / "stats_timeline.jsonl").read_text().splitlines()]
    assert mem["peak_rss_mb"]["mapper"] == max(float(r["peak_rss_mb"]) for r in timeline if r["node"] == "mapper")
    assert len(d["map_samples"]) == sum(1 for r in timeline if r["node"] == "mapper" and "gaussians" in r)
    assert json.loads((eval_run / "summary.json").read_text())["poses"] == d["poses"]
    assert "VmHWM" in mem["peak_rss_source"] and all(v > 20.0 for v in mem["peak_rss_mb"].values())
    # ATE against the synthetic ground truth, SE(3), every pose matched.
    tr = d["trajectory"]
    assert tr["sim3"] is False and tr["scale"] == 1.0 and tr["n_matched"] == len(stamps)
    assert tr["rmse_m"] == pytest.approx(math.sqrt(np.mean(np.square(tr["errors_m"]))))
    # The mapper's stats over time were recorded and end at the run's final size or before it.
    samples = d["map_samples"]
    assert samples and all(s["gaussians"] > 0 for s in samples)
    assert [s["t_s"] for s in samples] == sorted(s["t_s"] for s in samples)
    assert d["tracking_fps"] > 0 and d["mapping_iterations"] >= 50
    table = (eval_run / "table.md").read_text()
    assert table.startswith("| method | PSNR dB / Mem GB / Points k")
    assert f"| {q['psnr_db']:.2f} / " in table and f"/ {d['gaussians'] / 1000:.1f} |" in table
    for name in ("trajectory.png", "psnr.png", "map_size.png", "strip.png"):
        assert (eval_run / name).read_bytes()[:8] == PNG_MAGIC, name
    strip = np.load(eval_run / "strip.npz")
    assert strip["renders"].shape[1:] == (48, 64, 3) and strip["renders"].shape == strip["reals"].shape


def _check_round_trip_and_ablation_table(eval_run: Path) -> None:
    full = evaluation.result_from_dict(json.loads((eval_run / "eval.json").read_text()))
    assert full.gaussians > 0 and full.frames_quality.n > 0
    # A variant with twice the Gaussians, half the memory, 1 dB less and 2 cm more ATE.
    assert full.trajectory is not None and full.frames_quality.psnr_db is not None
    other = replace(full, variant="no_merge", gaussians=2 * full.gaussians,
                    memory=replace(full.memory, mapper_working_peak_bytes=full.memory.headline_bytes // 2),
                    frames_quality=replace(full.frames_quality, psnr_db=full.frames_quality.psnr_db - 1.0),
                    trajectory=replace(full.trajectory, rmse_m=full.trajectory.rmse_m + 0.02))
    table = ablation_table([full, other])
    last = table.strip().splitlines()[-1]
    cells = [c.strip() for c in last.strip("|").split("|")]
    assert cells[0] == "w/o merging"
    assert cells[1] == "+100.0 %"
    h = full.memory.headline_bytes  # the ablation compares the headline memory (working peak on CPU)
    assert cells[2] == f"{100.0 * (h // 2 - h) / h:+.1f} %"
    assert cells[3] == "-1.00" and cells[5] == "+2.00"

"""The benchmarks' shared helper (``benchmarks/_common.py``): where the TUM data is found, the
results writer and the memgs command runner; and no benchmark names a machine's own path."""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import _common  # noqa: E402 - the benchmarks folder is not a package

from memgs_ros.orchestration.run_files import SUMMARY_FILE, RunSummary  # noqa: E402


def _tum_folder(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "rgb.txt").write_text("# timestamp filename\n")
    return path


def test_tum_path_takes_the_argument_then_the_environment_then_the_shared_folder(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    arg, env = _tum_folder(tmp_path / "arg"), _tum_folder(tmp_path / "env")
    monkeypatch.setenv(_common.TUM_ENV, str(env))
    assert _common.tum_path(str(arg)) == arg
    assert _common.tum_path(None) == env
    monkeypatch.delenv(_common.TUM_ENV)
    # Beside the checkout, found from the helper's own location: no machine's path in the source.
    default = _common.tum_path(check=False)
    assert default == ROOT.parent / "shared" / "data" / "tum" / "rgbd_dataset_freiburg1_rpy_head"


def test_a_missing_tum_folder_says_both_ways_to_name_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(_common.TUM_ENV, str(tmp_path / "gone"))
    with pytest.raises(_common.TumNotFound) as err:
        _common.tum_path()
    assert str(err.value) == f"no TUM folder at {tmp_path / 'gone'} (no rgb.txt): pass --tum DIR or set MEMGS_TUM=DIR"
    assert err.value.path == tmp_path / "gone"
    (tmp_path / "empty").mkdir()  # a folder without rgb.txt is not a TUM folder either
    with pytest.raises(_common.TumNotFound):
        _common.tum_path(tmp_path / "empty")


def test_a_missing_tum_folder_is_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser(prog="bench_x")
    assert _common.tum_path_or_exit(parser, _tum_folder(tmp_path / "tum")) == tmp_path / "tum"
    with pytest.raises(SystemExit) as exit_:
        _common.tum_path_or_exit(parser, tmp_path / "gone")
    assert exit_.value.code == 2
    assert "bench_x: error: no TUM folder at" in capsys.readouterr().err


def test_write_results_replaces_the_file_whole_and_keeps_non_finite_figures(tmp_path: Path) -> None:
    path = tmp_path / "results" / "bench.json"  # its folder is made
    _common.write_results(path, {"old": 1})
    written = _common.write_results(path, {"fault_at_s": float("nan"), "out_dir": tmp_path, "rows": [1, 2]})
    assert written == path
    saved = json.loads(path.read_text())
    assert math.isnan(saved["fault_at_s"]) and saved["out_dir"] == str(tmp_path) and "old" not in saved
    assert path.read_text().endswith("\n")
    assert sorted(p.name for p in path.parent.iterdir()) == ["bench.json"]  # no temporary file left


def _summary(**kw: object) -> RunSummary:
    values = {"source": "s", "frames": 3, "poses": 3, "keyframes": 1, "gaussians": 10, "tracking_fps": 1.0,
              "wall_s": 2.0, "ply_path": "map.ply", "trajectory_path": "trajectory.txt", "delta_messages": 0,
              "delta_bytes": 0, "delta_bytes_per_s": 0.0, "lost_frames": 0, "merger_seq": 0, "namespace": "",
              "domain_id": 0, "mapping_iterations": 5, "model_bytes_peak": 0, "gaussians_peak": 10,
              "peak_rss_mb": {}, "merger_resyncs": 0, "restarts": {}, "replica_identical": True,
              "replica_max_abs_diff": 0.0, "render_size": (0, 0), "render_std": 0.0}
    return RunSummary(**{**values, **kw})  # type: ignore[arg-type]


def test_run_memgs_reads_the_summary_of_a_finished_command_only(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / SUMMARY_FILE).write_text(json.dumps(_summary(frames_played=7).as_dict()))
    # --help ends at once with exit 0, before --out is read: the summary in OUT is what it left.
    ok = _common.run_memgs(["--help"], out)
    assert ok.ok and "usage: memgs" in ok.output and ok.wall_s > 0
    assert ok.command[-2:] == ("--out", str(out)) and ok.summary is not None and ok.summary.frames_played == 7
    failed = _common.run_memgs(["no-such-command"], out)
    assert failed.returncode == 2 and failed.summary is None and "invalid choice" in failed.output
    log = tmp_path / "memgs.log"
    logged = _common.run_memgs(["--help"], log=log)
    assert logged.output == "" and "usage: memgs" in log.read_text() and logged.summary is None


def test_run_memgs_reports_a_timeout() -> None:
    run = _common.run_memgs(["--help"], timeout_s=1e-4)  # killed before the interpreter is up
    assert run.returncode == _common.TIMED_OUT and run.summary is None


def test_no_benchmark_names_a_machines_own_path() -> None:
    """Data is found through --tum / MEMGS_TUM / the checkout's location; output under results/."""
    absolute = re.compile(r"(?<![\w.$])/(work|home|root|check|tmp|mnt|Users)/")
    found = [f"{p.relative_to(ROOT)}:{n}" for p in sorted((ROOT / "benchmarks").rglob("*.py"))
             for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if absolute.search(line)]
    assert not found, found

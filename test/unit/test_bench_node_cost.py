"""The node-cost breakdown's stage timer: a stage's time excludes the stages nested in it, so the
rows of ``benchmarks/bench_node_cost.py`` add up to the frame path."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from bench_node_cost import StageTimer  # noqa: E402 - the benchmarks folder is not a package


def _spin(seconds: float) -> None:
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_a_stage_excludes_the_stages_nested_in_it() -> None:
    timer = StageTimer()
    inner = timer.wrap("inner", lambda: _spin(0.03))

    def outer_body() -> None:
        _spin(0.02)
        inner()
        inner()

    outer = timer.wrap("outer", outer_body)
    t0 = time.thread_time()
    outer()
    total = time.thread_time() - t0
    assert timer.frame["inner"] >= 0.06
    assert 0.02 <= timer.frame["outer"] < 0.035  # its own 20 ms, not the inner 60 ms
    assert abs(timer.frame["outer"] + timer.frame["inner"] - total) < 0.005


def test_a_stage_that_raises_still_counts_and_unwinds() -> None:
    timer = StageTimer()

    def boom() -> None:
        _spin(0.01)
        raise ValueError("x")

    failing = timer.wrap("boom", boom)
    with pytest.raises(ValueError, match="x"):
        failing()
    assert timer.frame["boom"] >= 0.01 and timer._stack == []  # noqa: SLF001


def test_the_opencv_floor_times_each_part_and_the_table_shows_what_remains(tmp_path: Path) -> None:
    from bench_node_cost import FLOOR_PARTS, opencv_floor, table

    from memgs_ros.io.synthetic import SyntheticSpec, generate_frames, write_tum_folder

    write_tum_folder(generate_frames(SyntheticSpec(width=320, height=240, n_frames=8, seed=3)), tmp_path / "seq")
    floor = opencv_floor(tmp_path / "seq", {"tracker.n_levels": 4, "color_topic": "ignored"}, 8)
    assert set(floor) == {*FLOOR_PARTS, "orb"}
    assert all(v > 0 for v in floor.values())
    # The unit runs FAST and smooths too (on 8 levels against these 4): the floor stays below it.
    assert sum(floor[k] for k in FLOOR_PARTS) < 2 * floor["orb"]
    res = {"source": "seq", "config": "x", "frames": 3, "date": "d", "mean_node_ms": 6.0, "mean_orb_ms": 2.0,
           "stages_ms": {"a": 6.0}, "stages_orb": {"a": 3.0}, "median": {"node_ms": 6, "orb_ms": 2, "ratio": 3},
           "opencv_floor_ms": {**dict.fromkeys(FLOOR_PARTS, 0.5), "orb": 2.0},
           "opencv_floor_orb": dict.fromkeys(FLOOR_PARTS, 0.25)}
    text = table(res)
    assert "| **floor** | **1.50** | **0.75** |" in text
    assert "1.25 remain for everything else" in text and "spends 2.25 there" in text


def test_every_stage_names_a_function_that_exists() -> None:
    """A stage renamed or moved in the code fails here, not in the benchmark's run."""
    import importlib

    from bench_node_cost import STAGES

    for label, module, attr in STAGES:
        owner = importlib.import_module(module)
        for part in attr.split("."):
            owner = getattr(owner, part, None)
            assert owner is not None, f"{label}: {module}.{attr} is gone"
        assert callable(owner), label

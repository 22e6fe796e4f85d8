"""The node-cost breakdown's stage timer: a stage's time excludes the stages nested in it, so the
rows of ``benchmarks/bench_node_cost.py`` add up to the frame path."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

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

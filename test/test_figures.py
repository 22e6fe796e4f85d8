"""Every figure in the README comes from the same benchmark run as the table beside it.

``benchmarks/make_figures.py`` writes a table (``benchmarks/figures/<name>.md``) and its PNGs
together, each PNG carrying the table's SHA-256, and puts both in a README block. These tests
fail when a figure is re-made without its table (or the README table is edited by hand).
"""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Images that are not plots of a benchmark table (a screenshot of a viewer): listed, not exempt silently.
SCREENSHOTS = {"benchmarks/figures/rerun_view.png"}


def _make_figures():  # noqa: ANN202 - the benchmarks folder is not a package
    spec = importlib.util.spec_from_file_location("make_figures", ROOT / "benchmarks" / "make_figures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_figures_match_the_tables_beside_them() -> None:
    mf = _make_figures()
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = mf.readme_blocks(text)
    assert blocks, "the README has no figures blocks"
    in_blocks = set()
    for name, table, images in blocks:
        sidecar = ROOT / "benchmarks" / "figures" / f"{name}.md"
        assert sidecar.is_file(), f"block {name}: no {sidecar.name}"
        assert table == sidecar.read_text(encoding="utf-8"), f"block {name}: README table differs from {sidecar.name}"
        assert images, f"block {name} has no figure"
        for image in images:
            assert mf.png_table_sha(ROOT / image) == mf.table_sha(table), f"{image} was not made with the table of {name}"
            in_blocks.add(image)
    for image in mf._IMAGE.findall(text):
        assert image in in_blocks or image in SCREENSHOTS, f"README image {image} is outside a figures block"
        assert (ROOT / image).is_file(), image


def test_a_figure_from_another_run_is_caught(tmp_path: Path) -> None:
    """The check above can fail: re-making a figure from a different table changes its digest."""
    mf = _make_figures()
    from matplotlib.figure import Figure

    fig = Figure()
    fig.subplots().plot([0, 1], [0, 1])
    png = mf._save(fig, tmp_path / "x.png", "| a |\n| --- |\n| 1 |\n")
    assert mf.png_table_sha(png) == mf.table_sha("| a |\n| --- |\n| 1 |\n")
    assert mf.png_table_sha(png) != mf.table_sha("| a |\n| --- |\n| 2 |\n")
    text = "x\n<!-- figures:n -->\nold\n<!-- /figures:n -->\ny\n"
    block = mf.readme_block("n", "| a |\n| --- |\n| 1 |\n", [png], tmp_path / "README.md")
    new = mf.replace_block(text, "n", block)
    [(name, table, images)] = mf.readme_blocks(new)
    assert (name, table, images) == ("n", "| a |\n| --- |\n| 1 |\n", ["x.png"])
    with pytest.raises(ValueError, match="no '<!-- figures:m -->'"):
        mf.replace_block(text, "m", block)


def test_load_figures_from_a_bench_load_record(tmp_path: Path) -> None:
    mf = _make_figures()
    timeline = [{"t_s": t, "node": n, "rss_mb": 100.0 + t, "gaussians": 10 * t, "keyframes": t // 10}
                for t in range(0, 300, 5) for n in ("tracker", "mapper")]
    trend = {"first_min_median": 150, "first_min_peak": 160, "last_min_median": 170, "last_min_peak": 180,
             "floors_mb": [140, 150]}
    record = {"spec": "synthetic:w=64", "seconds": 300.0, "fps": 30.0, "frames_tracked": 10, "keyframes": 3,
              "gaussians": 1000, "mapping_iterations": 5, "loadavg_before": 1.0, "loadavg_after": 2.0,
              "nodes": {"tracker": {"rss_mb_start": 100, "trend": trend}, "mapper": {"rss_mb_start": 200, "trend": trend}},
              "timeline": timeline, "command": "python benchmarks/bench_load.py --seconds 300"}
    table, images = mf.load_figures(json.loads(json.dumps(record)), "load", tmp_path)
    assert "| mapper | 200 | 150 (160) | 170 (180) | 140 → 150 |" in table
    assert [p.name for p in images] == ["load.png"] and mf.png_table_sha(images[0]) == mf.table_sha(table)

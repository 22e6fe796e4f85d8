"""Every figure in the documentation comes from the same benchmark run as the table beside it.

``tools/make_figures.py`` writes a table (``benchmarks/figures/<name>.md``) and its PNGs
together, each PNG carrying the table's SHA-256, and puts both in a block of a page
(``README.md`` or ``docs/*.md``). These tests fail when a figure is re-made without its table,
a table is edited by hand, or an image link does not resolve from the page that holds it.
"""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# Images that are not plots of a benchmark table (a screenshot of a viewer): listed, not exempt silently.
SCREENSHOTS = {"benchmarks/figures/rerun_view.png"}  # relative to the repository root


def _make_figures():  # noqa: ANN202 - tools/ is not a package
    spec = importlib.util.spec_from_file_location("make_figures", ROOT / "tools" / "make_figures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _from_root(page: Path, link: str) -> str:
    """An image link of ``page`` as a path relative to the repository root."""
    return (page.parent / link).resolve().relative_to(ROOT).as_posix()


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT).as_posix() for p in PAGES])
def test_figures_match_the_tables_beside_them(page: Path) -> None:
    mf = _make_figures()
    text = page.read_text(encoding="utf-8")
    in_blocks = set()
    for name, table, images in mf.readme_blocks(text):
        sidecar = ROOT / "benchmarks" / "figures" / f"{name}.md"
        assert sidecar.is_file(), f"{page.name}, block {name}: no {sidecar.name}"
        assert table == sidecar.read_text(encoding="utf-8"), (
            f"{page.name}, block {name}: table differs from {sidecar.name}")
        assert images, f"{page.name}, block {name} has no figure"
        for image in images:
            assert (page.parent / image).is_file(), f"{page.name}: {image} does not resolve from {page.parent}"
            assert mf.png_table_sha(page.parent / image) == mf.table_sha(table), (
                f"{page.name}: {image} was not made with the table of {name}")
            in_blocks.add(image)
    for image in mf._IMAGE.findall(text):
        assert (page.parent / image).is_file(), f"{page.name}: {image} does not resolve from {page.parent}"
        assert image in in_blocks or _from_root(page, image) in SCREENSHOTS, (
            f"{page.name}: image {image} is outside a figures block")


def test_the_blocks_are_where_the_docs_say() -> None:
    """The headline evaluation stays in the README; the detailed results live in docs/results.md.
    Each block appears once over all pages (make_figures.py replaces one page's block)."""
    mf = _make_figures()
    where = {name: page.relative_to(ROOT).as_posix() for page in PAGES
             for name, _, _ in mf.readme_blocks(page.read_text(encoding="utf-8"))}
    counts = [name for page in PAGES for name, _, _ in mf.readme_blocks(page.read_text(encoding="utf-8"))]
    assert sorted(counts) == sorted(where), f"a figures block appears twice: {counts}"
    assert where.get("tum_fr1_rpy") == "README.md" and where.get("load_30hz_640x480") == "docs/results.md", where
    assert mf.pages_with_block("load_30hz_640x480") == [ROOT / "docs" / "results.md"]


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
    # A page in a subfolder links the same image relative to itself.
    in_docs = mf.readme_block("n", "| a |\n| --- |\n| 1 |\n", [png], tmp_path / "docs" / "results.md")
    assert mf.readme_blocks(mf.replace_block(text, "n", in_docs))[0][2] == ["../x.png"]
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
              "nodes": {"tracker": {"rss_mb_start": 100, "trend": trend},
                        "mapper": {"rss_mb_start": 200, "trend": trend}},
              "timeline": timeline, "command": "python benchmarks/harness/bench_load.py --seconds 300"}
    table, images = mf.load_figures(json.loads(json.dumps(record)), "load", tmp_path)
    assert "| mapper | 200 | 150 (160) | 170 (180) | 140 → 150 |" in table
    assert [p.name for p in images] == ["load.png"] and mf.png_table_sha(images[0]) == mf.table_sha(table)


def test_a_page_without_the_block_is_refused_before_anything_is_written(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mf = _make_figures()
    page = tmp_path / "page.md"
    page.write_text("no blocks here\n", encoding="utf-8")
    out = tmp_path / "figures"
    code = mf.main(["load", str(tmp_path / "unread.json"), "--name", "load_30hz_640x480", "--out", str(out),
                    "--readme", str(page)])
    assert code == 2 and not out.exists()
    err = capsys.readouterr().err
    assert "page.md has no '<!-- figures:load_30hz_640x480 -->' block; it is in docs/results.md" in err


def test_the_gpu_table_in_the_docs_is_the_saved_runs() -> None:
    """docs/results.md's GPU table is what ``bench_gpu.py --table`` prints for the JSON beside it,
    so the numbers and the saved run change together."""
    spec = importlib.util.spec_from_file_location("bench_gpu", ROOT / "benchmarks" / "harness" / "bench_gpu.py")
    assert spec is not None and spec.loader is not None
    bench_gpu = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench_gpu)
    saved = json.loads((ROOT / "docs" / "data" / "bench_gpu_h200.json").read_text())
    assert bench_gpu.table(saved) in (ROOT / "docs" / "results.md").read_text()
    assert saved["headline"] == bench_gpu.headline(saved)


def test_the_two_hosts_table_in_the_docs_is_the_saved_runs() -> None:
    """docs/results.md's two-host table is what ``bench_two_hosts.py --table`` prints for its JSON."""
    pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    import subprocess
    import sys

    out = subprocess.run([sys.executable, str(ROOT / "test" / "system" / "harness" / "bench_two_hosts.py"), "--table",
                          str(ROOT / "docs" / "data" / "two_hosts_5mbit.json")], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert out.strip() and out in (ROOT / "docs" / "results.md").read_text()


def test_the_fault_matrix_in_the_docs_is_the_saved_runs() -> None:
    """docs/results.md's fault matrix is what ``bench_faults.py --table`` prints for its JSON."""
    pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    import subprocess
    import sys

    out = subprocess.run([sys.executable, str(ROOT / "test" / "system" / "harness" / "bench_faults.py"), "--table",
                          str(ROOT / "docs" / "data" / "faults_matrix.json")], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert out.strip() and out.rstrip("\n") in (ROOT / "docs" / "results.md").read_text()


def test_the_live_table_in_the_readme_is_the_saved_runs() -> None:
    """The README's live table is what ``bench_live.py --table`` prints for the JSON in docs/data."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "harness" / "bench_live.py"), "--table",
                          str(ROOT / "docs" / "data" / "bench_live.json")], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert out.strip() and out in (ROOT / "README.md").read_text()


def test_the_node_cost_table_in_the_results_is_the_saved_run() -> None:
    """docs/results.md's frame-path breakdown is what ``bench_node_cost.py --table`` prints for the
    JSON in docs/data."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_node_cost.py"), "--table",
                          str(ROOT / "docs" / "data" / "bench_node_cost.json")], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert out.strip() and out in (ROOT / "docs" / "results.md").read_text()


def test_the_map_bundle_table_in_the_readme_is_the_saved_run() -> None:
    """The README's map-bundle table is what ``bench_map_bundle.py --table`` prints for the JSON in docs/data."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_map_bundle.py"), "--table",
                          str(ROOT / "docs" / "data" / "map_bundle.json")], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert out.strip() and out in (ROOT / "README.md").read_text()

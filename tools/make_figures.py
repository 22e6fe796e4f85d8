"""Make the documentation's figures and the tables beside them from one benchmark run, together.

    python tools/make_figures.py eval results/bench_eval.json --name tum_fr1_rpy --readme README.md
    python tools/make_figures.py load results/bench_load_cap600.json --name load_30hz_640x480 \
        --readme docs/results.md
    python tools/make_figures.py flight docs/data/long_flight_before.json docs/data/long_flight_pingpong.json \
        --name long_flight_tum --readme README.md

``eval`` takes the JSON ``benchmarks/bench_eval.py`` writes (one evaluation or an ablation);
``load`` the JSON of ``benchmarks/harness/bench_load.py``; ``flight`` one or more JSONs of
``benchmarks/bench_long_flight.py`` (a table row and a figure colour each). Each writes into ``benchmarks/figures/``:
``<name>.md`` (the table) and the PNGs, every PNG carrying the SHA-256 of that table in its
metadata (``memgs-table-sha256``). With ``--readme FILE`` (``README.md`` or a page under
``docs/``) the block between ``<!-- figures:<name> -->`` and ``<!-- /figures:<name> -->`` in FILE
is replaced by the table and the images, linked relative to FILE. ``test/unit/test_figures.py``
checks every such block in ``README.md`` and ``docs/*.md`` against its table and PNGs, so a
figure and the table beside it cannot come from different runs.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

ROOT = Path(__file__).resolve().parents[1]
FIGURES = ROOT / "benchmarks" / "figures"
SHA_KEY = "memgs-table-sha256"  # PNG text chunk: the table a figure belongs to
_BLOCK = re.compile(r"<!-- figures:(?P<name>[\w.-]+) -->\n(?P<body>.*?)<!-- /figures:(?P=name) -->", re.S)
_IMAGE = re.compile(r"!\[[^\]]*\]\((?P<path>[^)]+\.png)\)")


def table_sha(table: str) -> str:
    return hashlib.sha256(table.encode("utf-8")).hexdigest()


def png_table_sha(path: Path) -> str | None:
    """The table digest a PNG written by this script carries, or None."""
    from PIL import Image  # matplotlib's own dependency

    with Image.open(path) as img:
        return img.info.get(SHA_KEY)


def _save(fig: Figure, path: Path, table: str) -> Path:
    FigureCanvasAgg(fig)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, metadata={SHA_KEY: table_sha(table), "Software": "memgs_ros make_figures"})
    return path


def image_link(image: Path, page: Path) -> str:
    """``image`` as a Markdown link target relative to the folder of ``page`` (``../benchmarks/...``
    from a page under ``docs/``)."""
    return Path(os.path.relpath(image.resolve(), page.resolve().parent)).as_posix()


def readme_block(name: str, table: str, images: Sequence[Path], readme: Path) -> str:
    """The figures block ``name``: the table, then the images linked relative to ``readme``."""
    links = "\n".join(f"![{p.stem}]({image_link(p, readme)})" for p in images)
    return f"<!-- figures:{name} -->\n{table.rstrip()}\n\n{links}\n<!-- /figures:{name} -->"


def replace_block(text: str, name: str, block: str) -> str:
    """``text`` with the figures block ``name`` replaced by ``block``; ValueError when it has none."""
    pattern = re.compile(rf"<!-- figures:{re.escape(name)} -->\n.*?<!-- /figures:{re.escape(name)} -->", re.S)
    if not pattern.search(text):
        raise ValueError(f"no '<!-- figures:{name} -->' ... '<!-- /figures:{name} -->' block")
    return pattern.sub(lambda _: block, text, count=1)


def readme_blocks(text: str) -> list[tuple[str, str, list[str]]]:
    """(name, table text, image paths as written, i.e. relative to the page) of every figures block
    in a page's text."""
    out = []
    for m in _BLOCK.finditer(text):
        body = m.group("body")
        images = [i.group("path") for i in _IMAGE.finditer(body)]
        table = _IMAGE.sub("", body).strip() + "\n"
        out.append((m.group("name"), table, images))
    return out


# ----------------------------------------------------------------------------- eval


def eval_figures(record: dict[str, Any], name: str, out_dir: Path) -> tuple[str, list[Path]]:
    """Table and figures of a bench_eval.py JSON: the ablation (or single) table, then the full
    variant's trajectory and PSNR-per-frame plots and, for an ablation, map size per variant."""
    from memgs_ros.evaluation.figures import save_ablation_plot, save_plots
    from memgs_ros.evaluation.tables import ablation_table, markdown_table
    from memgs_ros.evaluation.runs import result_from_dict

    result = record["result"]
    variants = result.get("variants") or [result]
    results = [result_from_dict(v) for v in variants]
    table = ablation_table(results) if len(results) > 1 else markdown_table(results)
    table = f"{table.rstrip()}\n\n`{' '.join(['python benchmarks/bench_eval.py', *record.get('argv', [])])}` " \
            f"({record.get('uptime_before', '').split('load average:')[-1].strip() or 'load n/a'} load before)\n"
    meta = {SHA_KEY: table_sha(table), "Software": "memgs_ros make_figures"}
    written = save_plots(results[0], out_dir, prefix=f"{name}_", kinds=("trajectory", "psnr"), metadata=meta)
    if len(results) > 1:
        path = save_ablation_plot(results, out_dir, prefix=f"{name}_", metadata=meta)
        written += [path] if path is not None else []
    return table, written


# ----------------------------------------------------------------------------- load


def load_figures(record: dict[str, Any], name: str, out_dir: Path) -> tuple[str, list[Path]]:
    """Table (RSS per node: start, first/last minute median and peak, 30 s floors) and the RSS /
    map-size figure of a bench_load.py JSON (which keeps its stats timeline for this)."""
    timeline = record.get("timeline")
    if not timeline:
        raise SystemExit("this bench_load JSON has no 'timeline': re-run benchmarks/harness/bench_load.py")
    lines = ["| node | start MB | first minute: median (peak) MB | last minute: median (peak) MB | "
             "30 s floors, first → last MB |", "| --- | --- | --- | --- | --- |"]
    for node, n in record["nodes"].items():
        t = n.get("trend")
        if t:
            lines.append(f"| {node} | {n['rss_mb_start']:.0f} "
                         f"| {t['first_min_median']:.0f} ({t['first_min_peak']:.0f}) "
                         f"| {t['last_min_median']:.0f} ({t['last_min_peak']:.0f}) "
                         f"| {t['floors_mb'][0]:.0f} → {t['floors_mb'][-1]:.0f} |")
    cap = record.get("mapper_max_mapper_mbytes") or 0.0
    acc = record.get("mapper_accounted_mb_max")
    lines += ["", f"`{record.get('command', 'python benchmarks/harness/bench_load.py')}`: {record['seconds']:.0f} s of "
              f"{record['spec']} at {record['fps']:.0f} Hz; {record['frames_tracked']} frames tracked, "
              f"{record['keyframes']} keyframes, {record['gaussians']} Gaussians at the end, "
              f"{record['mapping_iterations']} mapping iterations; mapper cap {cap:g} MiB"
              + (f", accounted peak {acc:.1f} MiB" if acc else "")
              + f"; load {record['loadavg_before']:.1f} → {record['loadavg_after']:.1f}"]
    table = "\n".join(lines) + "\n"
    fig = Figure(figsize=(9, 6))
    a, b = fig.subplots(2, 1, sharex=True)
    for node in record["nodes"]:
        rows = [r for r in timeline if r["node"] == node and "rss_mb" in r]
        a.plot([r["t_s"] for r in rows], [float(r["rss_mb"]) for r in rows], label=node)
    a.set_ylabel("resident memory [MB]")
    a.legend(loc="upper left", fontsize="small")
    a.grid(True, alpha=0.3)
    rows = [r for r in timeline if r["node"] == "mapper"]
    b.plot([r["t_s"] for r in rows], [float(r.get("gaussians", "nan")) / 1000 for r in rows], label="Gaussians")
    b.set_ylabel("Gaussians (mapper) [k]")
    b.set_xlabel("time since start [s]")
    b.grid(True, alpha=0.3)
    b2 = b.twinx()
    b2.plot([r["t_s"] for r in rows], [float(r.get("keyframes", "nan")) for r in rows], color="tab:red")
    b2.set_ylabel("keyframes inserted", color="tab:red")
    return table, [_save(fig, out_dir / f"{name}.png", table)]


# ----------------------------------------------------------------------------- flight


def flight_figures(records: Sequence[dict[str, Any]], name: str, out_dir: Path) -> tuple[str, list[Path]]:
    """Table and timelines of one or more bench_long_flight.py JSONs, a row per result and mode."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_long_flight as blf

    runs = []
    for r in records:
        loads = sorted({run.get("uptime_before", "").split("load average:")[-1].strip()
                        for runs_ in r["modes"].values() for run in runs_} - {""})
        runs.append(f"{r.get('label') or 'runs'}: {Path(r['source']).name} x{r['passes']}"
                    f"{' forward' if r.get('repeat_forward') else ''} ({r['config']}), "
                    f"{', '.join(f'{m} x{len(v)}' for m, v in r['modes'].items())}; load before {'; '.join(loads) or 'n/a'}")
    table = f"{blf.table(records).rstrip()}\n\n`python benchmarks/bench_long_flight.py` runs: " + " · ".join(runs) + "\n"
    path = out_dir / f"{name}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    blf.plot(records, path, metadata={SHA_KEY: table_sha(table), "Software": "memgs_ros make_figures"})
    return table, [path]


def pages_with_block(name: str, root: Path = ROOT) -> list[Path]:
    """The documentation pages (``README.md``, ``docs/*.md``) that hold the figures block ``name``."""
    pages = [root / "README.md", *sorted((root / "docs").glob("*.md"))]
    return [p for p in pages if p.is_file() and any(b[0] == name for b in readme_blocks(p.read_text(encoding="utf-8")))]


KINDS: dict[str, Callable[[dict[str, Any], str, Path], tuple[str, list[Path]]]] = {
    "eval": eval_figures, "load": load_figures}
MULTI_KINDS = {"flight": flight_figures}  # these take several results, a row each


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("kind", choices=sorted([*KINDS, *MULTI_KINDS]))
    p.add_argument("result", type=Path, nargs="+", help="the benchmark's JSON (flight: one or more)")
    p.add_argument("--name", required=True, help="figure name prefix and documentation block name")
    p.add_argument("--out", type=Path, default=FIGURES, help="folder for the PNGs and the table (.md)")
    p.add_argument("--readme", type=Path, default=None,
                   help="replace the block <!-- figures:NAME --> in this page (README.md or docs/*.md)")
    args = p.parse_args(argv)
    page = args.readme.read_text(encoding="utf-8") if args.readme is not None else ""
    if args.readme is not None and args.name not in {b[0] for b in readme_blocks(page)}:
        # Checked before any file is written: new figures without their page would fail test_figures.
        found = ", ".join(path.relative_to(ROOT).as_posix() for path in pages_with_block(args.name))
        print(f"{args.readme} has no '<!-- figures:{args.name} -->' block" + (f"; it is in {found}" if found else ""),
              file=sys.stderr)
        return 2
    if args.kind not in MULTI_KINDS and len(args.result) != 1:
        print(f"{args.kind} takes one result JSON, got {len(args.result)}", file=sys.stderr)
        return 2
    records = [json.loads(path.read_text(encoding="utf-8")) for path in args.result]
    if args.kind in MULTI_KINDS:
        table, images = MULTI_KINDS[args.kind](records, args.name, args.out)
    else:
        table, images = KINDS[args.kind](records[0], args.name, args.out)
    (args.out / f"{args.name}.md").write_text(table, encoding="utf-8")
    for path in images:
        print(f"wrote {path}")
    print(f"wrote {args.out / f'{args.name}.md'}\n\n{table}")
    if args.readme is not None:
        args.readme.write_text(replace_block(page, args.name, readme_block(args.name, table, images, args.readme)),
                               encoding="utf-8")
        print(f"updated the '{args.name}' block of {args.readme}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

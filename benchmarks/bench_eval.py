"""Thin wrapper around ``memgs eval`` for benchmark runs: the paper's table for one sequence.

Usage: ``python benchmarks/bench_eval.py SOURCE [memgs eval options]``; the results go to
``--json`` (default results/bench_eval.json) besides ``--out`` (default results/bench_eval/).
Every option of ``memgs eval`` is accepted (``--ablation``, ``--scale``, ``--set``, ...).
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from _common import uptime

from memgs_ros.cli import evaluate as eval_cli


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    eval_cli.add_arguments(p)
    p.add_argument("--json", type=Path, default=Path("results/bench_eval.json"), help="summary JSON path")
    p.set_defaults(out=Path("results/bench_eval"))
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        datefmt="%H:%M:%S")  # the pipeline's progress lines, as `memgs eval` shows them
    load = uptime()
    print(f"machine: {os.cpu_count()} cores, {load}")
    code = eval_cli.run(args)
    if code == 0:
        from memgs_ros.evaluation.runs import write_json

        name = "ablation.json" if args.ablation else "eval.json"
        record = json.loads((args.out / name).read_text())
        write_json(args.json, {"uptime_before": load, "argv": sys.argv[1:], "result": record})
        print(f"wrote {args.json}")
    return code


if __name__ == "__main__":
    sys.exit(main())

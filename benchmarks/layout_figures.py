"""The layout's size figures (issue 37): each node class's lines, the functions over 80 lines and
the largest classes in memgs_ros/. test/unit/test_sizes.py holds the bounds; this prints the figures.

    python benchmarks/layout_figures.py [--json OUT]
"""
from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ (not a package): _common
from _common import ROOT, write_results  # noqa: E402

PACKAGE = ROOT / "memgs_ros"


def figures(package: Path = PACKAGE, longest: int = 80, top: int = 5) -> dict[str, object]:
    """{"nodes": {class: lines}, "functions_over": [[lines, where]], "largest_classes": [[lines, where]]}."""
    nodes: dict[str, int] = {}
    classes: list[tuple[int, str]] = []
    long_functions: list[tuple[int, str]] = []
    for path in sorted(package.rglob("*.py")):
        rel = path.relative_to(package.parent)
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            lines = (node.end_lineno or node.lineno) - node.lineno + 1 if hasattr(node, "lineno") else 0
            if isinstance(node, ast.ClassDef):
                classes.append((lines, f"{rel}:{node.name}"))
                if rel.parts[1] == "nodes" and node in tree.body and any(
                        isinstance(b, ast.FunctionDef) and b.name == "__init__" for b in node.body):
                    nodes[node.name] = lines
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and lines > longest:
                long_functions.append((lines, f"{rel}:{node.name}"))
    return {"nodes": nodes, "functions_over": sorted(long_functions, reverse=True),
            "largest_classes": sorted(classes, reverse=True)[:top]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    f = figures()
    print("| node class | lines |\n|---|---|")
    for name, lines in sorted(f["nodes"].items(), key=lambda kv: -kv[1]):  # type: ignore[union-attr]
        print(f"| {name} | {lines} |")
    print(f"\nfunctions over 80 lines: {len(f['functions_over'])}")  # type: ignore[arg-type]
    for lines, where in f["functions_over"]:  # type: ignore[union-attr]
        print(f"  {lines} {where}")
    print("largest classes:")
    for lines, where in f["largest_classes"]:  # type: ignore[union-attr]
        print(f"  {lines} {where}")
    if args.json:
        write_results(args.json, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())

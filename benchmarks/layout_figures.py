"""The layout's figures. Issue 37: each node class's lines, the functions over 80 lines and the
largest classes in memgs_ros/ (test/unit/test_sizes.py holds the bounds). Issue 49: pairs of core/
subpackages importing each other (lazy imports too), each node package's lines, ros/ modules one
node alone imports, string-keyed stats writes, files naming "lockstep", the nodes that declare
depth_scale, the largest module.

    python benchmarks/layout_figures.py [--json OUT]
"""
from __future__ import annotations

import argparse
import ast
import re
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


def _imports(package: Path) -> dict[str, set[str]]:
    """{module: the package modules it imports, at module level or inside functions}."""
    mods = {".".join(p.relative_to(package.parent).with_suffix("").parts).removesuffix(".__init__"): p
            for p in package.rglob("*.py")}
    out: dict[str, set[str]] = {}
    for mod, path in mods.items():
        found: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names = [f"{node.module}.{a.name}" for a in node.names] + [node.module]
            found.update(n for n in names if n in mods)
        out[mod] = found - {mod}
    return out


def layering(package: Path = PACKAGE) -> dict[str, object]:
    """Issue 49's figures of the house: see the module docstring."""
    graph = _imports(package)
    sub = {m: m.split(".")[2] for m in graph if m.startswith("memgs_ros.core.") and len(m.split(".")) > 2}
    edges = {(sub[a], sub[b]) for a, deps in graph.items() for b in deps if a in sub and b in sub and sub[a] != sub[b]}
    pairs = sorted({tuple(sorted(e)) for e in edges if (e[1], e[0]) in edges})
    node_lines = {p.name: sum(len(f.read_text().splitlines()) for f in p.glob("*.py"))
                  for p in sorted((package / "nodes").iterdir()) if (p / "node.py").is_file()}
    owners: dict[str, set[str]] = {}
    for mod, deps in graph.items():
        parts = mod.split(".") + [""]
        for dep in deps:
            if dep.startswith("memgs_ros.ros."):
                owners.setdefault(dep, set()).add(parts[2] if parts[1] == "nodes" and len(parts) > 4 else parts[1])
    lone = sorted(m for m, o in owners.items() if len(o) == 1 and next(iter(o)) in node_lines)
    write = re.compile(r"""(?:counters|gauges)\[["']""")
    files = sorted(package.rglob("*.py"))
    stats_writes = sum(len(write.findall(f.read_text())) for f in files)
    lockstep = sum(1 for f in files if "lockstep" in f.read_text())
    sys.path.insert(0, str(package.parent))
    from memgs_ros.nodes.params import NODE_CONFIGS

    depth_scale = sorted(n for n, groups in NODE_CONFIGS.items()
                         if any(not prefix and "depth_scale" in getattr(cls, "__dataclass_fields__", {})
                                for prefix, cls in groups))
    largest = max((len(f.read_text().splitlines()), str(f.relative_to(package.parent))) for f in files)
    return {"core_pairs": [list(p) for p in pairs], "node_package_lines": node_lines,
            "ros_modules_of_one_node": lone, "string_keyed_stats_writes": stats_writes,
            "files_naming_lockstep": lockstep, "nodes_declaring_depth_scale": depth_scale,
            "largest_module": list(largest)}


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
    lay = layering()
    print(f"\ncore/ subpackage pairs importing each other: {len(lay['core_pairs'])} {lay['core_pairs']}")
    print("| node package | lines |\n|---|---|")
    for name, lines in sorted(lay["node_package_lines"].items(), key=lambda kv: -kv[1]):  # type: ignore[union-attr]
        print(f"| nodes/{name}/ | {lines} |")
    print(f"ros/ modules one node alone imports: {lay['ros_modules_of_one_node']}")
    print(f"string-keyed stats writes (counters[...] / gauges[...]): {lay['string_keyed_stats_writes']}")
    print(f"files of memgs_ros/ naming lockstep: {lay['files_naming_lockstep']}")
    print(f"nodes declaring depth_scale: {lay['nodes_declaring_depth_scale']}")
    print(f"largest module: {lay['largest_module'][0]} lines, {lay['largest_module'][1]}")
    if args.json:
        write_results(args.json, {**f, "layering": lay})
    return 0


if __name__ == "__main__":
    sys.exit(main())

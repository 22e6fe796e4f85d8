"""The package's tiers hold: no module imports from a tier above its own, and no modules import
each other in a circle (module-level imports, and imports inside functions too).

Tiers, bottom up: errors; core (no rclpy); io (datasets, bags); viz (Rerun logging, no rclpy);
ros (rclpy glue); nodes; orchestration (runs the graph); evaluation (scores runs: tables,
plots); cli. core/ must not import
rclpy at all."""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "memgs_ros"
TIERS = ("errors", "core", "io", "viz", "ros", "nodes", "orchestration", "evaluation", "cli", "testing")
# Tiers that may sit side by side (neither imports the other).
SAME: dict[str, str] = {}


def _tier(module: str) -> int | None:
    parts = module.split(".")
    if parts[0] != "memgs_ros" or len(parts) < 2:
        return None
    name = SAME.get(parts[1], parts[1])
    return TIERS.index(name) if name in TIERS else None


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(path: Path, module: str, known: set[str]) -> set[str]:
    """The package modules ``module`` imports (``from pkg import name`` counts as ``pkg.name``
    when that is a module, else ``pkg``)."""
    found: set[str] = set()
    is_pkg = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("memgs_ros"))
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = module.split(".") if is_pkg else module.split(".")[:-1]
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            if not base.startswith("memgs_ros"):
                continue
            for a in node.names:
                sub = f"{base}.{a.name}"
                found.add(sub if sub in known else base)
    found.discard(module)
    return {m for m in found if m in known}


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    return {m: _imports(p, m, set(mods)) for m, p in mods.items()}


def test_no_module_imports_from_a_higher_tier() -> None:
    upward = []
    for mod, deps in _graph().items():
        t = _tier(mod)
        for dep in deps:
            td = _tier(dep)
            if t is not None and td is not None and td > t:
                upward.append(f"{mod} -> {dep}")
    assert upward == [], "imports that run up the tiers " + str(TIERS) + ":\n" + "\n".join(sorted(upward))


# core/'s own floors, bottom up; subpackages on one floor sit side by side (neither imports the
# other). A module directly in core/ (kernels.py, sampling.py) is placed by its name.
CORE_FLOORS: tuple[tuple[str, ...], ...] = (
    ("runtime",), ("geometry",), ("gaussians",), ("raster",),
    ("metrics", "merge", "map_io", "sampling", "tracking"), ("mapping",), ("mapper_service",), ("kernels",),
)


def _core_part(module: str) -> str | None:
    parts = module.split(".")
    return parts[2] if len(parts) >= 3 and parts[:2] == ["memgs_ros", "core"] else None


def test_core_subpackages_keep_their_floors() -> None:
    """Inside core/, every import (lazy ones too) runs down a floor: no two subpackages import each
    other, and e.g. the rasterizer never reaches into the mapper that trains with it."""
    floor = {name: i for i, names in enumerate(CORE_FLOORS) for name in names}
    wrong = []
    for mod, deps in _graph().items():
        a = _core_part(mod)
        if a is None:
            continue
        assert a in floor, f"core/{a} has no floor in CORE_FLOORS"
        for dep in deps:
            b = _core_part(dep)
            if b is not None and b != a and floor[b] >= floor[a]:
                wrong.append(f"{mod} -> {dep}")
    assert wrong == [], "imports across core/'s floors " + str(CORE_FLOORS) + ":\n" + "\n".join(sorted(wrong))


def test_ros_holds_only_what_several_nodes_share() -> None:
    """A module of ros/ that one node alone imports belongs in that node's package (nodes/<name>/)."""
    owners: dict[str, set[str]] = {}
    for mod, deps in _graph().items():
        parts = mod.split(".") + [""]
        owner = parts[2] if parts[1] == "nodes" and len(parts) > 4 else parts[1]
        for dep in deps:
            if dep.startswith("memgs_ros.ros."):
                owners.setdefault(dep, set()).add(owner)
    nodes = {p.name for p in (PACKAGE / "nodes").iterdir() if (p / "node.py").is_file()}
    lone = sorted(f"{m} (only {next(iter(o))})" for m, o in owners.items() if len(o) == 1 and o <= nodes)
    assert lone == [], "ros/ modules that belong to one node's package: " + ", ".join(lone)


def test_every_node_is_a_package() -> None:
    """nodes/ holds one folder per node (its node.py beside what only it uses), and the shared
    files: params, registry, composed."""
    from memgs_ros.nodes.registry import NODES

    for name, (module, _) in NODES.items():
        assert module == f"memgs_ros.nodes.{name}.node", module
        assert (PACKAGE / "nodes" / name / "node.py").is_file(), name
    loose = sorted(p.name for p in (PACKAGE / "nodes").glob("*.py"))
    assert loose == ["__init__.py", "composed.py", "params.py", "registry.py"], loose


def test_core_does_not_import_rclpy() -> None:
    offenders = []
    for path in (PACKAGE / "core").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(n.split(".")[0] in ("rclpy", "rosidl_runtime_py") for n in names):
                offenders.append(str(path.relative_to(PACKAGE)))
    assert offenders == []


def test_no_import_circles() -> None:
    graph = _graph()
    # Packages import their own submodules in __init__; a submodule importing a sibling through
    # the package is not a circle of files, so edges to a package's __init__ from inside it are dropped.
    def inside(mod: str, pkg: str) -> bool:
        return mod.startswith(pkg + ".")
    edges = {m: {d for d in deps if not inside(m, d)} for m, deps in graph.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                circles.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    assert circles == [], f"modules importing each other in a circle: {circles}"


def test_only_the_mapper_node_loads_torch() -> None:
    """torch costs a node ~2.5 s of start-up and ~190 MB of memory: the nodes that do not train
    (tracker, sampler, merger, player, recorder) must not import it, however indirectly."""
    import subprocess
    import sys

    nodes = ("tracker", "keyframe_sampler", "merger", "bag_player", "recorder")
    code = ("import sys\n"
            + "".join(f"import memgs_ros.nodes.{n}.node\n" for n in nodes)
            + "print(sorted(m for m in sys.modules if m == 'torch' or m.startswith('torch.')))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    if "No module named 'rclpy'" in done.stderr:
        import pytest

        pytest.skip("the ROS extra is not installed")
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "[]", done.stdout[:500]

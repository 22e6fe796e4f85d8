"""The parameter reference (``docs/parameters.md``), made from the nodes' own parameter tables.

Each node module lists its parameters in ``CONFIGS`` ((prefix, frozen config dataclass) pairs;
the node's own parameters under the empty prefix). The rows are what the nodes declare: the
specs :func:`~memgs_ros.ros.config_params.config_specs` gives go through ``declare_all``, as
``declare_config`` sends them, on a stand-in node that records each ``declare_parameter`` call,
so names, defaults, descriptions and ranges are those ``ros2 param describe`` shows. No rclpy
node is created.

    python -m memgs_ros.orchestration.param_reference --write docs/parameters.md
    python -m memgs_ros.orchestration.param_reference --check docs/parameters.md   # exit 1 when stale
"""
from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, cast

from memgs_ros.nodes.registry import NODES, node_name
from memgs_ros.orchestration.run_files import NODE_NAMES
from memgs_ros.ros.config_params import module_specs
from memgs_ros.ros.params import declare_all

if TYPE_CHECKING:
    from rclpy.node import Node

__all__ = ["DEFAULT_PATH", "ParamRow", "node_modules", "parameter_rows", "render_markdown", "rows_from_declarations"]

DEFAULT_PATH = "docs/parameters.md"
REGENERATE = f"python -m memgs_ros.orchestration.param_reference --write {DEFAULT_PATH}"

@dataclass(frozen=True)
class ParamRow:
    """One declared parameter, as text for the reference table."""

    node: str  # the node's name (= its module's name)
    name: str  # full parameter name, prefix included (``tracker.n_features``)
    type: str  # bool, int, float, string or string array
    default: str
    range: str  # inclusive numeric range, the allowed values, or "" (any)
    description: str


@dataclass(frozen=True)
class _Declared:
    value: Any
    descriptor: Any  # rcl_interfaces.msg.ParameterDescriptor


class _RecordingNode:
    """Stands in for an rclpy ``Node`` in the declaring helpers: keeps every declaration in order
    and returns the default, as a node without overrides would."""

    def __init__(self) -> None:
        self.declared: dict[str, _Declared] = {}

    def declare_parameter(self, name: str, value: Any, descriptor: Any = None) -> _Declared:
        self.declared[name] = _Declared(value, descriptor)
        return self.declared[name]


def node_modules() -> list[ModuleType]:
    """The node modules, in the order of ``run_files.NODE_NAMES``."""
    return [importlib.import_module(NODES[name][0]) for name in NODE_NAMES]


def _type_name(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return "string array"
    return {bool: "bool", int: "int", float: "float", str: "string"}[type(value)]


def _number(x: float) -> str:
    return str(x) if isinstance(x, int) else f"{x:.12g}".replace("e+", "e")


def _default_text(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return ", ".join(f"`{v}`" for v in value)
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, float):
        return f"`{value!r}`"  # with its decimal point: rclpy refuses 2 for a float parameter
    return f"`{value}`" if value != "" else '`""`'


def _range_text(descriptor: Any, choices: tuple[str, ...]) -> str:
    if choices:
        return "one of " + ", ".join(f"`{c}`" for c in choices)
    for rng in (*descriptor.integer_range, *descriptor.floating_point_range):
        return f"[{_number(rng.from_value)}, {_number(rng.to_value)}]"
    return ""


def parameter_rows(node_module: ModuleType) -> list[ParamRow]:
    """Every parameter ``node_module`` declares (its ``CONFIGS``), in declaration order (rclpy's
    own ``use_sim_time`` and the like are not listed)."""
    recorder = _RecordingNode()
    declare_all(cast("Node", recorder), module_specs(node_module))  # the helpers only call declare_parameter
    return rows_from_declarations(node_module, {name: (d.value, d.descriptor) for name, d in recorder.declared.items()})


def rows_from_declarations(node_module: ModuleType, declared: Mapping[str, tuple[Any, Any]]) -> list[ParamRow]:
    """Rows of ``declared`` ({name: (value, ParameterDescriptor)}, from a stand-in or a real node)."""
    choices = {spec.name: spec.choices for spec in module_specs(node_module)}
    node = node_name(node_module.__name__)
    rows = []
    for name, (value, descriptor) in declared.items():
        allowed = choices.get(name, ())
        description = descriptor.description
        if allowed:  # params.declare appends the choices to the description; they have their own column
            description = description.removesuffix(f" (one of: {', '.join(allowed)})")
        if not descriptor.read_only:
            description += " (can be set at run time)"
        rows.append(ParamRow(node, name, _type_name(value), _default_text(value),
                             _range_text(descriptor, allowed), description))
    return rows


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _node_section(module: ModuleType) -> list[str]:
    name = node_name(module.__name__)
    lines = [f"## {name}", "", f"`{module.__name__}`."]
    groups = [f"`{prefix}.*` from `{cls.__module__}.{cls.__name__}`" if prefix
              else f"its own parameters from `{cls.__module__}.{cls.__name__}`" for prefix, cls in module.CONFIGS]
    if groups:
        lines[-1] += " Config groups: " + "; ".join(groups) + "."
    lines += ["", "| parameter | type | default | range | description |", "| --- | --- | --- | --- | --- |"]
    lines += [f"| `{r.name}` | {r.type} | {_cell(r.default)} | {r.range} | {_cell(r.description)} |"
              for r in parameter_rows(module)]
    return [*lines, ""]


def render_markdown() -> str:
    """The whole reference: one table per node."""
    lines = [
        "# Node parameters",
        "",
        f"Generated from the nodes' parameter tables by `{REGENERATE}`;",
        "a test fails when this file is stale. Do not edit it by hand.",
        "",
        "Set them in a params file (the launch file's `params_file:=`, `ros2 run ... --params-file`) or, for",
        "`memgs run` / `demo` / `eval`, with `--set NODE.PARAM=VALUE` (`--set mapper.mapping.max_gaussians=60000`).",
        "",
        "Each parameter is read once at start-up and is read-only afterwards unless its row says otherwise.",
        "A value outside its range, not one of its allowed values or of the wrong type stops the node with",
        "one line naming the parameter; so does a parameter the node does not declare. Ranges are inclusive.",
        "Write floats with a decimal point (`2.0`, not `2`). A config group (`tracker.*`, `mapping.*`, ...)",
        "is also checked as a whole by its dataclass: for example `tracker.mode` must be `rgbd` or `mono` and",
        "the `mapping.lr_*` rates must be positive. `ros2 param describe <node> <parameter>` shows the same",
        "description and range. rclpy's own parameters (`use_sim_time`, ...) are not listed.",
        "",
    ]
    for module in node_modules():
        lines += _node_section(module)
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Write or check the node parameter reference (Markdown).")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--write", metavar="PATH", type=Path, help="write the reference to PATH")
    group.add_argument("--check", metavar="PATH", type=Path, help="exit 1 when PATH differs from the reference")
    args = p.parse_args(argv)
    text = render_markdown()
    if args.write is not None:
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text(text, encoding="utf-8")
        print(f"wrote {args.write}")
    elif args.check is not None:
        current = args.check.read_text(encoding="utf-8") if args.check.is_file() else None
        if current != text:
            print(f"{args.check} is stale: run python -m memgs_ros.orchestration.param_reference --write {args.check}",
                  file=sys.stderr)
            return 1
        print(f"{args.check} is up to date")
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

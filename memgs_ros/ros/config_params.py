"""Expose every field of a core config dataclass as a described, ranged ROS parameter.

The core configs (TrackerConfig, MappingConfig, MergeConfig, PatchGridConfig) are the
single source of truth: their fields give names, types and defaults, their source
comments give the descriptions, and their ``__post_init__`` validation refuses bad
values. A node declares them under a prefix (``tracker.n_features``) and gets the
typed, validated config back. Numbers get a range: the node's table where it gives
one, else non-negative when the default is, so ``ros2 param describe`` documents all.
"""
from __future__ import annotations

import difflib
import inspect
import re
from collections.abc import Collection, Iterable, Mapping
from dataclasses import MISSING, Field, fields, is_dataclass
from functools import cache
from typing import TypeVar

from rclpy.node import Node

from memgs_ros.errors import ConfigError, MemgsError
from memgs_ros.ros.params import ParamSpec, declare

C = TypeVar("C")
_BIG = 1e12
# Parameters rclpy declares on every node itself.
ROS_PARAMETERS = frozenset({"use_sim_time", "start_type_description_service"})
_FIELD = re.compile(r"^\s+(\w+)\s*:[^=]*=.*?(?:#\s*(.*))?$")
_COMMENT = re.compile(r"^\s+#\s*(.*)$")


_DOC_ITEM = re.compile(r"^(\w+(?:\s*,\s*\w+)*)\s*:\s*(.*)$")


def _docstring_items(config_cls: type) -> dict[str, str]:
    """``name: text`` items of the class docstring (continuation lines indented)."""
    out: dict[str, str] = {}
    current: list[str] = []
    for line in (inspect.getdoc(config_cls) or "").splitlines():
        m = _DOC_ITEM.match(line)
        if m:
            current = [n.strip() for n in m.group(1).split(",")]
            for n in current:
                out[n] = m.group(2).strip()
        elif line.startswith((" ", "\t")) and current:
            for n in current:
                out[n] = f"{out[n]} {line.strip()}"
        else:
            current = []
    return out


@cache
def field_descriptions(config_cls: type) -> dict[str, str]:
    """Field name -> the comment on its line (or the comment block just above it), else its
    ``name: text`` item in the class docstring."""
    out: dict[str, str] = dict(_docstring_items(config_cls))
    try:
        lines = inspect.getsource(config_cls).splitlines()
    except (OSError, TypeError):
        return out
    above: list[str] = []  # comment lines right above the current field
    group = ""  # the last comment block: it heads every field below it until a blank line
    for line in lines:
        m = _FIELD.match(line)
        if m:
            if above:
                group = " ".join(above).rstrip(".")
            own = (m.group(2) or "").strip()
            words = m.group(1).replace("_", " ")
            out[m.group(1)] = own or out.get(m.group(1)) or (f"{group}: {words}" if group else words)
            above = []
            continue
        c = _COMMENT.match(line)
        if c:
            above.append(c.group(1).strip())
        elif not line.strip():
            above, group = [], ""
    return out


def _plain_fields(config_cls: type, defaults: Mapping[str, object]) -> list[tuple[Field, object]]:
    """The fields a config exposes as parameters (plain bool/int/float/str defaults) with their
    defaults; tuples and nested configs stay at their defaults."""
    if not is_dataclass(config_cls):
        raise TypeError(f"{config_cls!r} is not a dataclass")
    out = []
    for f in fields(config_cls):
        default = defaults.get(f.name, f.default)
        if default is not MISSING and isinstance(default, (bool, int, float, str)):
            out.append((f, default))
    return out


def _param_name(prefix: str, field_name: str) -> str:
    return f"{prefix}.{field_name}" if prefix else field_name  # no prefix: a node's own parameters


def parameter_names(specs: Iterable[ParamSpec], configs: Iterable[tuple[str, type]]) -> frozenset[str]:
    """Every parameter a node declares from its ``PARAMS`` specs and ``CONFIGS`` ((prefix, config
    class) pairs, as :func:`declare_config` declares them), without creating the node."""
    names = {spec.name for spec in specs}
    names.update(_param_name(prefix, f.name) for prefix, cls in configs for f, _ in _plain_fields(cls, {}))
    return frozenset(names | ROS_PARAMETERS)


def unknown_parameters(node_name: str, given: Iterable[str], declared: Collection[str]) -> list[str]:
    """One line for each name in ``given`` that ``declared`` lacks, with the closest declared names.

    rclpy ignores a parameter-file entry that no node declares, so a typo (``keyframe_max_frames``
    for ``tracker.keyframe_max_frames``) would silently run with the default."""
    lines = []
    for name in sorted(set(given) - set(declared)):
        if name.startswith("qos_overrides."):
            continue  # declared by rclpy with a publisher or subscription that allows QoS overrides
        leaf = name.rsplit(".", 1)[-1]
        close = [d for d in declared if d.rsplit(".", 1)[-1] == leaf] or difflib.get_close_matches(name, declared, 3)
        hint = f" (did you mean {' or '.join(sorted(close)[:3])}?)" if close else ""
        lines.append(f"{node_name} has no parameter '{name}'{hint}")
    return lines


def check_declared(node: Node) -> None:
    """ConfigError when the parameter file or overrides gave ``node`` a parameter it did not
    declare (call once the node has declared everything)."""
    given = getattr(node, "_parameter_overrides", {})  # rclpy: the overrides that matched this node
    lines = unknown_parameters(node.get_name(), given.keys(), set(node._parameters))
    if lines:
        raise ConfigError("; ".join(lines))


def declare_config(node: Node, config_cls: type[C], prefix: str,
                   ranges: Mapping[str, tuple[float, float]] | None = None,
                   defaults: Mapping[str, object] | None = None) -> C:
    """Declare ``<prefix>.<field>`` (``<field>`` when prefix is empty) for every plain
    (bool/int/float/str) field; build the config.

    defaults: per-node default overrides (e.g. mode="mono"); parameter files still win.
    Raises ConfigError naming the parameter when a value is refused.
    """
    ranges = ranges or {}
    docs = field_descriptions(config_cls)
    values: dict[str, object] = {}
    for f, default in _plain_fields(config_cls, defaults or {}):
        name = _param_name(prefix, f.name)
        desc = docs.get(f.name) or f"{config_cls.__name__}.{f.name}"
        rng = ranges.get(f.name)
        if rng is None and isinstance(default, (int, float)) and not isinstance(default, bool):
            rng = (0, _BIG) if default >= 0 else (-_BIG, _BIG)
            if isinstance(default, int):
                rng = (int(rng[0]), 2**31 - 1)
        values[f.name] = declare(node, name, default, desc, range=rng)
    try:
        return config_cls(**values)
    except MemgsError as err:
        raise ConfigError(f"parameters '{prefix}.*': {err}") from err
    except (TypeError, ValueError) as err:
        raise ConfigError(f"parameters '{prefix}.*' are inconsistent: {err}") from err

"""Node parameters from frozen config dataclasses: one declaration path for every node.

A config's fields give names, types and defaults, their source comments (or ``name: text``
items in the class docstring) the descriptions, its ``RANGES`` / ``CHOICES`` class variables
the numeric ranges and allowed strings, and its ``__post_init__`` refuses inconsistent values.
A node declares each config under a prefix (``tracker.n_features``; no prefix for the node's
own parameters) and gets the typed, validated config back. Numbers without a range get a
non-negative one when the default is, so ``ros2 param describe`` documents all.

:func:`config_specs` gives the declarations as data (for the CLI and the parameter reference);
:func:`check_values` judges given values as the node will, without starting it.
"""
from __future__ import annotations

import difflib
import inspect
import re
from collections.abc import Collection, Iterable, Mapping
from dataclasses import MISSING, Field, fields, is_dataclass
from functools import cache
from types import ModuleType
from typing import TYPE_CHECKING, Any, TypeVar, cast

from memgs_ros.errors import ConfigError, MemgsError
from memgs_ros.ros.params import ParamSpec, ParamValue, check_value, declare_all

if TYPE_CHECKING:
    from rclpy.node import Node

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


def _is_string_array(value: object) -> bool:
    return isinstance(value, (tuple, list)) and bool(value) and all(isinstance(v, str) for v in value)


def _plain_fields(config_cls: type, defaults: Mapping[str, object]) -> list[tuple[Field, object]]:
    """The fields a config exposes as parameters (plain bool/int/float/str defaults, or a
    non-empty tuple of str: a string array) with their defaults; other tuples and nested configs
    stay at their defaults."""
    if not is_dataclass(config_cls):
        raise TypeError(f"{config_cls!r} is not a dataclass")
    out = []
    for f in fields(config_cls):
        default = defaults.get(f.name, f.default)
        if default is not MISSING and (isinstance(default, (bool, int, float, str)) or _is_string_array(default)):
            out.append((f, default))
    return out


def _param_name(prefix: str, field_name: str) -> str:
    return f"{prefix}.{field_name}" if prefix else field_name  # no prefix: a node's own parameters


def _field_specs(config_cls: type, prefix: str, defaults: Mapping[str, object] | None,
                 ranges: Mapping[str, tuple[float, float]] | None) -> list[tuple[str, ParamSpec]]:
    """(field name, spec) for every parameter of ``config_cls`` under ``prefix``."""
    all_ranges = {**getattr(config_cls, "RANGES", {}), **(ranges or {})}
    choices: Mapping[str, tuple[str, ...]] = getattr(config_cls, "CHOICES", {})
    docs = field_descriptions(config_cls)
    out = []
    for f, default in _plain_fields(config_cls, defaults or {}):
        rng = all_ranges.get(f.name)
        if rng is None and isinstance(default, (int, float)) and not isinstance(default, bool):
            rng = (0, _BIG) if default >= 0 else (-_BIG, _BIG)
            if isinstance(default, int):
                rng = (int(rng[0]), 2**31 - 1)
        value = cast("ParamValue", default)
        desc = docs.get(f.name) or f"{config_cls.__name__}.{f.name}"
        out.append((f.name, ParamSpec(_param_name(prefix, f.name), value, desc, rng, tuple(choices.get(f.name, ())))))
    return out


def config_specs(config_cls: type, prefix: str = "", defaults: Mapping[str, object] | None = None,
                 ranges: Mapping[str, tuple[float, float]] | None = None) -> list[ParamSpec]:
    """The parameters :func:`declare_config` declares for ``config_cls`` under ``prefix``, in field order.

    Each plain field gives one: its default fixes the type, its source comment (or docstring item)
    the description, ``RANGES`` / ``CHOICES`` (class variables) the range and allowed values; a
    number without a range gets a non-negative one when its default is, else any sign.
    defaults: per-node default overrides; ranges: override ``RANGES``.
    """
    return [spec for _, spec in _field_specs(config_cls, prefix, defaults, ranges)]


def parameter_names(configs: Iterable[tuple[str, type]]) -> frozenset[str]:
    """Every parameter a node declares from its ``CONFIGS`` ((prefix, config class) pairs, as
    :func:`declare_config` declares them), rclpy's own included, without creating the node."""
    names = {spec.name for prefix, cls in configs for spec in config_specs(cls, prefix)}
    return frozenset(names | ROS_PARAMETERS)


def module_specs(node_module: ModuleType) -> list[ParamSpec]:
    """Every parameter a node module declares from its ``CONFIGS``, in declaration order."""
    return [spec for prefix, cls in node_module.CONFIGS for spec in config_specs(cls, prefix)]


def module_parameter_names(node_module: ModuleType) -> frozenset[str]:
    """Every parameter a node module declares (:func:`module_specs`), rclpy's own included: what
    the CLI checks parameter-file names against."""
    return parameter_names(node_module.CONFIGS)


def _group(prefix: str) -> str:
    return f"parameters '{prefix}.*'" if prefix else "parameters"


def _refusal(prefix: str, err: Exception) -> str:
    """A config's own validation refusing the values, in the words :func:`declare_config` uses."""
    if isinstance(err, MemgsError):
        return f"{_group(prefix)}: {err}"
    return f"{_group(prefix)} are inconsistent: {err}"


def check_values(config_cls: type, prefix: str, given: Mapping[str, object], *, node: str = "",
                 defaults: Mapping[str, object] | None = None,
                 ranges: Mapping[str, tuple[float, float]] | None = None,
                 int_as_float: bool = False) -> list[str]:
    """One line for each value in ``given`` ({parameter name: value}, as in a parameter file) that
    ``config_cls`` under ``prefix`` would refuse at start, in the words the node uses; [] when none.

    Checks type, range and allowed values of the names this config declares (others are left to
    :func:`unknown_parameters`), then, when those pass, builds the config with them so its
    ``__post_init__`` judges the whole group. No rclpy node is needed. node: prefixes each line
    (``mapper: ...``), as the node's fatal log line is. rclpy refuses an int for a float parameter
    (``2`` for ``2.0``), and so does this unless ``int_as_float`` (for a caller that converts).
    """
    lines: list[str] = []
    values: dict[str, object] = {}
    for field_name, spec in _field_specs(config_cls, prefix, defaults, ranges):
        if spec.name not in given:
            continue
        value = given[spec.name]
        problem = check_value(spec, value, int_as_float)
        if problem is not None:
            lines.append(problem)
        elif isinstance(value, list):
            values[field_name] = tuple(value)  # as declare_config passes a string array
        else:
            values[field_name] = float(cast("float", value)) if isinstance(spec.default, float) else value
    if not lines:
        try:
            config_cls(**{**(defaults or {}), **values})
        except (MemgsError, TypeError, ValueError) as err:
            lines.append(_refusal(prefix, err))
    return [f"{node}: {line}" for line in lines] if node else lines


def config_from_values(config_cls: type[C], prefix: str, given: Mapping[str, object]) -> C:
    """The config a node would build from ``given`` ({parameter name: value}, as in a parameter
    file; names of other groups ignored), without rclpy; ConfigError as the node would refuse it."""
    if lines := check_values(config_cls, prefix, given, int_as_float=True):
        raise ConfigError("; ".join(lines))
    values: dict[str, object] = {}
    for field_name, spec in _field_specs(config_cls, prefix, None, None):
        if spec.name in given:
            value = given[spec.name]
            values[field_name] = tuple(value) if isinstance(value, list) else (
                float(cast("float", value)) if isinstance(spec.default, float) else value)
    return config_cls(**values)


def changed_parameters(prefix: str, before: object, after: object) -> dict[str, object]:
    """{parameter name: value} of the fields in which config ``after`` differs from ``before``
    (one config class): what a parameter file must add to turn the one into the other."""
    return {_param_name(prefix, f.name): getattr(after, f.name) for f in fields(cast("Any", after))
            if getattr(after, f.name) != getattr(before, f.name)}


# Parameters that were renamed (old leaf name -> new): a saved config or command line still using
# the old name is told the new one. (The replay's pacing became one value, 2026-12.)
RENAMED = {"lockstep": "pacing", "lockstep_iterations": "iterations_per_frame", "lockstep_window": "ack_window"}


def unknown_parameters(node_name: str, given: Iterable[str], declared: Collection[str],
                       set_form: bool = False) -> list[str]:
    """One line for each name in ``given`` that ``declared`` lacks, with the closest declared names
    (``set_form``: also as ``memgs run --set`` takes them, the node's name first: a parameter named
    like its node, ``tracker.keyframe_max_frames``, is ``--set tracker.tracker.keyframe_max_frames``).

    rclpy ignores a parameter-file entry that no node declares, so a typo (``keyframe_max_frames``
    for ``tracker.keyframe_max_frames``) would silently run with the default."""
    lines = []
    for name in sorted(set(given) - set(declared)):
        if name.startswith("qos_overrides."):
            continue  # declared by rclpy with a publisher or subscription that allows QoS overrides
        leaf = name.rsplit(".", 1)[-1]
        if leaf in RENAMED and RENAMED[leaf] in declared:
            lines.append(f"{node_name} has no parameter '{name}': it is called '{RENAMED[leaf]}' now")
            continue
        close = [d for d in declared if d.rsplit(".", 1)[-1] == leaf] or difflib.get_close_matches(name, declared, 3)
        names = sorted(close)[:3]
        hint = f" (did you mean {' or '.join(names)}?" if close else ""
        if close and set_form:
            hint += f" with --set: {' or '.join(f'{node_name}.{n}=...' for n in names)}"
        hint += ")" if close else ""
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
    """Declare :func:`config_specs` (``<prefix>.<field>``, ``<field>`` when prefix is empty) on
    ``node`` and build the config from the values.

    defaults: per-node default overrides (e.g. mode="mono"); parameter files still win.
    ranges: override the class's ``RANGES``. Raises ConfigError naming the parameter when a
    value is refused.
    """
    specs = _field_specs(config_cls, prefix, defaults, ranges)
    declared = declare_all(node, [spec for _, spec in specs])
    values = {}
    for field_name, spec in specs:
        value = declared[spec.name]
        values[field_name] = tuple(value) if isinstance(value, list) else value  # frozen configs hold tuples
    try:
        return config_cls(**values)
    except (MemgsError, TypeError, ValueError) as err:
        raise ConfigError(_refusal(prefix, err)) from err

"""Declare node parameters with a description and range, and refuse bad values at start.

Every parameter gets a ``ParameterDescriptor`` (description, and a FloatingPointRange /
IntegerRange for numbers) so ``ros2 param describe`` documents the node, and rclpy itself
refuses out-of-range runtime updates. Parameters are read-only by default: the nodes read
them once into a typed config, so a later ``ros2 param set`` could not take effect.

    rate = declare(node, "rate", 1.0, "replay speed (real-time factor)", range=(0.01, 100.0))

A bad override (wrong type, out of range, not one of ``choices``) raises
:class:`ConfigError` naming the parameter, which ``main()`` turns into one log line.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

from memgs_ros.errors import ConfigError

if TYPE_CHECKING:  # rclpy only where a node declares: config_params.check_values needs none
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.node import Node

__all__ = ["ParamSpec", "ParamValue", "check_value", "declare", "declare_all", "type_name"]

ParamValue = bool | int | float | str | tuple[str, ...] | list[str]  # a string array: the recorder's topics


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: its default fixes the type; ``range`` is inclusive (numbers only)."""

    name: str
    default: ParamValue
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = True


def type_name(default: ParamValue) -> str:
    """The parameter type a default fixes, in the words of the refusals and docs/parameters.md."""
    return "string array" if isinstance(default, (tuple, list)) else type(default).__name__


def _descriptor(spec: ParamSpec) -> ParameterDescriptor:
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

    desc = spec.description
    if spec.choices:
        desc = f"{desc} (one of: {', '.join(spec.choices)})"
    d = ParameterDescriptor(description=desc, read_only=spec.read_only)
    if spec.range is not None:
        lo, hi = spec.range
        if isinstance(spec.default, bool) or not isinstance(spec.default, (int, float)):
            raise ConfigError(f"parameter '{spec.name}': a range needs a numeric default, got {spec.default!r}")
        if isinstance(spec.default, int):
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    return d


def _type_ok(default: ParamValue, value: object, int_as_float: bool) -> bool:
    if isinstance(default, bool):
        return isinstance(value, bool)
    if isinstance(value, bool):
        return False  # bool is an int to Python, not to rclpy
    if isinstance(default, int):
        return isinstance(value, int)
    if isinstance(default, float):
        return isinstance(value, float) or (int_as_float and isinstance(value, int))
    if isinstance(default, str):
        return isinstance(value, str)
    return isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value)  # a string array


def _wrong_type(spec: ParamSpec) -> str:
    hint = " (write floats with a decimal point, e.g. 2.0)" if isinstance(spec.default, float) else ""
    return f"parameter '{spec.name}' must be of type {type_name(spec.default)}{hint}"


def _value_problem(spec: ParamSpec, value: object) -> str | None:
    """Range and choices of a value of the right type (what rclpy does not check, or checks less)."""
    if spec.range is not None and not spec.range[0] <= cast("float", value) <= spec.range[1]:
        return f"parameter '{spec.name}' = {value!r} is outside [{spec.range[0]}, {spec.range[1]}]"
    if spec.choices and value not in spec.choices:
        return f"parameter '{spec.name}' = {value!r} is not one of {list(spec.choices)}"
    return None


def check_value(spec: ParamSpec, value: object, int_as_float: bool = False) -> str | None:
    """The line :func:`declare` would raise for ``value`` given to ``spec`` (type, range, choices),
    or None when it is accepted; needs no node. rclpy refuses an int for a float parameter
    (``2`` for ``2.0``), and so does this unless ``int_as_float`` (for a caller that converts)."""
    if not _type_ok(spec.default, value, int_as_float):
        return f"{_wrong_type(spec)}, got {value!r}"
    return _value_problem(spec, value)


def _declare_spec(node: Node, spec: ParamSpec) -> ParamValue:
    from rclpy.exceptions import InvalidParameterTypeException, ParameterException

    try:
        value = node.declare_parameter(spec.name, spec.default, _descriptor(spec)).value
    except InvalidParameterTypeException as err:
        raise ConfigError(f"{_wrong_type(spec)}: {err}") from err
    except ParameterException as err:
        # rclpy refused the override against the descriptor's range: name it as check_value does.
        given = getattr(node, "_parameter_overrides", {}).get(spec.name)  # rclpy: this node's overrides
        problem = None if given is None else _value_problem(spec, given.value)
        raise ConfigError(problem or f"parameter '{spec.name}' has a bad value (allowed {spec.range}): {err}") from err
    # rclpy checks ranges too; this also catches NaN, which compares false everywhere, and choices.
    problem = _value_problem(spec, value)
    if problem:
        raise ConfigError(problem)
    return value


def declare(
    node: Node,
    name: str,
    default: ParamValue,
    description: str,
    range: tuple[float, float] | None = None,  # noqa: A002 - reads best at call sites
    choices: tuple[str, ...] = (),
    read_only: bool = True,
) -> ParamValue:
    """Declare one parameter on ``node`` and return its (validated) value."""
    return _declare_spec(node, ParamSpec(name, default, description, range, tuple(choices), read_only))


def declare_all(node: Node, specs: Iterable[ParamSpec]) -> dict[str, ParamValue]:
    """Declare every spec; returns {name: value}. The first bad value raises ConfigError."""
    return {spec.name: _declare_spec(node, spec) for spec in specs}

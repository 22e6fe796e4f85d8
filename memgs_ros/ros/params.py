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

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, ParameterException
from rclpy.node import Node

from memgs_ros.errors import ConfigError

__all__ = ["ParamSpec", "ParamValue", "declare", "declare_all"]

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


def _descriptor(spec: ParamSpec) -> ParameterDescriptor:
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


def _declare_spec(node: Node, spec: ParamSpec) -> ParamValue:
    try:
        value = node.declare_parameter(spec.name, spec.default, _descriptor(spec)).value
    except InvalidParameterTypeException as err:
        hint = " (write floats with a decimal point, e.g. 2.0)" if isinstance(spec.default, float) else ""
        raise ConfigError(
            f"parameter '{spec.name}' must be of type {type(spec.default).__name__}{hint}: {err}"
        ) from err
    except ParameterException as err:
        raise ConfigError(f"parameter '{spec.name}' has a bad value (allowed {spec.range}): {err}") from err
    if spec.range is not None and not (spec.range[0] <= value <= spec.range[1]):
        # rclpy checks ranges too; this also catches NaN, which compares false everywhere.
        raise ConfigError(f"parameter '{spec.name}' = {value!r} is outside [{spec.range[0]}, {spec.range[1]}]")
    if spec.choices and value not in spec.choices:
        raise ConfigError(f"parameter '{spec.name}' = {value!r} is not one of {list(spec.choices)}")
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

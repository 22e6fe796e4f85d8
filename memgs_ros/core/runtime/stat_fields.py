"""Typed stats writes: each telemetry record (``telemetry.py``) has a generated twin of attributes
(``telemetry_fields.py``), so a node writes ``stats.frames_in += 1`` and ``stats.skipped["busy"]
+= 1`` and mypy (``test_lint``) catches a field renamed in the record, where a string key would
only fail when the line runs. The twin's fields read the value written so far (the record's
default before) and write through the store underneath: ``ros/diagnostics.NodeStats`` for a node,
:class:`StatValues` (a plain dict) for core code that reports through its owner.

    python -m memgs_ros.core.runtime.stat_fields --write   # after changing a record

``test_telemetry`` fails while ``telemetry_fields.py`` differs from what this writes. The base
record's ``problem`` family is the twin's ``problem_counts`` (``NodeStats.problem`` logs as it counts).
No rclpy here.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Generic, Self, TypeVar, overload

V = TypeVar("V")
FIELDS_PATH = Path(__file__).with_name("telemetry_fields.py")
RENAMED = {"problem": "problem_counts"}  # record field -> twin attribute, where a method has the name


class StatsWriter:
    """The store a generated twin writes through: one value per stats key."""

    def _stat(self, key: str, default: Any) -> Any:  # noqa: ANN401 - the field's type, checked at the twin
        raise NotImplementedError

    def _set_stat(self, key: str, value: Any) -> None:  # noqa: ANN401
        raise NotImplementedError


class Stat(Generic[V]):
    """One stats key as a typed attribute (a descriptor); on the class it is the key itself, which
    ``NodeStats.post_add``/``post_set``/``compute`` take."""

    def __init__(self, default: V) -> None:
        self.default = default
        self.key = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.key = name

    @overload
    def __get__(self, obj: None, owner: type) -> Stat[V]: ...

    @overload
    def __get__(self, obj: StatsWriter, owner: type) -> V: ...

    def __get__(self, obj: StatsWriter | None, owner: type) -> V | Stat[V]:
        if obj is None:
            return self
        return typing.cast(V, obj._stat(self.key, self.default))

    def __set__(self, obj: StatsWriter, value: V) -> None:
        obj._set_stat(self.key, value)


class FamilyValues(Generic[V]):
    """The members of a key family (``skipped.busy``, ``state.OK``): ``family[member] += 1``."""

    def __init__(self, writer: StatsWriter, prefix: str, zero: V) -> None:
        self._writer, self._prefix, self._zero = writer, prefix, zero

    def __getitem__(self, member: str) -> V:
        return typing.cast(V, self._writer._stat(f"{self._prefix}.{member}", self._zero))

    def __setitem__(self, member: str, value: V) -> None:
        if not member:
            raise ValueError(f"a member of {self._prefix}.* needs a name")
        self._writer._set_stat(f"{self._prefix}.{member}", value)


class Family(Generic[V]):
    """A key family as a typed attribute: its members by name."""

    def __init__(self, key: str, zero: V) -> None:
        self.key, self.zero = key, zero

    @overload
    def __get__(self, obj: None, owner: type) -> Family[V]: ...

    @overload
    def __get__(self, obj: StatsWriter, owner: type) -> FamilyValues[V]: ...

    def __get__(self, obj: StatsWriter | None, owner: type) -> FamilyValues[V] | Family[V]:
        if obj is None:
            return self
        return FamilyValues(obj, self.key, self.zero)


class StatValues(StatsWriter):
    """A plain store for core code: ``values`` holds what was written (handed to the node whole)."""

    def __init__(self) -> None:
        self.values: dict[str, Any] = {}

    @classmethod
    def of(cls, values: Mapping[str, Any]) -> Self:
        """A store holding a copy of ``values`` (written by a twin of the same record)."""
        out = cls()
        out.values.update(values)
        return out

    def _stat(self, key: str, default: Any) -> Any:  # noqa: ANN401
        return self.values.get(key, default)

    def _set_stat(self, key: str, value: Any) -> None:  # noqa: ANN401
        self.values[key] = value


def _type_name(hint: Any) -> str:  # noqa: ANN401 - a type hint
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if args and len(args) < len(typing.get_args(hint)):
        return f"{args[0].__name__} | None"
    return str(hint.__name__)


def render() -> str:
    """The source of ``telemetry_fields.py``: one twin per record of ``telemetry.TELEMETRY``, each
    field a :class:`Stat` or :class:`Family` with the record's type and default."""
    from memgs_ros.core.runtime import telemetry

    records: list[type] = [telemetry.NodeTelemetry, *dict.fromkeys(telemetry.TELEMETRY.values())]
    comments = _field_comments(Path(telemetry.__file__).read_text())
    lines = ['"""Generated from core/runtime/telemetry.py by `python -m memgs_ros.core.runtime.stat_fields',
             '--write`: do not edit (test_telemetry fails while it is stale). See stat_fields.py."""',
             "from __future__ import annotations", "",
             "from memgs_ros.core.runtime.stat_fields import Family, Stat, StatsWriter"]
    for record in records:
        base = record.__mro__[1]
        parent = "StatsWriter" if base is object else _twin(base)
        hints = typing.get_type_hints(record)
        own = [f for f in dataclasses.fields(record) if f.name not in getattr(base, "__dataclass_fields__", {})]
        lines += ["", "", f"class {_twin(record)}({parent}):",
                  f'    """{record.__name__}, written by attribute."""', ""]
        for f in own:
            hint = hints[f.name]
            name = RENAMED.get(f.name, f.name)
            if typing.get_origin(hint) is Mapping:
                kind = typing.get_args(hint)[1]
                line = f'    {name} = Family[{kind.__name__}]("{f.name}", {kind(0)!r})'
            else:
                default = f'"{f.default}"' if isinstance(f.default, str) else repr(f.default)
                line = f"    {name} = Stat[{_type_name(hint)}]({default})"
            comment = comments.get((record.__name__, f.name))
            lines.append(f"{line}  # {comment}" if comment else line)
    return "\n".join(lines) + "\n"


def _field_comments(source: str) -> dict[tuple[str, str], str]:
    """{(record, field): the comment on the field's line in telemetry.py}: the twin says what each means."""
    out: dict[tuple[str, str], str] = {}
    record = ""
    for line in source.splitlines():
        if line.startswith("class "):
            record = line[6:].split("(")[0].split(":")[0]
        elif line.startswith("    ") and ":" in line and "  # " in line and not line.lstrip().startswith("#"):
            out[(record, line.strip().split(":")[0])] = line.split("  # ", 1)[1].strip()
    return out


def _twin(record: type) -> str:
    return record.__name__.removesuffix("Telemetry") + "Fields"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="write (or check) core/runtime/telemetry_fields.py")
    ap.add_argument("--write", action="store_true", help="write it (default: exit 1 if it is stale)")
    args = ap.parse_args(argv)
    text = render()
    if args.write:
        FIELDS_PATH.write_text(text)
        return 0
    stale = FIELDS_PATH.read_text() != text
    if stale:
        print(f"{FIELDS_PATH} is stale: python -m memgs_ros.core.runtime.stat_fields --write", file=sys.stderr)
    return int(stale)


if __name__ == "__main__":
    sys.exit(main())

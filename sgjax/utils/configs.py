"""Frozen config dataclasses back from their saved form (`dataclasses.asdict`, e.g. through JSON).

Run directories and labelled directories save the config that made them as JSON; `from_dict` rebuilds
the dataclass from that, nested configs included, so a tool can re-run what made a directory (a
labelled scene rebuilt from its index, a training run's network) without the command line that made it.
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from typing import Any, TypeVar

T = TypeVar("T")


@functools.lru_cache(maxsize=None)
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def from_dict(cls: type[T], data: typing.Mapping[str, Any], where: str | None = None) -> T:
    """The dataclass `cls` from `data` (as `dataclasses.asdict(cls(...))` gives it, possibly through JSON:
    lists become tuples again, nested dataclass fields are rebuilt from their dicts). Fields missing
    from `data` take their defaults (a config saved before the field existed); a field the class has
    retired (its `RETIRED_FIELDS`: name -> the value that behaved as today's code does) is dropped when
    it holds that value, and refused by name otherwise (today's code cannot do what it asked); any other
    key `cls` does not have raises ValueError naming it, as does a value of the wrong kind for a nested
    config."""
    where = where or cls.__name__
    if not isinstance(data, typing.Mapping):
        raise ValueError(f"{where}: expected a mapping of fields, got {type(data).__name__}")
    data = _without_retired(cls, data, where)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(f"{where}: unknown fields {unknown}")
    hints = _hints(cls)
    return cls(**{name: _value(hints[name], data[name], f"{where}.{name}") for name in fields if name in data})


def _without_retired(cls: type, data: typing.Mapping[str, Any], where: str) -> typing.Mapping[str, Any]:
    """data without the fields `cls.RETIRED_FIELDS` names, each checked to hold its retired value."""
    retired = getattr(cls, "RETIRED_FIELDS", {})
    present = set(data) & set(retired)
    if not present:
        return data
    for name in present:
        if _tuples(data[name]) != retired[name]:
            raise ValueError(f"{where}.{name} = {data[name]!r}: this option was retired (docs/experiments.md); "
                             f"only {retired[name]!r}, today's behaviour, can be read back")
    return {k: v for k, v in data.items() if k not in present}


def _value(tp: Any, value: Any, where: str) -> Any:
    if value is None:
        return None
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, where)
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in args if a is not type(None)]
        configs = [a for a in options if dataclasses.is_dataclass(a)]
        if isinstance(value, typing.Mapping) and len(configs) == 1:
            return from_dict(configs[0], value, where)
        return _value(options[0], value, where) if len(options) == 1 else _tuples(value)
    if origin is tuple and isinstance(value, (list, tuple)):
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_value(args[0], v, where) for v in value)
        if args and len(args) == len(value):
            return tuple(_value(a, v, where) for a, v in zip(args, value))
        return _tuples(value)
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)  # JSON writes 2.0 as 2.0, but a hand-written 2 should still be a float
    return _tuples(value)


def _tuples(value: Any) -> Any:
    """Lists (JSON's sequences) as tuples, as the frozen configs hold them."""
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    return value

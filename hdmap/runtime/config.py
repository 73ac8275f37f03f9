"""Typed configuration: dataclasses filled from TOML tables, never bare dicts.

>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class C:
...     a: int = 1
...     b: float = 2.0
>>> from_mapping(C, {"a": 3})
C(a=3, b=2.0)
>>> from_mapping(C, {"c": 1})
Traceback (most recent call last):
...
hdmap.runtime.config.ConfigError: c: unknown key (known: a, b)
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    """A config file or mapping that does not fit its dataclass; names the key."""


EXIT_CONFIG = 78
"""Exit code of a service whose configuration is refused (sysexits ``EX_CONFIG``): a
permanent fault, like a corrupt database, that a restart cannot cure."""


def from_mapping(cls: type[T], data: Mapping[str, Any], path: str = "", base: T | None = None) -> T:
    """Build dataclass ``cls`` from a mapping, checking keys and scalar types.

    Keys override ``base`` (default: the class defaults); a nested table overrides the
    field's own default, so a section that sets one knob keeps the others its owner chose.
    """
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path or cls.__name__}: expected a table")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    unknown = set(data) - set(fields)
    if unknown:
        where = f"{path}." if path else ""
        raise ConfigError(
            f"{where}{sorted(unknown)[0]}: unknown key (known: {', '.join(sorted(fields))})"
        )
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        key = f"{path}.{name}" if path else name
        default = _field_default(fields[name]) if base is None else getattr(base, name)
        if dataclasses.is_dataclass(default) and isinstance(value, Mapping):
            kwargs[name] = from_mapping(type(default), value, key, base=default)
        else:
            kwargs[name] = _coerce(hints[name], value, key)
    return cls(**kwargs) if base is None else dataclasses.replace(base, **kwargs)  # type: ignore[type-var]


def _field_default(f: dataclasses.Field) -> Any:
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None if f.default is dataclasses.MISSING else f.default


def _coerce(tp: Any, value: Any, key: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return from_mapping(tp, value, key)  # type: ignore[arg-type]
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{key}: expected a list")
        (inner, *_rest) = typing.get_args(tp) or (Any,)
        return tuple(_coerce(inner, v, f"{key}[{i}]") for i, v in enumerate(value))
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(args[0], value, key)
    if origin is typing.Literal:
        allowed = typing.get_args(tp)
        if value not in allowed or isinstance(value, bool) != isinstance(allowed[0], bool):
            raise ConfigError(f"{key}: expected one of {', '.join(map(repr, allowed))}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{key}: expected a number, got {type(value).__name__}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {type(value).__name__}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string")
        return value
    if tp is Path:
        return Path(value)
    return value


def load_toml(path: str | Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def parse_settings(pairs: list[str]) -> dict[str, Any]:
    """``KEY=JSON`` pairs (a command line's repeated ``--set``) as a mapping of dotted keys
    to values; a pair without ``=`` or with a value that is not JSON is an error naming it.

    >>> parse_settings(["tick_s=0.5", "gate.chi2_gate=12"])
    {'tick_s': 0.5, 'gate.chi2_gate': 12}
    """
    out: dict[str, Any] = {}
    for kv in pairs:
        key, eq, value = kv.partition("=")
        if not eq or not key:
            raise ConfigError(f"{kv!r}: expected KEY=JSON")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{key}: {value!r} is not JSON ({exc.msg})") from exc
    return out


def dotted_table(settings: Mapping[str, Any]) -> dict[str, Any]:
    """Dotted keys as nested tables, what :func:`from_mapping` takes.

    >>> dotted_table({"tick_s": 0.5, "gate.chi2_gate": 12})
    {'tick_s': 0.5, 'gate': {'chi2_gate': 12}}
    """
    table: dict[str, Any] = {}
    for key, value in settings.items():
        *heads, last = key.split(".")
        node = table
        for h in heads:
            node = node.setdefault(h, {})
        node[last] = value
    return table

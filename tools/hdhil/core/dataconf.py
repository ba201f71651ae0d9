"""Typed configuration from plain data (TOML tables, JSON, CLI overrides).

Every configuration in hdhil is a tree of frozen dataclasses.  ``from_dict`` builds
one from nested dicts, checking names and types, so that a typo in a scenario file
or a value of the wrong kind is a one-line error naming the key, not a traceback.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
import types
import typing
from typing import Any, TypeVar

from hdhil.core.errors import ConfigError
from hdhil.core.numbers import FLOAT32_MAX, check_number

T = TypeVar("T")


def _convert(tp: Any, value: Any, where: str, allow_inf: bool = False) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, where, allow_inf)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{where}: bad value {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: must be one of {list(args)}, got {value!r}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if origin is tuple and args:
            if len(args) != len(value):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
            pairs = enumerate(zip(args, value, strict=True))
            return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in pairs)
        inner = args[0] if args else Any
        return origin(_convert(inner, v, f"{where}[{i}]") for i, v in enumerate(value))
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a table, got {value!r}")
        return from_dict(tp, value, where)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        if isinstance(value, tp):
            return value
        if isinstance(value, str):
            try:
                return tp[value.upper().replace("-", "_")]
            except KeyError:
                pass
        try:
            return tp(value)
        except ValueError:
            names = [m.name.lower() for m in tp]
            raise ConfigError(f"{where}: must be one of {names}, got {value!r}") from None
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        # Every configuration float is finite (a field may allow +inf, "never") and fits
        # the object dictionary's REAL32.
        check_number(value, where, lo=-FLOAT32_MAX, hi=FLOAT32_MAX, allow_inf=allow_inf)
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer() and abs(value) < 2**63:
                return int(value)
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        check_number(value, where, integer=True)
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


@functools.cache
def _shape(cls: type) -> tuple[dict[str, Any], dict[str, dataclasses.Field[Any]]]:
    """A dataclass's resolved field types and its ``__init__`` fields (resolving the
    annotations is most of the cost of a :func:`from_dict`; a class's never change)."""
    hints = typing.get_type_hints(cls)
    return hints, {f.name: f for f in dataclasses.fields(cls) if f.init}


def from_dict(cls: type[T], data: dict[str, Any], where: str = "") -> T:
    """Build dataclass ``cls`` from ``data``; missing keys keep their defaults.

    Raises ``ConfigError`` naming the dotted key for unknown keys, wrong types,
    and any ``ValueError`` the dataclass's own ``__post_init__`` checks raise.
    """
    if isinstance(data, cls):  # already built (a typed scenario's table)
        return data
    hints, fields = _shape(cls)
    unknown = sorted(set(data) - set(fields))
    if unknown:
        prefix = f"{where}." if where else ""
        raise ConfigError(f"unknown key {prefix}{unknown[0]} (known: {', '.join(sorted(fields))})")
    kwargs = {}
    for name, value in data.items():
        key = f"{where}.{name}" if where else name
        allow_inf = bool(fields[name].metadata.get("allow_inf"))
        kwargs[name] = _convert(hints[name], value, key, allow_inf)
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{where or cls.__name__}: {exc}") from None


def merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """Deep-merge two nested dicts (override wins), without mutating either."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = value
    return out


def to_dict(obj: Any) -> Any:
    """The plain-data form of a config tree (enums by lower-case name); fields derived in
    ``__post_init__`` (``init=False``) are left out, so ``from_dict`` takes it back."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init}
    if isinstance(obj, enum.Enum):
        return obj.name.lower()
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    return obj


_RULES = {
    "finite": ("be finite", lambda v: True),
    ">0": ("be > 0", lambda v: v > 0),
    ">=0": ("be >= 0", lambda v: v >= 0),
    "!=0": ("be non-zero", lambda v: v != 0),
}


def check_fields(obj: object, rules: dict[str, str]) -> None:
    """Validate numeric fields of a config dataclass in ``__post_init__``.

    ``rules`` maps a field name to ``"finite"``, ``">0"``, ``">=0"`` or ``"!=0"`` (every
    rule implies a finite number).  Raises ``ValueError`` naming ``Class.field``, which
    ``from_dict`` turns into a one-line ``ConfigError`` naming the key.
    """
    cls = type(obj).__name__
    for name, rule in rules.items():
        value = getattr(obj, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{cls}.{name} must be a number, got {value!r}")
        what, ok = _RULES[rule]
        if not (math.isfinite(value) and ok(value)):
            raise ValueError(f"{cls}.{name} must {what} (and finite), got {value!r}")

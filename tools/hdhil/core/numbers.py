"""One check for every number a user gives, on the command line or in a TOML file.

A number must be finite (unless a field says otherwise), inside its range, and
representable where it ends up: a configuration float is sent over CAN and held in
the object dictionary as REAL32 (CiA 301 data type 0x0008), so its magnitude must fit a
float32; a duration becomes a count of sample periods, so it must stay below
:data:`MAX_SECONDS`.  The same :func:`check_number` produces the message for an
``argparse`` type function (:func:`arg_float`, :func:`arg_int`) and for the
configuration dataclasses (:func:`hdhil.core.dataconf.from_dict`), so a value is
refused in the same words wherever it comes from.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from hdhil.core.errors import ConfigError

#: Largest finite float32 (IEEE 754 binary32): the object dictionary's REAL32.
FLOAT32_MAX = 3.4028234663852886e38
#: Longest duration accepted anywhere (s): a year, 3.2e10 sample periods at 1 kHz.
MAX_SECONDS = 365 * 24 * 3600.0
#: Widest integer accepted in a configuration (CiA 301 INTEGER64/UNSIGNED64 range).
INT_LIMIT = 2**64
#: Latest date accepted as a run's start (Unix seconds): 9999-12-31, the last year a
#: trace's date fields and ISO 8601 hold.
MAX_UNIX_TIME = 253402300799.999

__all__ = [
    "FLOAT32_MAX",
    "MAX_SECONDS",
    "MAX_UNIX_TIME",
    "arg_float",
    "arg_int",
    "arg_seconds",
    "check_number",
]


def _fmt(x: float) -> str:
    return f"{x:g}"


def check_number(
    value: object,
    where: str,
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    integer: bool = False,
    allow_inf: bool = False,
) -> float | int:
    """``value`` if it is a number (an integer if ``integer``), finite (``+inf`` too with
    ``allow_inf``), with ``lo <= value <= hi`` (``lo < value`` if ``lo_open``); else a
    :class:`ConfigError` "``where`` must be ..., got ``value``"."""
    if integer:
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, got {_short(value)}")
    elif isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{where} must be a number, got {_short(value)}")
    x = value
    ok_inf = allow_inf and x == math.inf
    if isinstance(x, float) and not math.isfinite(x) and not ok_inf:
        raise ConfigError(f"{where} must be a finite number, got {_short(x)}")
    if isinstance(x, int) and not -INT_LIMIT < x < INT_LIMIT:
        raise ConfigError(f"{where} must be within ±2^64, got {_short(x)}")
    if lo is not None and (x <= lo if lo_open else x < lo):
        op = ">" if lo_open else ">="
        raise ConfigError(f"{where} must be {op} {_fmt(lo)}, got {_short(x)}")
    if hi is not None and x > hi and not ok_inf:
        raise ConfigError(f"{where} must be <= {_fmt(hi)}, got {_short(x)}")
    return x


def _short(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _parse(text: str, integer: bool, where: str) -> float | int:
    if len(text) > 100:
        raise ConfigError(f"{where}: {text[:20]!r}... is not a number")
    if integer:
        try:
            return int(text, 0)
        except ValueError:
            raise ConfigError(f"{where} must be an integer, got {text!r}") from None
    try:
        return float(text)
    except ValueError:
        raise ConfigError(f"{where} must be a number, got {text!r}") from None


def _arg(integer: bool, where: str, **limits: object) -> Callable[[str], float | int]:
    def convert(text: str) -> float | int:
        try:
            return check_number(_parse(text, integer, where), where, integer=integer,
                                **limits)  # type: ignore[arg-type]  # fmt: skip
        except ConfigError as exc:
            # argparse prints "hdhil CMD: error: argument --x: <message>", one line, exit 2
            raise argparse.ArgumentTypeError(str(exc).removeprefix(f"{where} ")) from None

    convert.__name__ = "integer" if integer else "number"
    return convert


def arg_float(
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    allow_inf: bool = False,
) -> Callable[[str], float | int]:
    """An ``argparse`` ``type=`` for a finite float in range (see :func:`check_number`)."""
    return _arg(False, "value", lo=lo, hi=hi, lo_open=lo_open, allow_inf=allow_inf)


def arg_int(lo: int | None = None, hi: int | None = None) -> Callable[[str], float | int]:
    """An ``argparse`` ``type=`` for an integer in range (decimal, or 0x.. hexadecimal)."""
    return _arg(True, "value", lo=lo, hi=hi)


def arg_seconds(lo_open: bool = True, hi: float = MAX_SECONDS) -> Callable[[str], float | int]:
    """An ``argparse`` ``type=`` for a duration in seconds: finite, > 0 (>= 0 with
    ``lo_open=False``), at most :data:`MAX_SECONDS`."""
    return _arg(False, "value", lo=0.0, hi=hi, lo_open=lo_open)

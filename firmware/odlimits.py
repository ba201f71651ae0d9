"""The firmware configuration checked against the controller's object dictionary.

Every firmware parameter that lives in the OD (:data:`hdhil.firmware.controller.PARAMETERS`,
``dbc/controller.eds``) must be representable there: inside the entry's ``LowLimit`` ..
``HighLimit`` where the EDS gives them, and inside its data type (REAL32: a finite
float32; integers: their width).  A scenario value outside is refused with one line
naming the parameter and the object, instead of being written into the OD with only a
warning (CiA 306: the limits are the range a value may take).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

from hdhil.core.errors import ConfigError
from hdhil.core.numbers import FLOAT32_MAX
from hdhil.firmware.config import FirmwareConfig

#: Integer ranges of the CiA 301 integer data types (by the canopen package's type code).
_INT_RANGES = {
    0x02: (-(2**7), 2**7 - 1), 0x03: (-(2**15), 2**15 - 1), 0x04: (-(2**31), 2**31 - 1),
    0x15: (-(2**63), 2**63 - 1), 0x05: (0, 2**8 - 1), 0x06: (0, 2**16 - 1),
    0x07: (0, 2**32 - 1), 0x1B: (0, 2**64 - 1),
}  # fmt: skip
_REAL32 = 0x08


def _od() -> Any:
    """The controller's object dictionary, the parse its node copies (looked up only)."""
    from hdhil.canopen.od import reference_od
    from hdhil.dbc import eds_path

    return reference_od(eds_path("controller"), 1)


@functools.cache
def _eds_limits() -> dict[tuple[int, int], tuple[float | None, float | None]]:
    """``LowLimit``/``HighLimit`` per (index, sub) as written in the EDS (the canopen
    package keeps them for integer types only); read once per machine
    (:mod:`hdhil.dbc.parsecache`)."""
    from hdhil.dbc import eds_path
    from hdhil.dbc.parsecache import cached

    path = eds_path("controller")
    return cached(path, "odlimits", lambda: _read_limits(path), code=(__file__,))


def _read_limits(path: Path) -> dict[tuple[int, int], tuple[float | None, float | None]]:
    from hdhil.canopen.od import eds_parser

    eds = eds_parser(path)  # the controller node's own read of the file
    limits: dict[tuple[int, int], tuple[float | None, float | None]] = {}
    for section in eds.sections():
        index, _, sub = section.partition("sub")
        try:
            key = (int(index, 16), int(sub, 16) if sub else 0)
        except ValueError:
            continue
        lo, hi = eds[section].get("LowLimit"), eds[section].get("HighLimit")
        if lo is not None or hi is not None:
            limits[key] = (
                float(int(lo, 0))
                if lo and lo.lower().startswith("0x")
                else (float(lo) if lo else None),
                float(int(hi, 0))
                if hi and hi.lower().startswith("0x")
                else (float(hi) if hi else None),
            )
    return limits


def check_od_limits(cfg: FirmwareConfig) -> None:
    """Raise :class:`ConfigError` for the first parameter of ``cfg`` the OD cannot hold."""
    from hdhil.firmware.parameters import PARAMETERS

    od = _od()
    for p in PARAMETERS:
        value = p.get(cfg)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            continue  # enums and strings: their converters check them
        try:
            var = (
                od[p.index][p.sub]
                if p.sub or not hasattr(od[p.index], "data_type")
                else od[p.index]
            )
        except KeyError:
            continue
        where = f"firmware {p.stage} parameter {p.name} (object 0x{p.index:04X}:{p.sub:02X})"
        if var.data_type == _REAL32 and not (math.isfinite(value) and abs(value) <= FLOAT32_MAX):
            raise ConfigError(f"{where} must be a finite REAL32, got {value!r}")
        lo, hi = _INT_RANGES.get(var.data_type, (None, None))
        eds_lo, eds_hi = _eds_limits().get((p.index, p.sub), (None, None))
        lo = eds_lo if eds_lo is not None else lo
        hi = eds_hi if eds_hi is not None else hi
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise ConfigError(f"{where} must be within [{_g(lo)}, {_g(hi)}], got {value!r}")


def _g(x: float | None) -> str:
    return "unbounded" if x is None else f"{x:g}"

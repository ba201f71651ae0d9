"""Object-dictionary helpers on canopen's ``ObjectDictionary``.

canopen's EDS reader is used for everything it reads; :func:`load_od` only adds the
LowLimit/HighLimit of REAL32/REAL64 objects, which it drops, so range checks cover them.
:func:`variable` is the lookup every protocol module uses: unlike ``od[index][sub]`` it
never invents array members (canopen's ``ODArray`` answers any sub-index 1..255).
"""

from __future__ import annotations

import configparser
import re
from functools import cache
from pathlib import Path

import canopen
from canopen.objectdictionary import ObjectDictionary, ODVariable
from canopen.objectdictionary import datatypes as dt

__all__ = ["eds_index", "index_of", "is_comm_index", "is_mapping_index", "load_od", "variable"]

_SECTION = re.compile(r"^([0-9A-Fa-f]{4})(?:sub([0-9A-Fa-f]+))?$")


def load_od(source: str | Path | ObjectDictionary, node_id: int) -> ObjectDictionary:
    """Import an EDS/DCF (or pass an ``ObjectDictionary`` through).

    canopen's EDS reader parses LowLimit/HighLimit as integers only and silently drops
    them for REAL32/REAL64 objects; they are read again here so range checks cover them.
    """
    if isinstance(source, ObjectDictionary):
        return source
    od = canopen.import_od(str(source), node_id)
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",), strict=False)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read(str(source), encoding="utf-8")
    for section in parser.sections():
        match = _SECTION.match(section)
        if not match:
            continue
        index = int(match.group(1), 16)
        sub = int(match.group(2), 16) if match.group(2) else 0
        var = variable(od, index, sub)
        if var is None or var.data_type not in dt.FLOAT_TYPES:
            continue
        for option, attr in (("LowLimit", "min"), ("HighLimit", "max")):
            if parser.has_option(section, option):
                setattr(var, attr, float(parser.get(section, option)))
    return od


def variable(od: ObjectDictionary, index: int, sub: int) -> ODVariable | None:
    """The variable at index:sub, or None (array sub-indices must be defined)."""
    obj = od.get(index)
    if obj is None:
        return None
    if isinstance(obj, ODVariable):
        return obj if sub == 0 else None
    return obj.subindices.get(sub)


def is_comm_index(index: int) -> bool:
    """True for a PDO communication parameter (RPDO 0x1400-0x15FF, TPDO 0x1800-0x19FF)."""
    return 0x1400 <= index <= 0x15FF or 0x1800 <= index <= 0x19FF


def is_mapping_index(index: int) -> bool:
    """True for a PDO mapping parameter (RPDO 0x1600-0x17FF, TPDO 0x1A00-0x1BFF)."""
    return 0x1600 <= index <= 0x17FF or 0x1A00 <= index <= 0x1BFF


def index_of(od: ObjectDictionary, name: str) -> int:
    """Index of the object named ``name`` (its EDS ParameterName) in ``od``.

    Nodes find the CiA 402 objects by name, so the numbers live in the EDS only.
    """
    try:
        return od[name].index
    except KeyError:
        raise KeyError(f"no object named {name!r} in the object dictionary") from None


@cache
def eds_index(path: str, name: str) -> int:
    """:func:`index_of` in the EDS at ``path`` (read once per process)."""
    return index_of(canopen.import_od(path), name)

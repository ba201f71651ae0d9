"""Object-dictionary helpers on canopen's ``ObjectDictionary``.

canopen's EDS reader is used for everything it reads; :func:`load_od` only adds the
LowLimit/HighLimit of REAL32/REAL64 objects, which it drops, so range checks cover them.
:func:`variable` is the lookup every protocol module uses: unlike ``od[index][sub]`` it
never invents array members (canopen's ``ODArray`` answers any sub-index 1..255).

Each EDS/DCF file is parsed once per process and node-ID (keyed by its path, size and
modification time, so a rewritten file is read again): a run reads the controller's EDS
for its node and for the firmware's parameter limits (:func:`reference_od`,
:func:`eds_parser`), the drive's for its node and for the controller's name lookups
(:func:`eds_index`); each parse is also kept on disk, so a shipped file is parsed once
per machine (:mod:`hdhil.dbc.parsecache`).  :func:`load_od` hands every node a deep copy
of its own, since a node writes into its dictionary (unpickled from the parse's pickle: a
fraction of the time ``copy.deepcopy`` takes, and canopen's dictionary classes are plain
objects).
"""

from __future__ import annotations

import configparser
import os
import pickle
import re
from functools import lru_cache
from pathlib import Path

import canopen
from canopen.objectdictionary import ObjectDictionary, ODVariable
from canopen.objectdictionary import datatypes as dt

from hdhil.dbc.parsecache import cached, cached_pickle

__all__ = [
    "eds_index",
    "eds_parser",
    "index_of",
    "is_comm_index",
    "is_mapping_index",
    "load_od",
    "reference_od",
    "variable",
]

_SECTION = re.compile(r"^([0-9A-Fa-f]{4})(?:sub([0-9A-Fa-f]+))?$")
_OBJECT = re.compile(r"^[0-9A-Fa-f]{4}$")

#: (absolute path, size, modification time in ns): the cache key of a file's parse.
_FileKey = tuple[str, int, int]


def _file_key(path: str | Path) -> _FileKey:
    name = os.path.abspath(path)
    st = os.stat(name)
    return name, st.st_size, st.st_mtime_ns


def load_od(source: str | Path | ObjectDictionary, node_id: int) -> ObjectDictionary:
    """Import an EDS/DCF (or pass an ``ObjectDictionary`` through).

    canopen's EDS reader parses LowLimit/HighLimit as integers only and silently drops
    them for REAL32/REAL64 objects; they are read again here so range checks cover them.
    The result is the caller's own: a deep copy of the file's one parse for ``node_id``.
    """
    if isinstance(source, ObjectDictionary):
        return source
    od: ObjectDictionary = pickle.loads(_pickled_od(_file_key(source), node_id))
    return od


def reference_od(source: str | Path, node_id: int | None = None) -> ObjectDictionary:
    """The object dictionary :func:`load_od` copies, shared: for looking things up only
    (a node's own dictionary comes from :func:`load_od`)."""
    return _parsed_od(_file_key(source), node_id)


def eds_parser(source: str | Path) -> configparser.RawConfigParser:
    """The file's sections and options as read for the REAL limits (comments after ``;``
    dropped, option names as written), shared: for reading only."""
    return _parser(_file_key(source))


@lru_cache(maxsize=32)
def _parser(key: _FileKey) -> configparser.RawConfigParser:
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",), strict=False)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read(key[0], encoding="utf-8")
    return parser


@lru_cache(maxsize=32)
def _pickled_od(key: _FileKey, node_id: int | None) -> bytes:
    return cached_pickle(
        key[0], f"od-{node_id}", lambda: _parse_od(key, node_id), ("canopen",), (__file__,)
    )


@lru_cache(maxsize=32)
def _parsed_od(key: _FileKey, node_id: int | None) -> ObjectDictionary:
    od: ObjectDictionary = pickle.loads(_pickled_od(key, node_id))
    return od


def _parse_od(key: _FileKey, node_id: int | None) -> ObjectDictionary:
    od = canopen.import_od(key[0], node_id)
    parser = _parser(key)
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


def eds_index(path: str, name: str) -> int:
    """:func:`index_of` in the EDS at ``path``, from the file's sections (those
    :func:`load_od` reads; no object dictionary is built for it), named as canopen
    names them: each ``[xxxx]`` section's ParameterName, a later one winning."""
    try:
        return _object_names(_file_key(path))[name]
    except KeyError:
        raise KeyError(f"no object named {name!r} in the object dictionary") from None


@lru_cache(maxsize=32)
def _object_names(key: _FileKey) -> dict[str, int]:
    def parse() -> dict[str, int]:
        parser = _parser(key)
        return {
            parser.get(section, "ParameterName"): int(section, 16)
            for section in parser.sections()
            if _OBJECT.match(section)
        }

    return cached(key[0], "od-names", parse, code=(__file__,))

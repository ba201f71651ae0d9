"""Each EDS is consistent with itself (CiA 306): DeviceInfo against the identity object
0x1018, the PDO counts against the PDO objects present, SubNumber against the sub-index
sections, the object lists against the sections, and canopen's reader loads it."""

from __future__ import annotations

import configparser
import re

import canopen
import pytest

from hdhil.dbc import eds_path

NODES = ("controller", "drive")


def _parser(node: str) -> configparser.RawConfigParser:
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",), strict=True)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read(str(eds_path(node)), encoding="utf-8")
    return parser


def _objects(parser: configparser.RawConfigParser) -> list[int]:
    return sorted(int(s, 16) for s in parser.sections() if re.fullmatch(r"[0-9A-F]{4}", s))


@pytest.mark.parametrize("node", NODES)
def test_device_info_agrees_with_the_identity_object(node):
    p = _parser(node)
    info = p["DeviceInfo"]
    for option, sub in (("VendorNumber", 1), ("ProductNumber", 2), ("RevisionNumber", 3)):
        assert int(info[option], 0) == int(p[f"1018sub{sub}"]["DefaultValue"], 0), option
    objects = _objects(p)
    assert int(info["NrOfRXPDO"]) == sum(0x1400 <= i <= 0x15FF for i in objects)
    assert int(info["NrOfTXPDO"]) == sum(0x1800 <= i <= 0x19FF for i in objects)
    for i in objects:  # every communication parameter has its mapping parameter
        if 0x1400 <= i <= 0x15FF or 0x1800 <= i <= 0x19FF:
            assert i + 0x200 in objects, hex(i)


@pytest.mark.parametrize("node", NODES)
def test_sub_numbers_and_object_lists_match_the_sections(node):
    p = _parser(node)
    objects = _objects(p)
    for index in objects:
        section = p[f"{index:04X}"]
        subs = [s for s in p.sections() if re.fullmatch(rf"{index:04X}sub[0-9A-Fa-f]+", s)]
        if int(section["ObjectType"], 0) in (0x8, 0x9) and "CompactSubObj" not in section:
            assert int(section.get("SubNumber", "0"), 0) == len(subs), f"{index:04X}"
            sub0 = p[f"{index:04X}sub0"]
            if "highest sub-index" in sub0["ParameterName"].lower():
                highest = max(int(s[7:], 16) for s in subs)
                assert int(sub0["DefaultValue"], 0) == highest, f"{index:04X}"
        else:
            assert not subs, f"{index:04X} is a variable with sub-index sections"
    listed = []
    for name in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        block = p[name]
        n = int(block["SupportedObjects"], 0)
        listed += [int(block[str(k)], 0) for k in range(1, n + 1)]
    assert sorted(listed) == objects
    assert canopen.import_od(str(eds_path(node))) is not None

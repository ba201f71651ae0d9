"""hdhil.canopen.od: one parse per EDS file and node-ID, a node's own copy, the name lookup."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import canopen
import pytest
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from hdhil.canopen import od as od_mod
from hdhil.canopen.od import eds_index, load_od, reference_od, variable
from hdhil.dbc import eds_path

NODES = {"controller": 1, "drive": 2}


def variables(od: canopen.ObjectDictionary) -> dict[tuple[int, int], dict]:
    """Every variable's attributes (but its parent), by (index, sub)."""
    out = {}
    for obj in od.values():
        members = obj.values() if isinstance(obj, (ODArray, ODRecord)) else [obj]
        for var in members:
            out[var.index, var.subindex] = {
                k: v for k, v in vars(var).items() if k not in ("parent", "od")
            }
    return out


@pytest.mark.parametrize("name", sorted(NODES))
def test_eds_index_names_objects_as_canopen(name: str) -> None:
    path = str(eds_path(name))
    od = canopen.import_od(path)
    assert len(od.names) > 10
    for obj_name, obj in od.names.items():
        assert eds_index(path, obj_name) == obj.index
    with pytest.raises(KeyError, match="no object named"):
        eds_index(path, "no such object")


@pytest.mark.parametrize("name", sorted(NODES))
def test_load_od_is_a_fresh_parse_of_its_own(name: str) -> None:
    path, node_id = eds_path(name), NODES[name]
    first, second = load_od(path, node_id), load_od(str(path), node_id)
    assert first is not second
    assert variables(first) == variables(second) == variables(reference_od(path, node_id))
    # as canopen reads the file, plus the REAL limits canopen drops
    fresh = variables(canopen.import_od(str(path), node_id))
    ours = variables(first)
    assert ours.keys() == fresh.keys()
    reals = [k for k, v in ours.items() if v["min"] != fresh[k]["min"]]
    for key, attrs in ours.items():
        drop = ("min", "max") if key in reals else ()
        assert {k: v for k, v in attrs.items() if k not in drop} == {
            k: v for k, v in fresh[key].items() if k not in drop
        }
    if name == "controller":
        assert reals  # the filter's REAL32 parameters have limits in the EDS
    # a node's writes stay in its own dictionary
    var = next(v for v in first.values() if isinstance(v, ODVariable))
    var.default = "changed"
    assert variable(second, var.index, 0).default != "changed"
    assert variable(reference_od(path, node_id), var.index, 0).default != "changed"


def test_a_rewritten_file_is_read_again(tmp_path: Path) -> None:
    path = tmp_path / "drive.eds"
    shutil.copy(eds_path("drive"), path)
    index = eds_index(str(path), "statusword")
    assert load_od(path, 2)[index].name == "statusword"
    text = path.read_text(encoding="utf-8").replace(
        "ParameterName=statusword", "ParameterName=status word"
    )
    path.write_text(text, encoding="utf-8")
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    assert load_od(path, 2)[index].name == "status word"
    assert eds_index(str(path), "status word") == index


def test_one_parse_per_file_and_node(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HDHIL_CACHE_DIR", "")  # the per-process cache alone
    od_mod._pickled_od.cache_clear()
    od_mod._parsed_od.cache_clear()
    od_mod._parser.cache_clear()
    calls = []
    real = canopen.import_od
    monkeypatch.setattr(canopen, "import_od", lambda *a: calls.append(a) or real(*a))
    for _ in range(3):
        load_od(eds_path("drive"), 2)
    reference_od(eds_path("drive"), 2)
    load_od(eds_path("drive"), 3)
    assert [a[1] for a in calls] == [2, 3]

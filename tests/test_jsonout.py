"""Machine-readable output is valid JSON (RFC 8259) whatever the numbers:
:mod:`hdhil.core.jsonout` writes non-finite values as null with a ``non_finite`` note,
and every command writes its JSON through it."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hdhil.cli import main
from hdhil.core import jsonout

COMMANDS = Path(__file__).resolve().parents[1] / "tools" / "hdhil" / "commands"


def _strict(text: str) -> Any:
    def refuse(token: str) -> Any:
        raise ValueError(f"invalid JSON token {token}")

    return json.loads(text, parse_constant=refuse)


# ------------------------------------------------------------------------ the writer
@pytest.mark.parametrize(
    ("obj", "kw"),
    [
        ({"b": 1.5, "a": [1, 2.25, {"c": None, "d": True}], "e": "x"}, {"indent": 2}),
        ({"b": 1e-300, "a": (1, 2)}, {"indent": 1, "sort_keys": True}),
        ([0.1, 2, "s"], {"separators": (",", ":")}),
        ({"x": 3.0}, {}),
    ],
)
def test_finite_data_is_written_as_json_dumps_writes_it(obj: Any, kw: dict) -> None:
    assert jsonout.dumps(obj, **kw) == json.dumps(obj, **kw)


def test_non_finite_numbers_are_null_and_noted_by_path() -> None:
    obj = {
        "a": math.nan,
        "b": {"c": [1.0, math.inf, (2.0, -math.inf)]},
        "odd key": {"x y": math.nan},
        "ok": 1.0,
    }
    out = _strict(jsonout.dumps(obj, indent=2))
    assert out["a"] is None and out["b"] == {"c": [1.0, None, [2.0, None]]}
    assert out["odd key"] == {"x y": None} and out["ok"] == 1.0
    assert out["non_finite"] == ["$.a", "$.b.c[1]", "$.b.c[2][1]", '$["odd key"]["x y"]']


def test_numpy_scalars_and_arrays() -> None:
    obj = {
        "f64": np.float64(0.5),
        "f32": np.float32("nan"),
        "i": np.int64(3),
        "flag": np.bool_(True),
        "arr": np.array([[1.0, np.inf], [-np.inf, 2.0]]),
    }
    out = _strict(jsonout.dumps(obj))
    assert out["f64"] == 0.5 and out["f32"] is None and out["i"] == 3 and out["flag"] is True
    assert out["arr"] == [[1.0, None], [None, 2.0]]
    assert out["non_finite"] == ["$.f32", "$.arr[0][1]", "$.arr[1][0]"]
    assert jsonout.dumps({"x": np.float64(0.1)}) == json.dumps({"x": 0.1})


def test_a_top_level_list_or_number_gets_nulls_but_no_note() -> None:
    assert jsonout.dumps([math.nan, 1]) == "[null, 1]"
    assert jsonout.dumps(-math.inf) == "null"
    assert jsonout.dumps({"x": 1}) == '{"x": 1}'  # nothing replaced: no note


def test_a_missed_non_finite_value_fails_loudly() -> None:
    class Odd:
        pass

    with pytest.raises(ValueError):  # allow_nan=False even if a caller asks otherwise
        jsonout.dumps({"x": Odd()}, default=lambda _o: math.nan, allow_nan=True)


def test_dump_writes_what_dumps_returns(tmp_path: Path) -> None:
    path = tmp_path / "out.json"
    with path.open("w") as fh:
        jsonout.dump({"v": [math.nan]}, fh, indent=2)
    assert path.read_text() == jsonout.dumps({"v": [math.nan]}, indent=2)


def test_restore_puts_nan_back_at_the_noted_paths() -> None:
    obj = {"r": {"x y": [1.0, math.inf]}, "m": math.nan, "s": "t", "n": None}
    back = jsonout.restore(_strict(jsonout.dumps(obj, indent=1)))
    assert "non_finite" not in back and back["s"] == "t" and back["n"] is None
    assert math.isnan(back["m"]) and back["r"]["x y"][0] == 1.0
    assert math.isnan(back["r"]["x y"][1])  # an infinity comes back as NaN
    assert jsonout.restore({"a": None}) == {"a": None}  # no note: unchanged
    damaged = {"a": None, "non_finite": ["$.a", "$.gone[3]", "nonsense", 7]}
    assert math.isnan(jsonout.restore(damaged)["a"])


# ----------------------------------------------------------------------- the commands
def _blowing_up_override(tmp_path: Path) -> Path:
    path = tmp_path / "blow-up.toml"
    path.write_text("[plant.drivetrain]\nJ_motor = 1e9\n")
    return path


@pytest.mark.slow
def test_run_json_of_a_blowing_up_plant_is_strict_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    override = _blowing_up_override(tmp_path)
    argv = ["run", "--override", str(override), "--duration", "0.5", "--json", "--quiet"]
    main(argv)
    text = capsys.readouterr().out
    assert not re.search(r"\b(NaN|Infinity)\b", text)
    out = _strict(text)
    assert out["non_finite"], "the override no longer produces a non-finite value"
    for path in out["non_finite"]:
        node: Any = out
        for key in re.findall(r'\.(\w+)|\[(\d+)\]|\["([^"]*)"\]', path):
            name, index, quoted = key
            node = node[int(index)] if index else node[name or quoted]
        assert node is None, path


def test_every_command_writes_json_through_jsonout() -> None:
    offenders = [
        f"{src.name}:{n}"
        for src in sorted(COMMANDS.glob("*.py"))
        for n, line in enumerate(src.read_text().splitlines(), 1)
        if re.search(r"\bjson\.dumps?\(", line)
    ]
    assert offenders == []
    users = [src.name for src in COMMANDS.glob("*.py") if "jsonout.dump" in src.read_text()]
    assert len(users) >= 11


# ------------------------------------------------------------------ files written too
def test_a_sidecar_with_non_finite_metadata_is_strict_json(tmp_path: Path) -> None:
    from hdhil.can.traces.sidecar import read_metadata, write_metadata

    trace = tmp_path / "run.blf"
    path = write_metadata(trace, {"scenario": "s", "offset": math.nan, "seed": 1})
    data = _strict(path.read_text())
    assert data["offset"] is None and data["non_finite"] == ["$.offset"]
    assert read_metadata(trace) == data
    finite = {"scenario": "s", "seed": 1}
    write_metadata(trace, finite)
    assert path.read_text() == json.dumps(finite, indent=1, sort_keys=True) + "\n"


def test_a_stored_campaign_record_keeps_its_nan_when_read_back(tmp_path: Path) -> None:
    from types import SimpleNamespace

    from hdhil.rig.campaign import _load_stored

    record = {"digest": "d1", "result": {"rms": math.nan, "n": 3}, "error": None,
              "wall_s": 0.5, "worker": "w"}  # fmt: skip
    path = tmp_path / "d1.json"
    path.write_text(jsonout.dumps(record, indent=1))
    _strict(path.read_text())
    stored, damage = _load_stored(path, SimpleNamespace(digest="d1"))
    assert damage is None and stored is not None
    assert math.isnan(stored["result"]["rms"]) and stored["result"]["n"] == 3
    assert "non_finite" not in stored

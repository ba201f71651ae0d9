"""The Python API checks its arguments as the command line checks its options: a wrong
type is a ``TypeError`` naming the argument, a bad value (out of range, unknown, a
missing file) a ``ValueError`` naming it, with the command line's bounds; ``bytes`` names
are refused, never looked up as ``"b'free-motion'"``.  Every case fails before a run
starts, so the sweep is cheap."""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import hdhil
from hdhil import api
from hdhil.core.numbers import MAX_SECONDS

TYPE, VALUE = TypeError, ValueError


def _trace(tmp: Path) -> Path:
    """A file that is not a trace (the argument checks come first)."""
    path = tmp / "run.blf"
    path.write_bytes(b"not a trace")
    return path


CASES: list[tuple[str, Callable[[Path], Any], type[Exception], str]] = [
    # load_scenario: hdhil.load_scenario is the checked one
    ("load bytes", lambda t: hdhil.load_scenario(b"free-motion"), TYPE, "scenario must be a str"),
    ("load int", lambda t: hdhil.load_scenario(3), TYPE, "scenario must be a str"),
    ("load None", lambda t: hdhil.load_scenario(None), TYPE, "scenario must be a str"),
    ("load overrides list", lambda t: hdhil.load_scenario("free-motion", [1]), TYPE, "overrides"),
    ("load unknown", lambda t: hdhil.load_scenario("no-such-scenario"), VALUE,
     "unknown scenario 'no-such-scenario'"),
    ("load bad key", lambda t: hdhil.load_scenario("free-motion", {"plant": {"x": 1}}), VALUE,
     "plant"),
    # resolve: the same bounds as hdhil run's options
    ("resolve bytes", lambda t: hdhil.resolve(b"free-motion"), TYPE, "scenario must be a str"),
    ("resolve duration str", lambda t: hdhil.resolve(duration_s="1"), TYPE,
     "duration_s must be a number"),
    ("resolve duration bool", lambda t: hdhil.resolve(duration_s=True), TYPE, "duration_s"),
    ("resolve duration 0", lambda t: hdhil.resolve(duration_s=0.0), VALUE,
     "duration_s must be > 0"),
    ("resolve duration nan", lambda t: hdhil.resolve(duration_s=math.nan), VALUE,
     "duration_s must be a finite number"),
    ("resolve duration inf", lambda t: hdhil.resolve(duration_s=math.inf), VALUE, "duration_s"),
    ("resolve duration absurd", lambda t: hdhil.resolve(duration_s=1e300), VALUE,
     r"duration_s must be <= 3\.1536e\+07"),
    ("resolve duration past cap", lambda t: hdhil.resolve(duration_s=MAX_SECONDS * 1.001),
     VALUE, "duration_s must be <="),
    ("resolve seed str", lambda t: hdhil.resolve(seed="3"), TYPE, "seed must be an int"),
    ("resolve seed float", lambda t: hdhil.resolve(seed=3.5), TYPE, "seed must be an int"),
    ("resolve seed negative", lambda t: hdhil.resolve(seed=-1), VALUE, "seed must be >= 0"),
    ("resolve seed huge", lambda t: hdhil.resolve(seed=2**63), VALUE, "seed must be <="),
    ("resolve start negative", lambda t: hdhil.resolve(evaluate_from_s=-1.0), VALUE,
     "evaluate_from_s must be >= 0"),
    ("resolve start str", lambda t: hdhil.resolve(evaluate_from_s="0"), TYPE, "evaluate_from_s"),
    ("resolve overrides str", lambda t: hdhil.resolve(overrides="x.toml"), TYPE, "overrides"),
    ("resolve overrides [int]", lambda t: hdhil.resolve(overrides=[3]), TYPE, "overrides"),
    ("resolve overrides missing", lambda t: hdhil.resolve(overrides=[t / "none.toml"]), VALUE,
     "none.toml"),
    ("resolve faults str", lambda t: hdhil.resolve(faults="control.loss_rate=0.1"), TYPE,
     "faults"),
    ("resolve faults gen", lambda t: hdhil.resolve(faults=(f for f in ["x=1"])), TYPE, "faults"),
    ("resolve faults [int]", lambda t: hdhil.resolve(faults=[3]), TYPE, "faults"),
    ("resolve faults bad", lambda t: hdhil.resolve(faults=["nonsense"]), VALUE, "nonsense"),
    ("resolve mapping int", lambda t: hdhil.resolve(mapping=3), TYPE, "mapping must be a str"),
    ("resolve mapping unknown", lambda t: hdhil.resolve(mapping="zzz"), VALUE, "zzz"),
    ("resolve calibration int", lambda t: hdhil.resolve(calibration=3), TYPE, "calibration"),
    ("resolve calibration missing", lambda t: hdhil.resolve(calibration=t / "c.toml"), VALUE,
     "c.toml"),
    ("resolve dcf bytes", lambda t: hdhil.resolve(drive_dcf=b"d.dcf"), TYPE, "drive_dcf"),
    # run: the same, before anything runs
    ("run duration kw", lambda t: hdhil.run(duration=1e9), TYPE,
     "run\\(\\) got an unexpected keyword argument 'duration'"),
    ("run duration absurd", lambda t: hdhil.run(duration_s=1e300), VALUE, "duration_s"),
    ("run bytes", lambda t: hdhil.run(b"free-motion"), TYPE, "scenario must be a str"),
    ("run evaluate str", lambda t: hdhil.run(evaluate="yes"), TYPE, "evaluate must be a bool"),
    ("run trace int", lambda t: hdhil.run(trace=3), TYPE, "trace must be a str"),
    ("run trace bytes", lambda t: hdhil.run(trace=b"x.blf"), TYPE, "trace must be a str"),
    ("run start nan", lambda t: hdhil.run(start_time=math.nan), VALUE, "start_time"),
    ("run start negative", lambda t: hdhil.run(start_time=-1.0), VALUE,
     "start_time must be >= 0"),
    ("run start past 9999", lambda t: hdhil.run(start_time=1e300), VALUE,
     "start_time must be <="),
    ("run start str", lambda t: hdhil.run(start_time="2026-01-01"), TYPE, "start_time"),
    ("run controller int", lambda t: hdhil.run(controller_factory=3), TYPE,
     "controller_factory must be callable"),
    ("run drives int", lambda t: hdhil.run(drive_factories=3), TYPE, "drive_factories"),
    ("run drives [int]", lambda t: hdhil.run(drive_factories=[3]), TYPE,
     "drive_factories\\[0\\] must be callable"),
    ("run request + settings", lambda t: hdhil.run(hdhil.resolve(), seed=1), TYPE, "seed"),
    # results and traces
    ("cycle_arrays None", lambda t: hdhil.cycle_arrays(None), TYPE, "result must be a RunResult"),
    ("cycle_arrays dict", lambda t: hdhil.cycle_arrays({}), TYPE, "result must be a RunResult"),
    ("read_trace int", lambda t: hdhil.read_trace(3), TYPE, "path must be a str"),
    ("read_trace bytes", lambda t: hdhil.read_trace(os.fsencode(_trace(t))), TYPE,
     "path must be a str"),
    ("read_trace missing", lambda t: hdhil.read_trace(t / "none.blf"), VALUE, "none.blf"),
    ("read_trace folder", lambda t: hdhil.read_trace(t), VALUE, "directory"),
    ("evaluate int", lambda t: hdhil.evaluate_trace(3), TYPE, "path must be a str"),
    ("evaluate scenario bytes", lambda t: hdhil.evaluate_trace(_trace(t), scenario=b"free-motion"),
     TYPE, "scenario must be a str"),
    ("evaluate scenario int", lambda t: hdhil.evaluate_trace(_trace(t), scenario=3), TYPE,
     "scenario must be a str"),
    ("evaluate skip str", lambda t: hdhil.evaluate_trace(_trace(t), skip_s="1"), TYPE, "skip_s"),
    ("evaluate skip negative", lambda t: hdhil.evaluate_trace(_trace(t), skip_s=-1.0), VALUE,
     "skip_s must be >= 0"),
    ("evaluate skip nan", lambda t: hdhil.evaluate_trace(_trace(t), skip_s=math.nan), VALUE,
     "skip_s must be a finite number"),
    ("evaluate skip absurd", lambda t: hdhil.evaluate_trace(_trace(t), skip_s=1e300), VALUE,
     "skip_s must be <="),
    ("evaluate missing", lambda t: hdhil.evaluate_trace(t / "none.blf"), VALUE, "none.blf"),
]  # fmt: skip


@pytest.mark.parametrize(("call", "kind", "message"), [c[1:] for c in CASES],
                         ids=[c[0] for c in CASES])  # fmt: skip
def test_the_api_refuses_a_wrong_argument_naming_it(
    tmp_path: Path, call: Callable[[Path], Any], kind: type[Exception], message: str
) -> None:
    with pytest.raises(Exception) as info:
        call(tmp_path)
    exc = info.value
    # one exception type per kind of mistake: a wrong type is never a ValueError and a
    # bad value never a TypeError (ConfigError is a ValueError)
    assert type(exc) is kind or (kind is VALUE and isinstance(exc, ValueError)), repr(exc)
    assert not (kind is VALUE and isinstance(exc, TypeError)), repr(exc)
    assert re.search(message, str(exc)), str(exc)
    assert "\n" not in str(exc)
    assert not list(tmp_path.glob("*.blf.json")), "nothing written for a refused call"


def test_a_scenario_name_is_text_in_every_entry_point() -> None:
    from hdhil.rig.scenario import load_scenario

    with pytest.raises(TypeError, match="got bytes"):
        load_scenario(b"free-motion")  # type: ignore[arg-type]
    assert load_scenario(Path("free-motion")).name == hdhil.load_scenario("free-motion").name
    assert api.load_scenario is hdhil.load_scenario


def test_numpy_scalars_are_numbers_like_any_other() -> None:
    """A seed or a duration computed with numpy (``np.int64``, ``np.float32``) is taken
    as the int or float it holds, not refused for its type."""
    import numpy as np

    request = hdhil.resolve(seed=np.int64(3), duration_s=np.float32(0.5))
    assert request.seed == 3 and type(request.seed) is int
    assert request.duration_s == 0.5
    with pytest.raises(TypeError, match="seed must be an int"):
        hdhil.resolve(seed=np.float64(3.0))


@pytest.mark.parametrize("call", [hdhil.read_trace, hdhil.evaluate_trace])
def test_a_path_with_a_nul_character_is_refused_naming_the_argument(call) -> None:
    with pytest.raises(ValueError, match=r"^path: a path cannot hold a NUL character"):
        call("a\0.blf")

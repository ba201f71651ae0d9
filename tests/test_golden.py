"""Unchanged behaviour: the decoded free-motion trace and the ``run --json`` summaries.

The recorded values in ``tests/data/golden.json`` were produced by this same code path.
A refactoring must leave them identical. A change that alters behaviour on purpose
re-records them (``HDHIL_RECORD_GOLDEN=1 python -m pytest tests/test_golden.py``) and
says why in its commit message; the diff of the JSON file shows exactly what moved.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import can
import pytest

from hdhil.core import jsonout
from hdhil.dbc import CHANNEL_NUMBER, database

pytestmark = [pytest.mark.slow, pytest.mark.subprocess]

GOLDEN = Path(__file__).parent / "data" / "golden.json"
RECORD = os.environ.get("HDHIL_RECORD_GOLDEN") == "1"

SCENARIOS = (
    "free-motion",
    "misalignment",
    "chirp",
    "speed-chirp",
    "torque-steps",
    "sine-load",
    "lqg-tracking",
    "lqg-tracking-slow-link",
    "lqg-tracking-squared-weights",
    "lqg-misalignment",
    "lqg-experiment",
)

#: Fields of ``run --json`` that depend on the wall clock or on where the trace went.
WALL_CLOCK_KEYS = frozenset({"wall_s", "real_time_factor", "trace", "realtime", "start_time"})


def _rounded(value: Any) -> Any:
    """Floats to 10 significant digits: the last bits of a BLAS call are not part of the
    behaviour under test."""
    if isinstance(value, float):
        return float(f"{value:.10g}") if value == value else "nan"
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    return value


def _hdhil(*args: str) -> str:
    proc = subprocess.run(
        [sys.executable, "-m", "hdhil", *args], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def _summary(scenario: str) -> dict[str, Any]:
    out = _hdhil("run", "--scenario", scenario, "--duration", "2", "--seed", "1", "--json",
                 "--trace", "")  # fmt: skip
    result = jsonout.restore(json.loads(out))  # null at the non_finite paths -> NaN
    return _rounded({k: v for k, v in result.items() if k not in WALL_CLOCK_KEYS})


def _trace_digest(path: Path) -> dict[str, Any]:
    """Every frame decoded through the DBCs, with times relative to the first frame."""
    by_channel = {ch: database(bus) for bus, ch in CHANNEL_NUMBER.items()}
    digest = hashlib.sha256()
    frames = 0
    t0 = None
    with can.LogReader(str(path)) as reader:
        for msg in reader:
            if t0 is None:
                t0 = msg.timestamp
            db = by_channel[msg.channel]
            try:
                decoded = db.decode_message(msg.arbitration_id, msg.data, decode_choices=False)
            except KeyError:
                decoded = {"raw": msg.data.hex()}
            line = (
                f"{msg.timestamp - t0:.6f} {msg.channel} {msg.arbitration_id:x} "
                f"{json.dumps(_rounded(dict(decoded)), sort_keys=True)}\n"
            )
            digest.update(line.encode())
            frames += 1
    return {"frames": frames, "sha256": digest.hexdigest()}


def _load() -> dict[str, Any]:
    if not GOLDEN.exists():
        return {}
    return json.loads(GOLDEN.read_text())


def _store(key: str, value: Any) -> None:
    data = _load()
    data[key] = value
    GOLDEN.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")


def _check(key: str, value: Any) -> None:
    if RECORD:
        _store(key, value)
        return
    expected = _load().get(key)
    assert expected is not None, f"no recorded value for {key}: record with HDHIL_RECORD_GOLDEN=1"
    assert value == expected


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_run_json_summary_unchanged(scenario: str) -> None:
    _check(f"summary/{scenario}", _summary(scenario))


def test_free_motion_trace_unchanged(tmp_path: Path) -> None:
    trace = tmp_path / "golden.blf"
    _hdhil("run", "--duration", "2", "--seed", "1", "--trace", str(trace))
    _check("trace/free-motion", _trace_digest(trace))


#: Scenarios whose whole trace is digested beside free-motion: loads, a misalignment
#: and the torque-control laws, so a move of the plant, the nodes or the trace path
#: that changes any frame of them fails here.
TRACED = ("torque-steps", "sine-load", "misalignment", "lqg-tracking", "lqg-experiment")


@pytest.mark.parametrize("scenario", TRACED)
def test_scenario_trace_and_evaluation_unchanged(scenario: str, tmp_path: Path) -> None:
    trace = tmp_path / "golden.blf"
    _hdhil("run", "--scenario", scenario, "--duration", "2", "--seed", "1", "--trace", str(trace))
    _check(f"trace/{scenario}", _trace_digest(trace))
    evaluated = json.loads(_hdhil("evaluate", str(trace), "--json"))
    _check(f"evaluate/{scenario}", _rounded(evaluated))

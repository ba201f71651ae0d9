"""One run of a scenario with given settings, as the plain-data result ``hdhil run --json``
prints: the unit of work of a campaign (:mod:`hdhil.rig.campaign`).

A variant travels to a worker process (or a Dask worker on another machine) as plain data:
the fully resolved scenario in its TOML layout (:func:`scenario_data`, every default filled
in, so the worker needs no scenario file) and the run settings.  The worker rebuilds the
:class:`~hdhil.hostsim.scenario.Scenario` with :func:`~hdhil.hostsim.scenario.scenario_from_dict`
(the function ``hdhil run`` loads a scenario with) and calls
:func:`~hdhil.rig.runner.run_lockstep` with the same arguments ``hdhil run`` passes for the
same options, so a variant's result is the result ``hdhil run --json`` prints for it.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hdhil.core.dataconf import to_dict
from hdhil.hostsim.scenario import Scenario, scenario_from_dict
from hdhil.rig.runner import run_lockstep

#: Keys of ``hdhil run --json`` that measure the host, not the run: left out of a
#: variant's stored result so that the same variant gives the same record anywhere.
WALL_CLOCK_KEYS = ("wall_s", "real_time_factor", "realtime", "trace", "start_time")


def scenario_data(scenario: Scenario) -> dict[str, Any]:
    """The scenario in its TOML layout with every default filled in (plain data).

    ``scenario_from_dict(scenario_data(s)) == s``: the form sent to workers and hashed
    to recognise a variant's settings.
    """
    data: dict[str, Any] = {
        "scenario": {
            "name": scenario.name,
            "description": scenario.description,
            "duration_s": scenario.duration_s,
            "seed": scenario.seed,
            "evaluate_from_s": scenario.evaluate_from_s,
        },
        "plant": to_dict(scenario.plant),
        "firmware": scenario.firmware,
    }
    if scenario.faults is not None:
        data["faults"] = to_dict(scenario.faults)
    return data


@dataclass(frozen=True)
class RunSettings:
    """What ``hdhil run --scenario FILE --duration D --seed S --json`` is told, as data.

    ``scenario`` is :func:`scenario_data`'s form.  ``duration_s`` and ``seed`` of None
    keep the scenario's.  The other ``hdhil run`` options keep their defaults (simulated
    bus at 1 Mbit/s, next-SYNC actuation, evaluation from the scenario's
    ``evaluate_from_s``).  ``trace_suffix`` (".blf", ".asc", ...) records the run's trace,
    returned as bytes.
    """

    scenario: dict[str, Any]
    duration_s: float | None = None
    seed: int | None = None
    trace_suffix: str | None = None


def run_settings(settings: RunSettings) -> tuple[dict[str, Any], bytes | None]:
    """Run one variant; return ``hdhil run --json``'s dictionary and the trace's bytes.

    Raises what the run raises (a configuration the runner refuses, a drive that never
    reaches operation): the caller records it.
    """
    scenario = scenario_from_dict(settings.scenario, "variant")
    with tempfile.TemporaryDirectory(prefix="hdhil-variant-") as tmp:
        trace = Path(tmp) / f"trace{settings.trace_suffix}" if settings.trace_suffix else None
        result = run_lockstep(
            scenario,
            settings.duration_s,
            settings.seed,
            trace,
            "simbus",
            "next-sync",
            1_000_000,
            None,
            evaluate=True,
            evaluate_skip_s=scenario.evaluate_from_s,
        )
        data = trace.read_bytes() if trace is not None and trace.is_file() else None
    return result.as_dict(), data

"""One run of a scenario with given settings, as the plain-data result ``hdhil run --json``
prints: the unit of work of a campaign (:mod:`hdhil.rig.campaign`).

A variant travels to a worker process (or a Dask worker on another machine) as plain data:
the fully resolved scenario in its TOML layout (:func:`scenario_data`, every default filled
in, so the worker needs no scenario file) and the run settings.  The worker resolves them
into the :class:`~hdhil.rig.request.RunRequest` ``hdhil run`` would make of the same
options, so a variant's result is the result ``hdhil run --json`` prints for it.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hdhil.can.traces.sidecar import metadata_path
from hdhil.rig.request import RunRequest, resolve
from hdhil.rig.rigrun import run_rig
from hdhil.rig.runner import run_lockstep
from hdhil.rig.scenario import scenario_from_dict

__all__ = ["WALL_CLOCK_KEYS", "RunSettings", "request_of", "run_settings"]

#: Keys of ``hdhil run --json`` that measure the host, not the run: left out of a
#: variant's stored result so that the same variant gives the same record anywhere.
WALL_CLOCK_KEYS = (
    "wall_s", "real_time_factor", "realtime", "trace", "start_time", "us_per_cycle",
)  # fmt: skip


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


def request_of(settings: RunSettings) -> RunRequest:
    """The request ``hdhil run`` makes of the same options; raises
    :class:`~hdhil.core.dataconf.ConfigError` for what it refuses (a duration under one
    sample period or over a year, a seed outside [0, 2**63))."""
    scenario = scenario_from_dict(settings.scenario, "variant")
    return resolve(scenario, duration_s=settings.duration_s, seed=settings.seed)


def run_settings(settings: RunSettings) -> tuple[dict[str, Any], bytes | None, bytes | None]:
    """Run one variant; return ``hdhil run --json``'s dictionary, the trace's bytes and
    its sidecar JSON's bytes (None without a trace).

    The variant is resolved as ``hdhil run`` resolves its options
    (:func:`hdhil.rig.request.resolve`) and run as ``hdhil run`` runs it: a rig of several
    joints by :func:`hdhil.rig.rigrun.run_rig`, a single joint by
    :func:`hdhil.rig.runner.run_lockstep`. Raises what the run raises (a configuration the
    runner refuses, a drive that never reaches operation): the caller records it.
    """
    request = request_of(settings)
    with tempfile.TemporaryDirectory(prefix="hdhil-variant-") as tmp:
        trace = Path(tmp) / f"trace{settings.trace_suffix}" if settings.trace_suffix else None
        result: Any
        if request.scenario.is_rig:  # as `hdhil run` runs a rig: lockstep, every joint
            result = run_rig(request, trace=trace)
        else:
            result = run_lockstep(request, trace=trace, evaluate=True, keep_recording=False)
        data = sidecar = None
        if trace is not None and trace.is_file():
            data = trace.read_bytes()
            side = metadata_path(trace)
            sidecar = side.read_bytes() if side.is_file() else None
    return result.as_dict(), data, sidecar

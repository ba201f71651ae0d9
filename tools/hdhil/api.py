"""hdhil from Python: run a scenario, read a trace into arrays, evaluate a trace.

The command line is a thin layer over these functions; a script or a notebook can call
them directly (the README's "Python API" section runs this module's example)::

    import hdhil.api as hd

    result = hd.run("free-motion", duration_s=1.0, trace="run.blf")
    print(result.torque["rms_error_filtered"])        # the run's figures, as run --json
    arrays = hd.cycle_arrays(result)                  # per-cycle numpy arrays
    table = hd.read_trace("run.blf")                  # a trace as per-cycle arrays
    scores = hd.evaluate_trace("run.blf")             # the evaluation table, as a dict

Arrays are keyed by signal name with its unit (``T_meas_Nm``, ``velocity_radps``), as
``hdhil dump --csv`` writes them.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["cycle_arrays", "evaluate_trace", "read_trace", "run"]


def run(
    scenario: str | os.PathLike[str] = "free-motion",
    *,
    duration_s: float | None = None,
    seed: int | None = None,
    trace: str | os.PathLike[str] | None = None,
    overrides: dict[str, Any] | None = None,
    start_time: float | None = None,
    evaluate: bool = True,
) -> Any:
    """Run ``scenario`` (a shipped name or a TOML file) in lockstep on the simulated bus,
    as ``hdhil run`` does, and return its :class:`hdhil.rig.runner.RunResult`:
    ``result.as_dict()`` is what ``hdhil run --json`` prints, and with ``evaluate``
    :func:`cycle_arrays` gives the per-cycle signals.  ``overrides`` is a nested dict in
    the scenario file's layout merged over it (e.g. ``{"firmware": {"ripple": {"mode":
    "paper"}}}``); ``trace`` writes a trace (format from the extension) and its sidecar
    JSON; ``start_time`` (Unix seconds) pins the trace's dates."""
    from hdhil.hostsim.scenario import load_scenario
    from hdhil.rig.runner import run_lockstep

    sc = load_scenario(str(scenario), overrides)
    return run_lockstep(
        sc,
        duration_s,
        seed,
        Path(trace) if trace is not None else None,
        evaluate=evaluate,
        evaluate_skip_s=sc.evaluate_from_s,
        start_time=start_time,
        metadata={"scenario_source": str(scenario), "overrides": []},
    )


#: :class:`hdhil.rig.evaluate.Recording` columns and the names (with units) they get.
_RECORDING_NAMES = {
    "adc_torque": "ADC_torque_count",
    "adc_tacho": "ADC_tacho_count",
    "adc_current": "ADC_current_count",
    "encoder": "ENC_count",
    "T_meas_tele": "T_meas_Nm",
    "T_filtered_tele": "T_filtered_Nm",
    "velocity_tele": "velocity_radps",
    "T_true": "T_true_Nm",
    "T_ripple": "T_ripple_Nm",
    "theta_motor": "theta_motor_rad",
    "omega_motor": "omega_motor_radps",
    "theta_output": "theta_output_rad",
}


def cycle_arrays(result: Any) -> dict[str, np.ndarray]:
    """The per-cycle signals of a :func:`run` (samples in operation): ``time_s`` (the
    sample instants k·Ts), the drive's ADC counts and encoder, the controller's telemetry
    and the emulator's ground truth, as float arrays (NaN where a frame was missing).
    Needs a run with ``evaluate=True`` (it records every cycle)."""
    rec = getattr(result, "recording", None)
    if rec is None:
        raise ValueError("the run kept no per-cycle recording: run it with evaluate=True")
    out = {"time_s": np.arange(len(rec)) * rec.sample_period_s}
    for column, name in _RECORDING_NAMES.items():
        out[name] = rec.column(column).copy()
    return out


def read_trace(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """A trace (any format ``hdhil run``/``log`` write, a real drive's included) as
    per-cycle arrays: ``time_s`` (since the trace's first frame), ``sample`` and one
    array per signal that occurs (:func:`hdhil.can.cycles.read_cycles`)."""
    from hdhil.can.cycles import read_cycles
    from hdhil.canopen.mapping import trace_decoder

    return read_cycles(path, trace_decoder(Path(path)))


def evaluate_trace(
    path: str | os.PathLike[str], scenario: str | None = None, skip_s: float | None = None
) -> dict[str, Any]:
    """Score the firmware's filter and the alternatives against the ground truth in a
    trace, as ``hdhil evaluate --json`` does.  The scenario defaults to the one in the
    trace's sidecar JSON; ``skip_s`` to that scenario's ``evaluate_from_s`` (0 without
    one)."""
    from hdhil.commands.options import scenario_for_trace
    from hdhil.core.dataconf import from_dict
    from hdhil.firmware.config import FirmwareConfig
    from hdhil.rig.evaluate import evaluate, recording_from_trace

    sc, _source = scenario_for_trace(Path(path), scenario)
    fw = from_dict(FirmwareConfig, sc.firmware, "firmware") if sc else FirmwareConfig()
    if skip_s is None:
        skip_s = sc.evaluate_from_s if sc is not None else 0.0
    rec, damage = recording_from_trace(Path(path), fw.sample_period_s)
    if damage:
        raise ValueError(damage)
    return evaluate(rec, fw, skip_s)

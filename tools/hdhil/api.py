"""hdhil from Python: resolve and run a scenario, read a trace into arrays, score a trace.

The commands are thin layers over these functions; a script or a notebook calls them
directly (``docs/api.md``; the same names are importable from :mod:`hdhil`)::

    import hdhil

    request = hdhil.resolve("free-motion", duration_s=1.0, seed=3)
    result = hdhil.run(request, trace="run.blf")
    print(result.headline)                        # the figure `hdhil run` leads with
    arrays = hdhil.cycle_arrays(result)           # per-cycle numpy arrays
    table = hdhil.read_trace("run.blf")           # a trace as per-cycle arrays
    scores = hdhil.evaluate_trace("run.blf")      # the evaluation, as `evaluate --json`

Arguments are checked as the command line checks its options: a wrong type is a
``TypeError`` naming the argument, a value out of range or a bad scenario a
``ValueError`` (:class:`hdhil.core.errors.ConfigError`) naming the key or the argument.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["cycle_arrays", "evaluate_trace", "load_scenario", "read_trace", "resolve", "run"]


def _path_arg(value: Any, name: str, optional: bool = True) -> Path | None:
    if value is None and optional:
        return None
    if isinstance(value, bytes) or not isinstance(value, (str, os.PathLike)):
        raise TypeError(f"{name} must be a str or os.PathLike, got {type(value).__name__}")
    text = os.fspath(value)
    if not isinstance(text, str):
        raise TypeError(f"{name} must be a str path, got {type(text).__name__}")
    return Path(text)


def load_scenario(scenario: str | os.PathLike[str], overrides: dict[str, Any] | None = None) -> Any:
    """A scenario (a shipped name or a TOML file), typed (:class:`hdhil.rig.scenario.Scenario`)."""
    from hdhil.rig.scenario import load_scenario as load

    path = _path_arg(scenario, "scenario", optional=False)
    if overrides is not None and not isinstance(overrides, dict):
        raise TypeError(f"overrides must be a dict, got {type(overrides).__name__}")
    return load(str(path), overrides)


def resolve(
    scenario: Any = "free-motion",
    *,
    duration_s: float | None = None,
    seed: int | None = None,
    overrides: Sequence[str | os.PathLike[str] | dict[str, Any]] | dict[str, Any] | None = None,
    faults: Sequence[str] = (),
    calibration: str | os.PathLike[str] | None = None,
    mapping: str | None = None,
    drive_dcf: str | os.PathLike[str] | None = None,
    evaluate_from_s: float | None = None,
) -> Any:
    """The :class:`hdhil.rig.request.RunRequest` for ``scenario`` (a shipped name, a TOML
    file or a :class:`~hdhil.rig.scenario.Scenario`) with ``overrides`` (nested dicts in
    the scenario file's layout, or TOML files, in order), ``faults`` (``--fault`` flags:
    ``"control.loss_rate=0.05"``), a calibration file, a mapping (``"raw"``, ``"cst"``)
    or a DCF, duration, seed and evaluation start; as ``hdhil run`` resolves its options."""
    from hdhil.rig.request import resolve as resolve_request
    from hdhil.rig.scenario import Scenario

    if not isinstance(scenario, Scenario):
        scenario = _path_arg(scenario, "scenario", optional=False)
    for name, value in (("duration_s", duration_s), ("evaluate_from_s", evaluate_from_s)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
        raise TypeError(f"seed must be an int, got {type(seed).__name__}")
    if overrides is None:
        items: list[Any] = []
    elif isinstance(overrides, dict):
        items = [overrides]
    elif isinstance(overrides, (list, tuple)):
        items = [o if isinstance(o, dict) else _path_arg(o, "overrides") for o in overrides]
    else:
        raise TypeError(f"overrides must be a dict or a list, got {type(overrides).__name__}")
    if isinstance(faults, (str, bytes)) or not all(isinstance(f, str) for f in faults):
        raise TypeError("faults must be a list of 'KEY=VALUE' strings")
    if mapping is not None and not isinstance(mapping, str):
        raise TypeError(f"mapping must be a str, got {type(mapping).__name__}")
    return resolve_request(
        scenario,
        overrides=items,
        faults=list(faults),
        calibration=_path_arg(calibration, "calibration"),
        mapping=mapping,
        drive_dcf=_path_arg(drive_dcf, "drive_dcf"),
        duration_s=duration_s,
        seed=seed,
        evaluate_from_s=evaluate_from_s,
    )


def run(
    scenario: Any = "free-motion",
    *,
    trace: str | os.PathLike[str] | None = None,
    start_time: float | None = None,
    evaluate: bool = True,
    controller_factory: Any = None,
    drive_factories: Sequence[Any] | None = None,
    **settings: Any,
) -> Any:
    """Run a scenario in lockstep on the simulated bus, as ``hdhil run`` does, and return
    its :class:`hdhil.rig.result.RunResult` (``result.as_dict()`` is ``run --json``).

    ``scenario`` is a :class:`~hdhil.rig.request.RunRequest`, or anything :func:`resolve`
    takes, with its keyword ``settings`` (``duration_s``, ``seed``, ``overrides`` ...).
    ``trace`` writes a trace (format from the extension) and its sidecar JSON;
    ``start_time`` (Unix seconds) pins the trace's dates. ``controller_factory`` and
    ``drive_factories`` plug in your own nodes (:mod:`hdhil.rig.factories`)."""
    from hdhil.rig.request import RunRequest
    from hdhil.rig.runner import run_lockstep

    request = scenario if isinstance(scenario, RunRequest) else resolve(scenario, **settings)
    if isinstance(scenario, RunRequest) and settings:
        raise TypeError(f"run() of a RunRequest takes no {', '.join(sorted(settings))}")
    if not isinstance(evaluate, bool):
        raise TypeError(f"evaluate must be a bool, got {type(evaluate).__name__}")
    if start_time is not None and (
        isinstance(start_time, bool) or not isinstance(start_time, (int, float))
    ):
        raise TypeError(f"start_time must be a number, got {type(start_time).__name__}")
    return run_lockstep(
        request,
        trace=_path_arg(trace, "trace"),
        evaluate=evaluate,
        start_time=start_time,
        controller_factory=controller_factory,
        drive_factories=drive_factories,
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
    """The per-cycle signals of a :func:`run` (the firmware's samples): ``time_s`` (the
    sample instants k·Ts), the drive's ADC counts and encoder, the controller's telemetry
    and the emulator's ground truth, as float arrays (NaN where a frame was missing).
    Needs a run with ``evaluate=True`` (it records every cycle)."""
    rec = getattr(result, "recording", None)
    if rec is None:
        raise ValueError(
            "the run kept no per-cycle recording: run it with evaluate=True "
            "(and keep_recording=True)"
        )
    rec = rec.operation()  # the firmware's samples, as the run counts them
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
    trace, as ``hdhil evaluate --json`` does: with the run recorded in the trace's sidecar
    (or ``scenario``), from its evaluation start unless ``skip_s`` is given."""
    from hdhil.rig.trace_score import score_trace

    trace = _path_arg(path, "path", optional=False)
    assert trace is not None
    if skip_s is not None and (isinstance(skip_s, bool) or not isinstance(skip_s, (int, float))):
        raise TypeError(f"skip_s must be a number, got {type(skip_s).__name__}")
    scores, damage = score_trace(trace, scenario, skip_s)
    if damage:
        raise ValueError(damage)
    return scores

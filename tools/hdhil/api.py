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

Arguments are checked as the command line checks its options, with the same bounds
(a duration in (0, :data:`~hdhil.core.numbers.MAX_SECONDS`] s, a seed in [0, 2**63), a
start time from 1970 to the year 9999): a wrong type is a ``TypeError`` naming the
argument, a value out of range, a bad scenario or a bad file a ``ValueError``
(:class:`hdhil.core.errors.ConfigError`) naming the key, the file or the argument.
Names and paths are ``str`` or :class:`os.PathLike` (``bytes`` are refused with a
``TypeError``: a name is text, and a ``bytes`` path would be looked up as its repr).
"""

from __future__ import annotations

import functools
import numbers
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from hdhil.core.errors import ConfigError, UserError
from hdhil.core.numbers import MAX_SECONDS, MAX_UNIX_TIME, check_number

__all__ = ["cycle_arrays", "evaluate_trace", "load_scenario", "read_trace", "resolve", "run"]


_F = TypeVar("_F", bound=Callable[..., Any])


def _value_errors(func: _F) -> _F:
    """``func`` with the command line's input errors (:class:`UserError`: a missing,
    damaged or refused file) raised as ``ValueError`` (:class:`ConfigError`), the one
    exception type of a bad value."""

    @functools.wraps(func)
    def checked(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except UserError as exc:
            raise ConfigError(str(exc)) from exc

    return checked  # type: ignore[return-value]


def _number(
    value: Any,
    name: str,
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    integer: bool = False,
) -> Any:
    """``value`` checked as the command line checks a number option: ``TypeError`` if it
    is not an integer (``integer``) or a real number (``bool`` is neither; numpy's
    scalars are either), a :class:`ConfigError` naming ``name`` if it is not finite or
    not in range."""
    kind = numbers.Integral if integer else numbers.Real
    if isinstance(value, bool) or not isinstance(value, kind):
        what = "an int" if integer else "a number"
        raise TypeError(f"{name} must be {what}, got {type(value).__name__}")
    value = int(value) if integer or isinstance(value, numbers.Integral) else float(value)
    return check_number(value, name, lo=lo, hi=hi, lo_open=lo_open, integer=integer)


def _path_arg(value: Any, name: str, optional: bool = True) -> Path | None:
    if value is None and optional:
        return None
    if isinstance(value, bytes) or not isinstance(value, (str, os.PathLike)):
        raise TypeError(f"{name} must be a str or os.PathLike, got {type(value).__name__}")
    text = os.fspath(value)
    if not isinstance(text, str):
        raise TypeError(f"{name} must be a str path, got {type(text).__name__}")
    if "\0" in text:
        raise ConfigError(f"{name}: a path cannot hold a NUL character")
    return Path(text)


@_value_errors
def load_scenario(scenario: str | os.PathLike[str], overrides: dict[str, Any] | None = None) -> Any:
    """A scenario (a shipped name or a TOML file), typed (:class:`hdhil.rig.scenario.Scenario`),
    with ``overrides`` (a nested dict in the file's layout) merged in."""
    from hdhil.rig.scenario import load_scenario as load

    path = _path_arg(scenario, "scenario", optional=False)
    if overrides is not None and not isinstance(overrides, dict):
        raise TypeError(f"overrides must be a dict, got {type(overrides).__name__}")
    return load(str(path), overrides)


@_value_errors
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
    drive_node_id: int | None = None,
) -> Any:
    """The :class:`hdhil.rig.request.RunRequest` for ``scenario`` (a shipped name, a TOML
    file or a :class:`~hdhil.rig.scenario.Scenario`) with ``overrides`` (nested dicts in
    the scenario file's layout, or TOML files, in order), ``faults`` (``--fault`` flags:
    ``"control.loss_rate=0.05"``), a calibration file, a mapping (``"raw"``, ``"cst"``,
    ``"cst-sensor"``) or a DCF, duration, seed, evaluation start and the drive's CANopen
    node-ID (2..127; its PDO COB-IDs follow it); as ``hdhil run`` resolves its options."""
    from hdhil.rig.request import resolve as resolve_request
    from hdhil.rig.scenario import Scenario

    if not isinstance(scenario, Scenario):
        scenario = _path_arg(scenario, "scenario", optional=False)
    if duration_s is not None:
        duration_s = _number(duration_s, "duration_s", lo=0.0, lo_open=True, hi=MAX_SECONDS)
    if evaluate_from_s is not None:
        evaluate_from_s = _number(evaluate_from_s, "evaluate_from_s", lo=0.0, hi=MAX_SECONDS)
    if seed is not None:
        seed = _number(seed, "seed", lo=0, hi=2**63 - 1, integer=True)
    if overrides is None:
        items: list[Any] = []
    elif isinstance(overrides, dict):
        items = [overrides]
    elif isinstance(overrides, (list, tuple)):
        items = [o if isinstance(o, dict) else _path_arg(o, "overrides") for o in overrides]
    else:
        raise TypeError(f"overrides must be a dict or a list, got {type(overrides).__name__}")
    if isinstance(faults, (str, bytes)) or not isinstance(faults, (list, tuple)):
        raise TypeError(
            f"faults must be a list of 'KEY=VALUE' strings, got {type(faults).__name__}"
        )
    if not all(isinstance(f, str) for f in faults):
        raise TypeError("faults must be a list of 'KEY=VALUE' strings")
    if mapping is not None and not isinstance(mapping, str):
        raise TypeError(f"mapping must be a str, got {type(mapping).__name__}")
    layout = None
    if drive_node_id is not None:
        from hdhil.rig.factories import DriveSlot, RigLayout

        drive_node_id = _number(drive_node_id, "drive_node_id", lo=2, hi=127, integer=True)
        layout = RigLayout(1, (DriveSlot(int(drive_node_id)),))
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
        layout=layout,
    )


#: The keyword settings :func:`run` hands to :func:`resolve`.
_RESOLVE_SETTINGS = frozenset(
    {"duration_s", "seed", "overrides", "faults", "calibration", "mapping", "drive_dcf",
     "evaluate_from_s", "drive_node_id"}
)  # fmt: skip


@_value_errors
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
    ``start_time`` (Unix seconds, 0 to the year 9999) pins the trace's dates.
    ``controller_factory`` and ``drive_factories`` (callables) plug in your own nodes
    (:mod:`hdhil.rig.factories`).  A run whose plant goes non-finite ends with a
    ``result.verdict`` saying what and when, as ``hdhil run`` (exit code 1) does; a
    long run is interrupted with Ctrl-C (``KeyboardInterrupt``, once the trace is closed)."""
    from hdhil.rig.request import RunRequest
    from hdhil.rig.runner import run_lockstep

    unknown = sorted(set(settings) - _RESOLVE_SETTINGS)
    if unknown:
        raise TypeError(
            f"run() got an unexpected keyword argument {unknown[0]!r} (settings: "
            f"{', '.join(sorted(_RESOLVE_SETTINGS))})"
        )
    if isinstance(scenario, RunRequest) and settings:
        raise TypeError(f"run() of a RunRequest takes no {', '.join(sorted(settings))}")
    if not isinstance(evaluate, bool):
        raise TypeError(f"evaluate must be a bool, got {type(evaluate).__name__}")
    if start_time is not None:
        start_time = _number(start_time, "start_time", lo=0.0, hi=MAX_UNIX_TIME)
    if controller_factory is not None and not callable(controller_factory):
        raise TypeError(
            f"controller_factory must be callable, got {type(controller_factory).__name__}"
        )
    if drive_factories is not None:
        if not isinstance(drive_factories, (list, tuple)):
            raise TypeError(
                f"drive_factories must be a list of callables, got {type(drive_factories).__name__}"
            )
        for i, make in enumerate(drive_factories):
            if not callable(make):
                raise TypeError(f"drive_factories[{i}] must be callable, got {type(make).__name__}")
    trace_path = _path_arg(trace, "trace")
    request = scenario if isinstance(scenario, RunRequest) else resolve(scenario, **settings)
    return run_lockstep(
        request,
        trace=trace_path,
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
    from hdhil.rig.result import RunResult

    if not isinstance(result, RunResult):
        raise TypeError(f"result must be a RunResult (from run()), got {type(result).__name__}")
    rec = result.recording
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


@_value_errors
def read_trace(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """A trace (any format ``hdhil run``/``log`` write, a real drive's included) as
    per-cycle arrays: ``time_s`` (since the trace's first frame), ``sample`` and one
    array per signal that occurs (:func:`hdhil.can.cycles.read_cycles`)."""
    from hdhil.can.cycles import read_cycles
    from hdhil.canopen.mapping import trace_decoder

    trace = _path_arg(path, "path", optional=False)
    assert trace is not None
    return read_cycles(trace, trace_decoder(trace))


@_value_errors
def evaluate_trace(
    path: str | os.PathLike[str],
    scenario: str | os.PathLike[str] | None = None,
    skip_s: float | None = None,
) -> dict[str, Any]:
    """Score the firmware's filter and the alternatives against the ground truth in a
    trace, as ``hdhil evaluate --json`` does: with the run recorded in the trace's sidecar
    (or ``scenario``), from its evaluation start unless ``skip_s`` is given.  A rig's
    trace: its scores per joint (``joints``) and its worst joint (``worst_joint``), as
    its run's result has them."""
    from hdhil.rig.trace_score import score_trace

    trace = _path_arg(path, "path", optional=False)
    assert trace is not None
    named = _path_arg(scenario, "scenario")
    if skip_s is not None:
        skip_s = _number(skip_s, "skip_s", lo=0.0, hi=MAX_SECONDS)
    scores, damage = score_trace(trace, None if named is None else str(named), skip_s)
    if damage:
        raise ValueError(damage)
    return scores

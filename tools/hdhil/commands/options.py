"""Command-line options several commands share."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
from typing import Any

from hdhil.core.errors import UserError


def add_scenario_arguments(
    p: argparse.ArgumentParser,
    *,
    default: str | None = "free-motion",
    what: str = "",
    duration: float | None = None,
    duration_help: str | None = None,
) -> None:
    """The options every command that runs a scenario takes, in one group:
    ``--scenario --duration --seed --override --fault --fault-log --calibration`` and
    ``--mapping``/``--drive-dcf``; :func:`request_from_args` resolves them into a
    :class:`hdhil.rig.request.RunRequest`."""
    from hdhil.core.numbers import arg_int, arg_seconds
    from hdhil.dbc import MAPPINGS
    from hdhil.rig.scenario import list_scenarios

    g = p.add_argument_group("scenario" + (f" ({what})" if what else ""))
    g.add_argument(
        "--scenario",
        default=default,
        help=f"scenario name or TOML file (shipped: {', '.join(list_scenarios())}; "
        "default: %(default)s)",
    )
    g.add_argument(
        "--duration",
        type=arg_seconds(),
        default=duration,
        metavar="S",
        help=duration_help
        or "simulated seconds (default: "
        + ("the scenario's)" if duration is None else f"{duration:g})"),
    )
    g.add_argument(
        "--seed",
        type=arg_int(0, 2**63 - 1),
        default=None,
        help="noise seed of the plant (default: the scenario's)",
    )
    g.add_argument(
        "--override",
        type=Path,
        action="append",
        default=[],
        metavar="FILE",
        help="TOML file deep-merged into the scenario, e.g. [firmware.ripple] written by "
        "`hdhil tune --out` (repeatable, in order)",
    )
    g.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="inject a fault: a key of the scenario's [faults] table, dotted, and a TOML "
        "value, merged over the table (the flag wins; repeatable), e.g. "
        "control.loss_rate=0.05, control.jitter_us=200, sensors.tacho_spike_rate=0.001, "
        "seed=3, 'control.silence=[{node=2,start_s=1,duration_s=0.5}]'",
    )
    g.add_argument(
        "--fault-log",
        type=Path,
        default=None,
        metavar="FILE",
        help="write every injected fault as JSON lines",
    )
    g.add_argument(
        "--calibration",
        type=Path,
        default=None,
        metavar="FILE",
        help="calibration file written by `hdhil calibrate --out` (the firmware uses its gain)",
    )
    mapping = g.add_mutually_exclusive_group()
    mapping.add_argument(
        "--drive-dcf",
        metavar="FILE",
        default=None,
        help="configure the drive at boot from this DCF (its ParameterValue entries, by "
        "SDO); the controller's PDOs follow the drive's mapping",
    )
    mapping.add_argument(
        "--mapping",
        choices=list(MAPPINGS),
        default=None,
        help="the drive's PDO mapping by name: raw ([Taghirad97]'s ADC/DAC objects, the "
        "default), cst (CiA 402 cyclic synchronous torque: 0x6040 + 0x6071 in, 0x6077 + "
        "0x6064 out; the DCF shipped as drive-cst.dcf) or cst-sensor (cst with the "
        "joint-torque sensor 0x2102 beside 0x6077 + 0x6064, which the firmware filters; "
        "drive-cst-sensor.dcf)",
    )


def add_drive_node_id_argument(
    p: argparse.ArgumentParser, flag: str = "--drive-node-id", whose: str = "the drive's"
) -> None:
    """``--drive-node-id N`` (``hdhil run``, ``firmware``) or ``--node-id N``
    (``emulate``): the drive's CANopen node-ID, 1..127 and not the controller's (1);
    its PDO COB-IDs follow it (CiA 301 pre-defined connection set).  Read by
    :func:`request_from_args` into the request's layout."""
    from hdhil.core.numbers import arg_int

    p.add_argument(
        flag,
        dest="drive_node_id",
        type=arg_int(1, 127),
        default=None,
        metavar="N",
        help=f"{whose} CANopen node-ID, 2..127 (default: 2); its PDOs, heartbeat, EMCY and "
        "SDO identifiers follow it (CiA 301 pre-defined connection set)",
    )


def layout_from_args(args: argparse.Namespace) -> Any:
    """The rig layout ``--drive-node-id``/``--node-id`` names (the controller at node-ID
    1), or None without one; the controller's own node-ID is a one-line error."""
    from hdhil.rig.factories import DriveSlot, RigLayout

    node_id = getattr(args, "drive_node_id", None)
    if node_id is None:
        return None
    controller = RigLayout().controller_node_id
    if node_id == controller:
        raise UserError(
            f"drive node-ID {node_id} is the controller's: give the drive another (2..127)"
        )
    return RigLayout(controller, (DriveSlot(int(node_id)),))


def request_from_args(
    args: argparse.Namespace, *, run_duration: bool = True, **settings: Any
) -> Any:
    """The :class:`hdhil.rig.request.RunRequest` the scenario options name (plus
    ``settings``: ``evaluate_from_s``, ``actuation``, ``bitrate`` ...); a mistake is a
    one-line :class:`ConfigError` naming the file, key or flag. ``run_duration=False``:
    ``--duration`` is the command's own (wall seconds), the request keeps the scenario's."""
    from hdhil.rig.request import resolve

    return resolve(
        args.scenario,
        overrides=args.override,
        faults=args.fault,
        calibration=args.calibration,
        mapping=args.mapping,
        drive_dcf=args.drive_dcf,
        duration_s=args.duration if run_duration else None,
        seed=args.seed,
        layout=layout_from_args(args),
        **settings,
    )


def require_raw_sensor_frames(trace: Path, command: str) -> None:
    """A one-line error when ``trace`` was recorded in a mapping whose sensor frame is
    not the seed's raw ADC/encoder frame (its sidecar says so): ``command`` replays the
    raw channels."""
    from hdhil.canopen.mapping import raw_sensor_frames

    try:
        mapping = raw_sensor_frames(trace)
    except ValueError as exc:
        raise UserError(f"{trace}: {exc}") from None
    if mapping is not None:
        raise UserError(
            f"{trace} was recorded in the {mapping} mapping (its sidecar JSON): its sensor "
            f"frames carry no ADC channels, which hdhil {command} replays; hdhil evaluate, "
            "tune, plot and dump read it"
        )


# ------------------------------------------------------------------ CAN bus options

#: The bit rate of the control bus when neither the command line, the environment
#: (``CAN_BITRATE``) nor python-can's configuration file names one: the system's 1 Mbit/s.
DEFAULT_BITRATE = 1_000_000

#: Where to name an interface, for the error when none is named anywhere.
NO_INTERFACE = (
    "no CAN interface named: give --interface NAME (e.g. socketcan, pcan, kvaser, vector, "
    "virtual), set CAN_INTERFACE, or write 'interface = NAME' under [default] in "
    "python-can's configuration file (~/.canrc)"
)

_BUS_KEYS = ("interface", "channel", "bitrate", "fd", "data_bitrate", "timing", "can_filters")


def add_bus_options(
    p: argparse.ArgumentParser, *, prefix: str | None = None, title: str | None = None
) -> None:
    """python-can's own bus options (``can.cli.add_bus_arguments``): ``--interface``,
    ``--channel``, ``--bitrate``, ``--fd``, ``--data-bitrate``, ``--timing``, ``--filter``
    and ``--bus-kwargs`` (with ``prefix``: ``--PREFIX-interface`` ...).

    Options left out are not set at all, so python-can's order of precedence holds when
    the bus is opened: command line, then ``CAN_INTERFACE``/``CAN_CHANNEL``/``CAN_BITRATE``,
    then its configuration file.
    """
    import can.cli

    can.cli.add_bus_arguments(p, filter_arg=True, prefix=prefix, group_title=title)


def _given(args: argparse.Namespace, prefix: str | None) -> dict[str, Any]:
    """The bus options given on the command line (python-can's names, prefix removed)."""
    given = {}
    for key in (*_BUS_KEYS, "bus_kwargs"):
        name = f"{prefix}_{key}" if prefix else key
        if name in args:
            given[key] = getattr(args, name)
    return given


def bus_named(args: argparse.Namespace, prefix: str | None = None) -> bool:
    """Whether ``--[PREFIX-]interface`` was given on the command line."""
    return "interface" in _given(args, prefix)


def resolve_bus_config(
    args: argparse.Namespace, prefix: str | None = None, use_environment: bool = True
) -> dict[str, Any]:
    """The bus configuration python-can will use: the command line over the environment
    over the configuration file (``can.util.load_config``), with the bit rate defaulting
    to :data:`DEFAULT_BITRATE` only when none of them names one.  A missing or unknown
    interface is a :class:`UserError` saying how to name one."""
    import can

    given = _given(args, prefix)
    config = {k: v for k, v in given.items() if k != "bus_kwargs"}
    config.update(given.get("bus_kwargs", {}))
    try:
        if use_environment:
            resolved = dict(can.util.load_config(config=config))
        else:
            resolved = dict(config)
            resolved.setdefault("channel", None)
    except can.CanInterfaceNotImplementedError:
        raise UserError(NO_INTERFACE) from None
    except (ValueError, TypeError) as exc:
        raise UserError(f"bad CAN bus configuration: {exc}") from None
    interface = resolved.get("interface")
    if not interface:
        raise UserError(NO_INTERFACE)
    if interface not in can.VALID_INTERFACES:
        raise UserError(
            f"unknown CAN interface {interface!r}: "
            f"use one of {', '.join(sorted(can.VALID_INTERFACES))}"
        )
    if resolved.get("bitrate") is None and resolved.get("timing") is None:
        resolved["bitrate"] = DEFAULT_BITRATE
    return resolved


def open_bus(
    args: argparse.Namespace,
    what: str = "control bus",
    prefix: str | None = None,
    **extra: Any,
) -> tuple[Any, dict[str, Any]]:
    """Open the bus the options name through python-can's own factory
    (``can.cli.create_bus_from_namespace``); returns the bus and its resolved
    configuration (interface, channel, bit rate, ...).

    ``extra`` keyword arguments apply only where neither the command line, the
    environment nor the configuration file sets the same key.  Any failure is one line
    naming the bus and the interface.
    """
    import can
    import can.cli

    resolved = resolve_bus_config(args, prefix)
    defaults = {k: v for k, v in extra.items() if k not in resolved}
    if "bitrate" not in _given(args, prefix) and resolved.get("timing") is None:
        # python-can's own sources named no bit rate: the system's, not the interface's.
        defaults.setdefault("bitrate", resolved["bitrate"])
    if resolved["interface"] == "udp_multicast":
        defaults.pop("bitrate", None)  # the multicast "bus" has no bit rate
        defaults.setdefault("receive_own_messages", False)
    try:
        bus = can.cli.create_bus_from_namespace(args, prefix=prefix, **defaults)
    except argparse.ArgumentError as exc:
        cause = exc.__cause__ or exc
        text = " ".join(str(cause).split()) or type(cause).__name__
        raise UserError(
            f"cannot open the {what} ({resolved['interface']} {resolved.get('channel')}): {text}"
        ) from None
    return bus, resolved


#: ``(path, what)`` pairs for :func:`hdhil.core.files.check_not_inputs`.
Files = list[tuple[Any, str]]


def scenario_inputs(args: argparse.Namespace) -> Files:
    """The files the scenario options read (``--scenario`` as a file or a shipped name,
    ``--override``, ``--calibration``, ``--drive-dcf``, ``--config``), for
    :func:`check_outputs`; options a command lacks are skipped."""
    files: Files = []
    scenario = getattr(args, "scenario", None)
    if isinstance(scenario, str) and scenario:
        from hdhil.rig.scenario import scenario_path

        with contextlib.suppress(ValueError):  # an unknown name: the loading says so
            files.append((scenario_path(scenario), "scenario file"))
    files += [(p, "override file") for p in getattr(args, "override", None) or []]
    files.append((getattr(args, "calibration", None), "calibration file"))
    files.append((getattr(args, "drive_dcf", None), "DCF"))
    files.append((getattr(args, "config", None), "configuration file"))
    return files


def trace_inputs(trace: Any) -> Files:
    """A trace the command reads and its sidecar (which it reads too)."""
    from hdhil.can.traces.sidecar import metadata_path

    if trace is None or str(trace) in ("", "-"):
        return []
    return [(trace, "trace"), (metadata_path(Path(trace)), "trace's sidecar")]


def run_outputs(traces: list[Any], fault_log: Any = None) -> Files:
    """What a run writes: each trace and its sidecar, the fault log."""
    from hdhil.can.traces.sidecar import metadata_path

    files: Files = []
    for trace in traces:
        files += [(trace, "trace"), (metadata_path(Path(trace)), "sidecar")]
    return [*files, (fault_log, "fault log")]


def check_outputs(outputs: Files, inputs: Files) -> None:
    """Refuse in one line, before any work, an output that is one of the inputs or
    another output (:func:`hdhil.core.files.check_not_inputs`)."""
    from hdhil.core.files import check_not_inputs

    check_not_inputs(outputs, inputs)


def refuse_simbus(args: argparse.Namespace, command: str, truth: bool = False) -> None:
    """A one-line :class:`UserError` when the control bus (or with ``truth`` the truth bus)
    is ``simbus``: the simulated bus lives inside one process, so a node on it alone would
    wait for peers that can never join. Checked before anything opens or waits; a bus
    configuration that does not resolve is left to the command's own error."""
    for prefix in (None, "truth") if truth else (None,):
        if prefix is not None and not bus_named(args, prefix):
            continue
        try:
            interface = resolve_bus_config(args, prefix).get("interface")
        except UserError:
            continue
        if interface == "simbus":
            option = f"--{prefix}-interface" if prefix else "--interface"
            option = option if bus_named(args, prefix) else "the configured interface"
            raise UserError(
                f"{command}: {option} simbus is the simulated bus inside one process: use "
                "`hdhil run`, or udp_multicast or socketcan between processes"
            )

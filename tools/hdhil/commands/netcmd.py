"""One node per process, on any python-can interface: ``emulate``, ``firmware``, ``log``,
``sdo`` and ``nmt``.

``hdhil run`` puts everything in one process on the simulated bus; these commands split
the system the way a bench is split (drive emulator, firmware and logger in processes of
their own on a shared bus: SocketCAN, a real adapter, or ``udp_multicast``), so any node
can be replaced by real hardware. Here: the options, the buses they name, the signals
that stop a node and what is printed; the nodes themselves run in
:mod:`hdhil.rig.standalone`. ``docs/hardware.md`` has the recipes.
"""

from __future__ import annotations

import argparse
import struct
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from hdhil.can.traces.writer import check_trace_path
from hdhil.canopen.nmt import COMMAND_NAMES as NMT_COMMAND_NAMES
from hdhil.canopen.nmt import nmt_frame
from hdhil.commands.options import (
    add_bus_options,
    add_drive_node_id_argument,
    add_scenario_arguments,
    bus_named,
    check_outputs,
    layout_from_args,
    open_bus,
    refuse_simbus,
    request_from_args,
    resolve_bus_config,
    run_outputs,
    scenario_inputs,
)
from hdhil.core import jsonout
from hdhil.core.errors import UserError
from hdhil.core.numbers import arg_int, arg_seconds
from hdhil.core.signals import stop_on_signals
from hdhil.dbc import eds_path
from hdhil.dbc import node_ids as dbc_node_ids
from hdhil.rig.standalone import (
    StandaloneController,
    StandaloneDrive,
    controller_faults,
    drive_faults,
    log_metadata,
    record,
)
from hdhil.rig.verdict import format_verdict


def add_bus_arguments(p: argparse.ArgumentParser, truth: bool = False) -> None:
    """python-can's bus options for the control bus, and with ``truth`` the same options
    prefixed ``--truth-`` for the ground-truth channel (none: no truth)."""
    add_bus_options(p, title="control bus (python-can; else CAN_INTERFACE, CAN_CHANNEL, "
                    "CAN_BITRATE, then python-can's configuration file)")  # fmt: skip
    if truth:
        add_bus_options(p, prefix="truth", title="ground-truth bus (only if --truth-interface)")


def _control_bus(args: argparse.Namespace) -> can.BusABC:
    bus, _ = open_bus(args, "control bus")
    return bus


def _truth_bus(args: argparse.Namespace) -> can.BusABC | None:
    if not bus_named(args, "truth"):
        return None
    bus, _ = open_bus(args, "truth bus", prefix="truth")
    return bus


def _rig_buses(args: argparse.Namespace, command: str) -> dict[str, str | None] | None:
    """``--bus NAME[=CHANNEL]`` (repeatable for emulate) as ``{name: channel or None}``;
    None when no ``--bus`` was given."""
    given = getattr(args, "rig_bus", None)
    if not given:
        return None
    buses: dict[str, str | None] = {}
    for text in given if isinstance(given, list) else [given]:
        name, sep, channel = text.partition("=")
        if not name or (sep and not channel):
            raise UserError(f"bad --bus {text!r}: use NAME or NAME=CHANNEL, e.g. can0=239.0.0.1")
        if name in buses:
            raise UserError(f"--bus {name} is given twice")
        buses[name] = channel if sep else None
    if len(buses) > 1 and None in buses.values():
        raise UserError(f"hdhil {command} serves several buses on channels of their own: give "
                        "each its channel, --bus NAME=CHANNEL")  # fmt: skip
    return buses


def _rig_request(args: argparse.Namespace, command: str) -> Any:
    """The request the scenario options name; for a rig, served by bus (``--bus``,
    ``--node``), what the rig's process does not take is a one-line error."""
    request = request_from_args(args)
    buses = _rig_buses(args, command)
    joint = getattr(args, "rig_joint", None)
    if not request.scenario.is_rig:
        if buses is not None or joint is not None:
            raise UserError(f"--bus and --node take a scenario of several joints; "
                            f"{request.name} is a single joint")  # fmt: skip
        return request
    s = request.scenario
    if buses is None and joint is None:
        raise UserError(
            f"scenario {s.name} lays out {len(s.joints)} joints on bus(es) "
            f"{', '.join(n for n, _ in s.buses)}: give --bus NAME"
            + (" (or --node JOINT)" if command == "emulate" else "")
        )
    for flag, given in (("--fault", args.fault), ("--fault-log", args.fault_log),
                        ("--node-id/--drive-node-id", args.drive_node_id),
                        ("--truth-interface", bus_named(args, "truth"))):  # fmt: skip
        if given:
            raise UserError(f"hdhil {command} --bus: a rig of several joints runs without {flag}")
    return request


def _bus_opener(args: argparse.Namespace, channels: dict[str, str | None]) -> Any:
    """Opens a handle on a rig's bus by name: the bus options, with the bus's own channel
    where ``--bus NAME=CHANNEL`` gave one; a udp_multicast handle receives its own group
    only (:func:`hdhil.can.multicast.own_group_only`). Every handle opened is kept in the
    opener's ``opened``."""
    from hdhil.can.multicast import own_group_only

    opened: list[can.BusABC] = []

    def open_named(name: str) -> can.BusABC:
        ns = argparse.Namespace(**vars(args))
        channel = channels.get(name)
        if channel is not None:
            ns.channel = channel
        bus, _ = open_bus(ns, f"bus {name}")
        own_group_only(bus)
        opened.append(bus)
        return bus

    open_named.opened = opened  # type: ignore[attr-defined]
    return open_named


def _shutdown(buses: list[can.BusABC]) -> None:
    for bus in buses:
        bus.shutdown()


def _emulate_rig(args: argparse.Namespace, request: Any) -> int:
    from hdhil.rig.rigprocess import RigDrives, served_joints

    channels = _rig_buses(args, "emulate") or {}
    joints = served_joints(request, list(channels), args.rig_joint)
    if not channels:  # --node alone: its bus on the bus options' channel
        channels = {joints[0].bus: None}
    opener = _bus_opener(args, channels)
    try:
        drives = RigDrives(request, joints, opener)
        if drives.passive:
            print(f"hdhil: emulate: the arm of {request.name} couples joints "
                  f"{', '.join(drives.passive)} that this process does not serve: they stay in "
                  "the arm with their amplifiers off (serve every bus of the arm in one "
                  "process: --bus NAME=CHANNEL for each)", file=sys.stderr)  # fmt: skip
        with stop_on_signals() as stop:
            drives.serve(stop.is_set, args.duration)
        summary = drives.summary()
        print(jsonout.dumps(summary))
    finally:
        _shutdown(opener.opened)
    return _verdict_exit("emulate", summary)


def _firmware_rig(args: argparse.Namespace, request: Any) -> int:
    from hdhil.rig.realtime import RealtimeConfig
    from hdhil.rig.rigprocess import RigController

    channels = _rig_buses(args, "firmware") or {}
    if len(channels) != 1:
        raise UserError("hdhil firmware runs the controller of one bus: give one --bus NAME")
    (bus,) = channels
    opener = _bus_opener(args, channels)
    try:
        pacing = RealtimeConfig(spin_us=args.spin_us, floor_s=args.floor_s)
        ctrl = RigController(request, bus, opener, args.boot_timeout, pacing)
        return _serve_controller(ctrl, args, lambda: ctrl.recovery)
    finally:
        _shutdown(opener.opened)


def run_emulate(args: argparse.Namespace) -> int:
    refuse_simbus(args, "emulate", truth=True)
    request = _rig_request(args, "emulate")
    if request.scenario.is_rig:
        return _emulate_rig(args, request)
    check_outputs(run_outputs([], args.fault_log), scenario_inputs(args))
    injector = drive_faults(request, args.fault, args.fault_log, truth=bus_named(args, "truth"))
    bus = truth = None
    try:
        bus = _control_bus(args)
        truth = _truth_bus(args)
        drive = StandaloneDrive(request, bus, truth, injector)
        with stop_on_signals() as stop:  # Ctrl-C or SIGTERM: how a server ends, not an error
            drive.serve(stop.is_set, args.duration)
        summary = drive.summary()
        print(jsonout.dumps(summary))
    finally:
        for b in (bus, truth):
            if b is not None:
                b.shutdown()
        injector.log.close()
    return _verdict_exit("emulate", summary)  # 0 also after a stop by Ctrl-C or SIGTERM


def run_firmware(args: argparse.Namespace) -> int:
    refuse_simbus(args, "firmware")
    request = _rig_request(args, "firmware")
    if request.scenario.is_rig:
        return _firmware_rig(args, request)
    if args.floor_s or args.spin_us is not None:
        raise UserError("--floor-s and --spin-us take a rig's controller (--bus)")
    check_outputs(run_outputs([], args.fault_log), scenario_inputs(args))
    injector = controller_faults(request, args.fault, args.fault_log)
    bus = None
    try:
        bus = _control_bus(args)
        ctrl = StandaloneController(request, bus, injector, args.boot_timeout)
        return _serve_controller(
            ctrl, args, lambda: [] if ctrl.recovery is None else [ctrl.recovery]
        )
    finally:
        if bus is not None:
            bus.shutdown()
        injector.log.close()


def _serve_controller(
    ctrl: Any, args: argparse.Namespace, recovery: Callable[[], list[str]]
) -> int:
    """Boot ``ctrl`` (a single joint's or a rig bus's controller), run it until its
    duration, a verdict or Ctrl-C/SIGTERM, print its JSON summary; the exit code. A boot
    that fails (no boot-up, no SDO answer) is a stop, told as a verdict; ``recovery``
    gives the lines of what the boot recovered from."""
    with stop_on_signals() as stop:
        failed = ctrl.boot(stop.is_set)
        for line in recovery():
            print(f"hdhil: firmware: {line}", file=sys.stderr)
        if failed is not None:
            print(jsonout.dumps(failed))
            return _verdict_exit("firmware", failed)
        ctrl.run(stop.is_set, realtime=not args.lockstep)
    summary = ctrl.summary(stopped=stop.is_set())
    print(jsonout.dumps(summary))
    if stop.is_set():
        return 130
    return _verdict_exit("firmware", summary)


def _verdict_exit(command: str, summary: dict[str, Any]) -> int:
    """The exit code of a node's summary: 1 with its verdict's line on stderr, else 0."""
    verdict = summary.get("verdict")
    if verdict is None:
        return 0
    print(f"hdhil: {command} {format_verdict(verdict)}", file=sys.stderr)
    return 1


def run_log(args: argparse.Namespace) -> int:
    refuse_simbus(args, "log", truth=True)
    try:
        check_trace_path(Path(args.trace))  # a bad name or format: before any bus opens
    except ValueError as exc:
        raise UserError(str(exc)) from None
    check_outputs(run_outputs([args.trace]), scenario_inputs(args))
    if args.scenario is None and (
        args.override
        or args.fault
        or args.calibration
        or args.mapping
        or args.drive_dcf
        or args.seed is not None
    ):
        raise UserError("--override, --fault, --calibration, --mapping and --seed describe "
                        "the run being recorded: give its --scenario too")  # fmt: skip
    control_config = resolve_bus_config(args)
    request = None if args.scenario is None else request_from_args(args, run_duration=False)
    metadata = log_metadata(control_config, request)
    layout = layout_from_args(args)  # --drive-node-id: the trace decodes at that node-ID
    if request is None and layout is not None:
        metadata["layout"] = {"controller_node_id": layout.controller_node_id,
                              "drives": [{"node_id": d.node_id, "bus": d.bus}
                                         for d in layout.drives]}  # fmt: skip
    control = _control_bus(args)
    truth = None
    try:
        truth = _truth_bus(args)
        with stop_on_signals() as stop:  # from here on, Ctrl-C ends the log cleanly
            recording = record(Path(args.trace), control, truth, metadata, stop.is_set,
                               args.duration)  # fmt: skip
        print(jsonout.dumps({"trace": args.trace, "frames": recording.frames}))
    finally:
        for bus in (control, truth):
            if bus is not None:
                bus.shutdown()
    return 0  # also after Ctrl-C or SIGTERM: the trace is complete (as can.logger)


def _parse_index(text: str) -> tuple[int, int]:
    try:
        index, _, sub = text.partition(":")
        address = int(index, 0), int(sub, 0) if sub else 0
    except ValueError:
        raise UserError(f"bad object address {text!r}: use INDEX[:SUB], e.g. 0x2100:2") from None
    if not (0 <= address[0] <= 0xFFFF and 0 <= address[1] <= 0xFF):
        raise UserError(
            f"bad object address {text!r}: the index is 16 bits (0..0xFFFF), the sub-index "
            "8 bits (0..0xFF)"
        )
    return address


def run_sdo(args: argparse.Namespace) -> int:
    import canopen

    from hdhil.canopen.sdo import ABORT_TIMEOUT
    from hdhil.canopen.services import SdoError, sdo_read, sdo_write

    refuse_simbus(args, "sdo")
    index, sub = _parse_index(args.address)
    node_eds = {n: name.lower() for name, n in dbc_node_ids("control").items()}.get(args.node)
    od = canopen.import_od(str(eds_path(node_eds)), args.node) if node_eds else None
    network = canopen.Network()
    network.bus = _control_bus(args)
    network.notifier = can.Notifier(network.bus, network.listeners, 0.1)
    try:
        if args.action == "read":
            value = sdo_read(network, args.node, index, sub, od=od, timeout=args.timeout)
            print(value)
        else:
            if args.value is None:
                raise UserError("sdo write needs a VALUE")
            sdo_write(network, args.node, index, sub, _parse_value(args.value), od=od,
                      timeout=args.timeout)  # fmt: skip
            print("ok")
    except SdoError as exc:
        if exc.code == ABORT_TIMEOUT:  # the node did not answer: the system, not the input
            print(f"hdhil: sdo {args.action} 0x{index:04X}:{sub:02X}: node {args.node} did "
                  f"not answer within {args.timeout:g} s (SDO abort 0x{exc.code:08X}: "
                  f"{exc.text})", file=sys.stderr)  # fmt: skip
            return 1
        raise UserError(f"SDO abort 0x{exc.code:08X}: {exc.text}") from None
    except (TypeError, ValueError, KeyError, ArithmeticError, struct.error) as exc:
        raise UserError(f"sdo {args.action} 0x{index:04X}:{sub:02X} on node {args.node}: "
                        f"{exc}") from None  # fmt: skip
    finally:
        network.notifier.stop()
        network.bus.shutdown()
    return 0


def _parse_value(text: str) -> int | float:
    try:
        return int(text, 0)
    except ValueError:
        try:
            return float(text)
        except ValueError:
            raise UserError(f"bad value {text!r}: a number is expected") from None


def run_nmt(args: argparse.Namespace) -> int:
    refuse_simbus(args, "nmt")
    bus = _control_bus(args)
    try:
        bus.send(nmt_frame(NMT_COMMAND_NAMES[args.action], args.node), timeout=args.timeout)
    except can.CanError as exc:  # not sent: no node acknowledged it (the system, not the input)
        text = " ".join(str(exc).split()) or type(exc).__name__
        print(f"hdhil: nmt {args.action} node {args.node}: the command was not sent within "
              f"{args.timeout:g} s, no node answered on the bus ({text})",
              file=sys.stderr)  # fmt: skip
        return 1
    finally:
        bus.shutdown()
    print("ok")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("emulate", help="run the drive emulator alone on a CAN interface")
    add_bus_arguments(p, truth=True)
    add_scenario_arguments(
        p,
        what="its [plant] and [faults]: sensors.*, and control.*/truth.* on the drive's own frames",
        duration_help="wall seconds to serve (default: until Ctrl-C / SIGTERM)",
    )
    add_drive_node_id_argument(p, "--node-id", "the emulated drive's")
    rig = p.add_argument_group("a rig of several joints (docs/several-joints.md)")
    rig.add_argument(
        "--bus",
        dest="rig_bus",
        action="append",
        metavar="NAME[=CHANNEL]",
        help="serve the drives of the scenario's bus NAME, on CHANNEL (default: --channel); "
        "repeat for several buses of one arm, each on its own channel",
    )
    rig.add_argument(
        "--node",
        dest="rig_joint",
        metavar="JOINT",
        help="serve the drive of joint JOINT alone (on its bus's channel)",
    )
    p.set_defaults(func=run_emulate)

    p = sub.add_parser("firmware", help="run the controller firmware alone on a CAN interface")
    add_bus_arguments(p)
    add_scenario_arguments(
        p,
        what="its [firmware], and [faults] control.* on the controller's own frames",
        duration_help="simulated seconds of operation (default: the scenario's)",
    )
    add_drive_node_id_argument(p, whose="the drive's (an emulated or a real one)")
    pacing = p.add_mutually_exclusive_group()
    pacing.add_argument(
        "--lockstep",
        action="store_true",
        help="network lockstep: the next SYNC as soon as the drive answered, faster than "
        "the sample period the filters, differentiator and LQG assume; for tests and "
        "emulated drives only, NEVER with a motor (default: real time at the sample period)",
    )
    pacing.add_argument(
        "--realtime",
        action="store_true",
        help="no effect, accepted for older scripts: SYNC is paced at the sample period on "
        "the monotonic clock by default",
    )
    p.add_argument(
        "--boot-timeout",
        type=arg_seconds(hi=3600.0),
        default=2.0,
        help="seconds to wait for the drive's boot-up",
    )
    rig = p.add_argument_group("a rig of several joints (docs/several-joints.md)")
    rig.add_argument(
        "--bus",
        dest="rig_bus",
        metavar="NAME[=CHANNEL]",
        help="run the controller nodes of the scenario's bus NAME, on CHANNEL (default: --channel)",
    )
    rig.add_argument(
        "--floor-s",
        type=arg_seconds(lo_open=False, hi=3600.0),
        default=0.0,
        help="with --bus, in real time: after the run, measure the machine floor (the bare "
        "sleep+spin loop) for this many seconds, reported beside the run's SYNC jitter",
    )
    rig.add_argument(
        "--spin-us",
        type=arg_seconds(lo_open=False, hi=1e6),
        default=None,
        help="with --bus, in real time: the spin window before each SYNC in µs (default: "
        "60%% of the period within the RT budget); smaller leaves the CPU to the other "
        "processes of the rig",
    )
    p.set_defaults(func=run_firmware)

    p = sub.add_parser("log", help="record a CAN interface (and the truth bus) to a trace")
    add_bus_arguments(p, truth=True)
    p.add_argument("trace", help="trace file (.blf .asc .log .csv .trc)")
    add_scenario_arguments(
        p,
        default=None,
        what="of the run being recorded, written into the trace's sidecar so that "
        "`hdhil evaluate` scores the trace with its settings",
        duration_help="wall seconds to record (default: until Ctrl-C / SIGTERM)",
    )
    add_drive_node_id_argument(p, whose="the recorded drive's")
    p.set_defaults(func=run_log)

    p = sub.add_parser("sdo", help="read or write a node's object dictionary (SDO client)")
    add_bus_arguments(p)
    p.add_argument("action", choices=("read", "write"))
    p.add_argument("node", type=arg_int(1, 127), help="node-ID (1 controller, 2 drive)")
    p.add_argument("address", help="INDEX[:SUB], e.g. 0x2100:2")
    p.add_argument("value", nargs="?", default=None)
    p.add_argument("--timeout", type=arg_seconds(hi=3600.0), default=1.0)
    p.set_defaults(func=run_sdo)

    p = sub.add_parser("nmt", help="send an NMT command")
    add_bus_arguments(p)
    p.add_argument("action", choices=tuple(NMT_COMMAND_NAMES))
    p.add_argument("node", type=arg_int(0, 127), help="node-ID (0 = all nodes)")
    p.add_argument(
        "--timeout",
        type=arg_seconds(hi=3600.0),
        default=1.0,
        help="seconds for the command to leave (no node acknowledging it on the bus: exit 1)",
    )
    p.set_defaults(func=run_nmt)

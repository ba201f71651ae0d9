"""One node per process, on any python-can interface: ``emulate``, ``firmware``, ``log``,
``sdo`` and ``nmt``.

``hdhil run`` puts everything in one process on the simulated bus; these commands split
the system the way a bench is split (drive emulator, firmware and logger in processes of
their own on a shared bus: SocketCAN, a real adapter, or ``udp_multicast``), so any node
can be replaced by real hardware. Every node runs in the one node loop
(:mod:`hdhil.rig.loop`). ``firmware`` paces SYNC in network lockstep (SYNC k+1 once the
drive's cycle k is answered, or after the loop's cycle timeout) or, with ``--realtime``,
by the pacer of ``hdhil run --realtime``. Each process injects the faults that arise in
it (``emulate``: sensor faults and its own transmissions; ``firmware``: its own
transmissions), from the request's ``[faults]`` table. ``docs/hardware.md`` has the
recipes.
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import can

from hdhil.can.faults import FaultLog, FaultyTransmitBus, check_node_transmit_faults
from hdhil.can.traces.tap import BusTap, FrameCounter
from hdhil.can.traces.writer import WriterError, WriterProcess, check_trace_path
from hdhil.canopen.nmt import COMMAND_NAMES as NMT_COMMAND_NAMES
from hdhil.canopen.nmt import nmt_frame
from hdhil.commands.options import (
    add_bus_options,
    add_scenario_arguments,
    bus_named,
    open_bus,
    request_from_args,
    resolve_bus_config,
)
from hdhil.core.dataconf import ConfigError
from hdhil.core.errors import UserError
from hdhil.core.numbers import arg_int, arg_seconds
from hdhil.core.signals import stop_on_signals
from hdhil.dbc import CHANNEL_NUMBER, eds_path
from hdhil.dbc import node_ids as dbc_node_ids
from hdhil.firmware.controller import ControllerNode
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant
from hdhil.rig.faults import FaultConfig, FaultInjector, parse_fault_flags
from hdhil.rig.loop import NodeLoop, controller_expects_answer, serve
from hdhil.rig.realtime import RealtimeLoop
from hdhil.rig.sidecar import run_metadata
from hdhil.rig.verdict import (
    dcf_refused,
    drive_verdict,
    format_verdict,
    startup_verdict,
    stop_verdict,
)

#: The logger's pause when no frame is waiting (s): short against a 1 ms cycle.
IDLE_SLEEP_S = 0.0002
#: The controller's node-ID (control.dbc's node CONTROLLER).
CONTROLLER_NODE_ID = dbc_node_ids("control")["CONTROLLER"]
#: SYNC cycles allowed for walking the drive back to "stopped" after the run.
MAX_STOP_CYCLES = 2000


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


def _fault_injector(
    args: argparse.Namespace, faults: FaultConfig | None, stream: str, acts_on: tuple[str, ...]
) -> FaultInjector:
    """The process's faults: ``faults`` (the request's table, ``--fault`` flags merged);
    flags for parts that do not act in this process are refused."""
    flagged = sorted(set(parse_fault_flags(args.fault)) - {"seed", *acts_on})
    if flagged:
        raise ConfigError(
            f"--fault {flagged[0]}.*: these faults do not act in hdhil {args.command} "
            f"(it injects {', '.join(acts_on)})"
        )
    config = faults or FaultConfig()
    for role in ("control", "truth"):
        if role in acts_on:
            check_node_transmit_faults(config, role)  # type: ignore[arg-type]
    try:
        log = FaultLog(args.fault_log, keep=False)
    except OSError as exc:
        raise ConfigError(f"cannot write the fault log {args.fault_log}: {exc}") from None
    return FaultInjector(config, log, stream=stream)


def _with_faults(
    bus: can.BusABC | None,
    injector: FaultInjector,
    role: Literal["control", "truth"],
    node_id: int,
) -> Any:
    """``bus``, or its :class:`~hdhil.can.faults.FaultyTransmitBus` when the own frames of
    node ``node_id`` on channel ``role`` are to be faulted (a silence of that node stops
    all of them)."""
    hook = injector.channel(role)
    if bus is None or hook is None:
        return bus
    return FaultyTransmitBus(bus, hook, node_id=node_id)


def run_emulate(args: argparse.Namespace) -> int:
    request = request_from_args(args)
    scenario, fw, seed = request.scenario, request.firmware, request.seed
    acts_on = (
        ("sensors", "control", "truth") if bus_named(args, "truth") else ("sensors", "control")
    )
    injector = _fault_injector(args, scenario.faults, "drive", acts_on)
    bus = truth = None
    try:
        bus = _control_bus(args)
        truth = _truth_bus(args)
        drive_config = DriveConfig(sample_period_s=fw.sample_period_s)
        node_bus = _with_faults(bus, injector, "control", drive_config.node_id)
        node_truth = _with_faults(truth, injector, "truth", drive_config.node_id)
        drive = DriveNode(
            node_bus,
            Plant(scenario.plant, seed, faults=injector.sensors()),
            drive_config,
            truth_bus=node_truth,
            faults=injector,
        )
        t_end = time.monotonic() + args.duration if args.duration else float("inf")
        with stop_on_signals() as stop:
            drive.boot(time.monotonic())
            serve(drive, stop.is_set, lambda: time.monotonic() >= t_end)
        stopped_by_signal = stop.is_set()
        for b in (node_bus, node_truth):
            if isinstance(b, FaultyTransmitBus):
                b.flush()
        d = drive.diagnostics
        verdict = drive_verdict(drive)
        summary = {"node": "drive", "syncs": d.syncs, "commands": d.commands,
                   "nmt_state": str(drive.nmt_state), "drive_state": str(drive.drive_state),
                   "plant_time_s": drive.plant.time, "faults": injector.summary()}  # fmt: skip
        if verdict is not None:
            summary["verdict"] = verdict
        print(json.dumps(summary))
    finally:
        for b in (bus, truth):
            if b is not None:
                b.shutdown()
        injector.log.close()
    if stopped_by_signal:
        return 130
    if verdict is not None:
        print(f"hdhil: emulate {format_verdict(verdict)}", file=sys.stderr)
        return 1
    return 0


def run_firmware(args: argparse.Namespace) -> int:
    request = request_from_args(args)
    scenario, fw = request.scenario, request.firmware
    Ts = fw.sample_period_s
    cycles = request.cycles
    injector = _fault_injector(args, scenario.faults, "controller", ("control",))
    bus = None
    try:
        bus = _control_bus(args)
        node_bus = _with_faults(bus, injector, "control", CONTROLLER_NODE_ID)
        try:
            ctrl = ControllerNode(
                node_bus,
                fw,
                node_id=CONTROLLER_NODE_ID,
                boot_timeout_s=args.boot_timeout,
                drive_dcf=request.mapping.dcf,
            )
        except ValueError as exc:
            raise UserError(str(exc)) from None
        pacer: RealtimeLoop | None = None
        with stop_on_signals() as stop:
            ctrl.boot(time.monotonic())
            # Wait for the drive's boot-up (or the timeout) while producing heartbeats.
            serve(ctrl, stop.is_set, lambda: ctrl.phase != "wait-boot" or bool(ctrl.boot_error))
            if dcf_refused(ctrl):  # the user's DCF has to change: an input error
                raise UserError(ctrl.boot_error)
            if ctrl.boot_error and not stop.is_set():
                # No boot-up (or no SDO answer) from the drive: a stop, told as a verdict.
                return _boot_failed(ctrl, injector, cycles)
            pacer = RealtimeLoop(Ts) if args.realtime else None
            loop = NodeLoop(
                [ctrl],
                producer=ctrl,
                answers=lambda: ctrl.diagnostics.commands_sent,
                expects_answer=lambda: controller_expects_answer(ctrl),
                period_s=Ts,
                pacer=pacer,
            )
            if pacer is not None:
                pacer.instrument(ctrl)
                pacer.enter()
                pacer.start()
            try:
                done = _sync_cycles(loop, ctrl, stop.is_set, cycles, pacer)
                if pacer is not None:
                    pacer.end_recording()
                ctrl.request_stop()  # walk the drive back to "stopped"
                for _ in range(MAX_STOP_CYCLES):
                    if ctrl.phase in ("stopped", "safe"):
                        break
                    loop.cycle()
            finally:
                if pacer is not None:
                    pacer.exit()
        if isinstance(node_bus, FaultyTransmitBus):
            node_bus.flush()
        d = ctrl.diagnostics
        verdict = None if stop.is_set() else stop_verdict(ctrl, cycles, done, Ts)
        summary = {"node": "controller", "operational_cycles": done,
                   "syncs_sent": d.syncs_sent, "sensor_frames": d.sensor_frames,
                   "phase": str(ctrl.phase.value), "mapping": ctrl.sensor_mapping,
                   "faults": injector.summary()}  # fmt: skip
        if ctrl.rated_torque_Nm is not None:
            summary["rated_torque_Nm"] = ctrl.rated_torque_Nm
        if ctrl.phase == "safe":
            summary["safe_reason"] = d.safe_reason
        if pacer is not None:  # the real-time statistics, as in hdhil run --json
            summary["realtime"] = pacer.result()
        if verdict is not None:
            summary["verdict"] = verdict
        print(json.dumps(summary))
        if stop.is_set():
            return 130
        if verdict is not None:
            print(f"hdhil: firmware {format_verdict(verdict)}", file=sys.stderr)
            return 1
        return 0
    finally:
        if bus is not None:
            bus.shutdown()
        injector.log.close()


def _boot_failed(ctrl: ControllerNode, injector: FaultInjector, cycles: int) -> int:
    """``hdhil firmware``'s verdict when the drive never booted or answered: the JSON
    summary with it, the one-line reason on stderr, exit code 1."""
    d = ctrl.diagnostics
    node = ctrl.drive_node_id if hasattr(ctrl, "drive_node_id") else None
    verdict = startup_verdict(ctrl, str(ctrl.boot_error), node, 0, cycles,
                              ctrl.config.sample_period_s)  # fmt: skip
    summary = {"node": "controller", "operational_cycles": 0, "syncs_sent": d.syncs_sent,
               "sensor_frames": d.sensor_frames, "phase": str(ctrl.phase.value),
               "safe_reason": d.safe_reason, "faults": injector.summary(),
               "verdict": verdict}  # fmt: skip
    print(json.dumps(summary))
    print(f"hdhil: firmware {format_verdict(verdict)}", file=sys.stderr)
    return 1


def _sync_cycles(
    loop: NodeLoop,
    ctrl: ControllerNode,
    stop: Callable[[], bool],
    cycles: int,
    pacer: RealtimeLoop | None = None,
) -> int:
    """Run the loop's SYNC cycles until ``cycles`` of them found the controller
    operational, it went safe, or a stop; return the operational cycles.  The pacer's
    statistics start with operation, as in ``hdhil run --realtime``."""
    operational = 0
    while operational < cycles and not stop():
        if ctrl.phase == "safe":
            break
        loop.cycle()
        if ctrl.phase == "operational":
            if pacer is not None and not pacer.recording:
                pacer.begin_recording()
            operational += 1
    return operational


def _log_metadata(args: argparse.Namespace, control: dict[str, Any]) -> dict[str, Any]:
    """The sidecar of a logged trace: what was recorded from where and, with
    ``--scenario``, the run's request (so ``evaluate`` scores it with its settings)."""
    meta: dict[str, Any] = {
        "recorded_by": "hdhil log",
        "interface": control.get("interface"),
        "channel": control.get("channel"),
        "bitrate": control.get("bitrate"),
        "channels": dict(CHANNEL_NUMBER),
        "time_offset_s": 0.0,
    }
    if args.scenario is not None:
        request = request_from_args(args, run_duration=False)
        meta.update(
            scenario=request.name,
            seed=request.seed,
            sample_period_s=request.sample_period_s,
            **run_metadata(request),
        )
    return meta


def run_log(args: argparse.Namespace) -> int:
    try:
        check_trace_path(Path(args.trace))  # a bad name or format: before any bus opens
    except ValueError as exc:
        raise UserError(str(exc)) from None
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
    metadata = _log_metadata(args, control_config)
    control = _control_bus(args)
    buses = {CHANNEL_NUMBER["control"]: control}
    try:
        truth = _truth_bus(args)
        if truth is not None:
            buses[CHANNEL_NUMBER["truth"]] = truth
        counter = FrameCounter()
        with stop_on_signals() as stop:  # from here on, Ctrl-C ends the log cleanly
            try:
                # written to a temporary, renamed into place when complete (also on Ctrl-C)
                writer = WriterProcess(Path(args.trace), metadata=metadata)
            except ValueError as exc:
                raise UserError(str(exc)) from None
            tap = BusTap(buses, [writer, counter])
            t_end = time.monotonic() + args.duration if args.duration else float("inf")
            try:
                while not stop.is_set() and time.monotonic() < t_end:
                    if not tap.poll():
                        time.sleep(IDLE_SLEEP_S)
                stopped_by_signal = stop.is_set()
                tap.poll()
            finally:
                try:
                    tap.stop()  # flushes and closes the trace, renames it into place
                except WriterError as exc:
                    raise UserError(str(exc)) from None
        print(json.dumps({"trace": args.trace, "frames": counter.total}))
    finally:
        for bus in buses.values():
            bus.shutdown()
    return 130 if stopped_by_signal else 0


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

    from hdhil.canopen.services import SdoError, sdo_read, sdo_write

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
    bus = _control_bus(args)
    try:
        bus.send(nmt_frame(NMT_COMMAND_NAMES[args.action], args.node))
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
    p.set_defaults(func=run_emulate)

    p = sub.add_parser("firmware", help="run the controller firmware alone on a CAN interface")
    add_bus_arguments(p)
    add_scenario_arguments(
        p,
        what="its [firmware], and [faults] control.* on the controller's own frames",
        duration_help="simulated seconds of operation (default: the scenario's)",
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="pace SYNC at the sample period on the monotonic clock",
    )
    p.add_argument(
        "--boot-timeout",
        type=arg_seconds(hi=3600.0),
        default=2.0,
        help="seconds to wait for the drive's boot-up",
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
    p.set_defaults(func=run_nmt)

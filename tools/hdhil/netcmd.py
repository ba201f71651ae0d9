"""One node per process, on any python-can interface: ``emulate``, ``firmware``, ``log``,
``sdo`` and ``nmt``.

``hdhil run`` puts everything in one process on the simulated bus.  These commands split
the system the way a bench is split: the drive emulator in one process, the firmware in
another, a logger in a third, all on a shared bus, e.g. SocketCAN ``vcan0``, a real
adapter, or python-can's ``udp_multicast`` (what the tests use, inside a private network
namespace).  Any node can be replaced by real hardware: ``hdhil firmware`` against a real
drive, ``hdhil emulate`` against real firmware.

Pacing of ``hdhil firmware`` (the SYNC producer):

- default, *network lockstep*: SYNC k+1 goes out as soon as the controller has answered
  the drive's sensor frame of cycle k (deterministic order, faster than real time);
- ``--realtime``: SYNC at the sample period on the monotonic clock (sleep, then spin to
  the deadline).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from firmware.config import FirmwareConfig
from firmware.controller import ControllerNode
from hdhil.dataconf import ConfigError, from_dict
from hdhil.dbc import CHANNEL_NUMBER, eds_path
from hdhil.run import stop_on_signals
from hdhil.trace import BusTap, FrameCounter, open_writer
from hostsim.drive import DriveConfig, DriveNode
from hostsim.plant import Plant
from hostsim.scenario import load_scenario

#: How long a node blocks in one receive before it runs its timers again (s).
RECV_SLICE_S = 0.002
#: The logger's pause when no frame is waiting (s): short against a 1 ms cycle.
IDLE_SLEEP_S = 0.0002
#: A SYNC cycle the drive does not answer within this time counts as missed (s).
CYCLE_TIMEOUT_S = 0.2


def add_bus_arguments(p: argparse.ArgumentParser, truth: bool = False) -> None:
    p.add_argument(
        "--interface",
        default="config",
        help="python-can interface (socketcan, pcan, kvaser, udp_multicast, ...); "
        "'config' (default) reads python-can's configuration / CAN_INTERFACE",
    )
    p.add_argument("--channel", default=None, help="python-can channel, e.g. vcan0, can0")
    p.add_argument("--bitrate", type=int, default=1_000_000, help="bit rate (default 1 Mbit/s)")
    if truth:
        p.add_argument(
            "--truth-interface",
            default=None,
            help="python-can interface of the ground-truth channel (none: no truth)",
        )
        p.add_argument("--truth-channel", default=None, help="channel of the truth bus")


def open_bus(
    interface: str | None, channel: str | None, bitrate: int, what: str = "control bus"
) -> can.BusABC:
    """A python-can bus with a one-line error instead of a traceback."""
    iface = None if interface in (None, "config") else interface
    kwargs: dict[str, Any] = {"bitrate": bitrate}
    if iface == "udp_multicast":
        kwargs = {"receive_own_messages": False}
    try:
        return can.Bus(interface=iface, channel=channel, **kwargs)
    except (can.CanError, ImportError, OSError, ValueError, TypeError) as exc:
        raise ConfigError(f"cannot open the {what} ({interface} {channel}): {exc}") from None


def _truth_bus(args: argparse.Namespace) -> can.BusABC | None:
    if not getattr(args, "truth_interface", None):
        return None
    return open_bus(args.truth_interface, args.truth_channel, args.bitrate, "truth bus")


def _serve(
    node: Any,
    stop: Callable[[], bool],
    until: Callable[[], bool],
    now: Callable[[], float] = time.monotonic,
) -> None:
    """Receive and handle frames, running the node's timers, until ``until()`` or a stop."""
    recv = node.bus.recv
    while not stop() and not until():
        node.tick(now())
        msg = recv(RECV_SLICE_S)
        while msg is not None:
            node.on_message(msg)
            msg = recv(0)


def run_emulate(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    fw = from_dict(FirmwareConfig, scenario.firmware, "firmware")
    seed = scenario.seed if args.seed is None else args.seed
    bus = open_bus(args.interface, args.channel, args.bitrate)
    truth = None
    try:
        truth = _truth_bus(args)
        drive = DriveNode(
            bus,
            Plant(scenario.plant, seed),
            DriveConfig(sample_period_s=fw.sample_period_s),
            truth_bus=truth,
        )
        t_end = time.monotonic() + args.duration if args.duration else float("inf")
        with stop_on_signals() as stop:
            drive.boot(time.monotonic())
            _serve(drive, stop.is_set, lambda: time.monotonic() >= t_end)
        stopped_by_signal = stop.is_set()
        d = drive.diagnostics
        print(json.dumps({"node": "drive", "syncs": d.syncs, "commands": d.commands,
                          "nmt_state": str(drive.nmt_state), "drive_state": str(drive.drive_state),
                          "plant_time_s": drive.plant.time}))  # fmt: skip
    finally:
        bus.shutdown()
        if truth is not None:
            truth.shutdown()
    return 130 if stopped_by_signal else 0


def run_firmware(args: argparse.Namespace) -> int:
    from hdhil.cli import UserError

    scenario = load_scenario(args.scenario)
    fw = from_dict(FirmwareConfig, scenario.firmware, "firmware")
    Ts = fw.sample_period_s
    cycles = round((args.duration or scenario.duration_s) / Ts)
    bus = open_bus(args.interface, args.channel, args.bitrate)
    try:
        ctrl = ControllerNode(bus, fw, boot_timeout_s=args.boot_timeout)
        with stop_on_signals() as stop:
            ctrl.boot(time.monotonic())
            # Wait for the drive's boot-up (or the timeout) while producing heartbeats.
            _serve(ctrl, stop.is_set, lambda: ctrl.phase != "wait-boot" or ctrl.boot_error)
            if ctrl.boot_error:
                raise UserError(ctrl.boot_error)
            done = _sync_loop(ctrl, stop.is_set, cycles, Ts, args.realtime)
            ctrl.request_stop()
            _sync_loop(ctrl, lambda: False, 2000, Ts, args.realtime,
                       until=lambda: ctrl.phase in ("stopped", "safe"))  # fmt: skip
        d = ctrl.diagnostics
        print(json.dumps({"node": "controller", "operational_cycles": done,
                          "syncs_sent": d.syncs_sent, "sensor_frames": d.sensor_frames,
                          "phase": ctrl.phase}))  # fmt: skip
        return 130 if stop.is_set() else 0
    finally:
        bus.shutdown()


def _sync_loop(
    ctrl: ControllerNode,
    stop: Callable[[], bool],
    cycles: int,
    Ts: float,
    realtime: bool,
    until: Callable[[], bool] | None = None,
) -> int:
    """Produce SYNCs; return the cycles run while the controller was operational."""
    operational = 0
    deadline = time.monotonic()
    recv = ctrl.bus.recv
    while operational < cycles and not stop() and not (until and until()):
        if ctrl.phase == "safe":
            break
        answered = ctrl.diagnostics.commands_sent
        ctrl.tick(time.monotonic())
        ctrl.send_sync()
        cycle_end = time.monotonic() + CYCLE_TIMEOUT_S
        if realtime:
            deadline += Ts
            cycle_end = deadline
        while True:
            left = cycle_end - time.monotonic()
            if not realtime and ctrl.diagnostics.commands_sent > answered:
                break
            if left <= 0:
                break
            msg = recv(min(left, RECV_SLICE_S))
            while msg is not None:
                ctrl.on_message(msg)
                msg = recv(0)
        if realtime:
            while time.monotonic() < deadline:  # spin the last stretch
                pass
        if ctrl.phase == "operational":
            operational += 1
    return operational


def run_log(args: argparse.Namespace) -> int:
    control = open_bus(args.interface, args.channel, args.bitrate)
    buses = {CHANNEL_NUMBER["control"]: control}
    try:
        truth = _truth_bus(args)
        if truth is not None:
            buses[CHANNEL_NUMBER["truth"]] = truth
        counter = FrameCounter()
        tap = BusTap(buses, [open_writer(Path(args.trace)), counter])
        t_end = time.monotonic() + args.duration if args.duration else float("inf")
        try:
            with stop_on_signals() as stop:
                while not stop.is_set() and time.monotonic() < t_end:
                    if not tap.poll():
                        time.sleep(IDLE_SLEEP_S)
            stopped_by_signal = stop.is_set()
            tap.poll()
        finally:
            tap.stop()  # flushes and closes the trace
        print(json.dumps({"trace": args.trace, "frames": counter.total}))
    finally:
        for bus in buses.values():
            bus.shutdown()
    return 130 if stopped_by_signal else 0


def _parse_index(text: str) -> tuple[int, int]:
    from hdhil.cli import UserError

    try:
        index, _, sub = text.partition(":")
        return int(index, 0), int(sub, 0) if sub else 0
    except ValueError:
        raise UserError(f"bad object address {text!r}: use INDEX[:SUB], e.g. 0x2100:2") from None


def run_sdo(args: argparse.Namespace) -> int:
    import canopen

    from hdhil.canopen_services import SdoError, sdo_read, sdo_write
    from hdhil.cli import UserError

    index, sub = _parse_index(args.address)
    node_eds = {1: "controller", 2: "drive"}.get(args.node)
    od = canopen.import_od(str(eds_path(node_eds)), args.node) if node_eds else None
    network = canopen.Network()
    network.bus = open_bus(args.interface, args.channel, args.bitrate)
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
    except (TypeError, ValueError, KeyError) as exc:
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
            from hdhil.cli import UserError

            raise UserError(f"bad value {text!r}: a number is expected") from None


NMT_COMMANDS = {"start": 0x01, "stop": 0x02, "pre-op": 0x80, "reset": 0x81, "reset-comm": 0x82}


def run_nmt(args: argparse.Namespace) -> int:
    bus = open_bus(args.interface, args.channel, args.bitrate)
    try:
        bus.send(can.Message(arbitration_id=0x000, is_extended_id=False,
                             data=bytes([NMT_COMMANDS[args.action], args.node])))  # fmt: skip
    finally:
        bus.shutdown()
    print("ok")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("emulate", help="run the drive emulator alone on a CAN interface")
    add_bus_arguments(p, truth=True)
    p.add_argument("--scenario", default="free-motion", help="scenario (its plant section)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        help="wall seconds (default: until Ctrl-C / SIGTERM)",
    )
    p.set_defaults(func=run_emulate)

    p = sub.add_parser("firmware", help="run the controller firmware alone on a CAN interface")
    add_bus_arguments(p)
    p.add_argument("--scenario", default="free-motion", help="scenario (its firmware section)")
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        help="simulated seconds of operation (default: the scenario's)",
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="pace SYNC at the sample period on the monotonic clock",
    )
    p.add_argument(
        "--boot-timeout", type=float, default=2.0, help="seconds to wait for the drive's boot-up"
    )
    p.set_defaults(func=run_firmware)

    p = sub.add_parser("log", help="record a CAN interface (and the truth bus) to a trace")
    add_bus_arguments(p, truth=True)
    p.add_argument("trace", help="trace file (.blf .asc .log .csv .trc)")
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        help="wall seconds (default: until Ctrl-C / SIGTERM)",
    )
    p.set_defaults(func=run_log)

    p = sub.add_parser("sdo", help="read or write a node's object dictionary (SDO client)")
    add_bus_arguments(p)
    p.add_argument("action", choices=("read", "write"))
    p.add_argument("node", type=int, help="node-ID (1 controller, 2 drive)")
    p.add_argument("address", help="INDEX[:SUB], e.g. 0x2100:2")
    p.add_argument("value", nargs="?", default=None)
    p.add_argument("--timeout", type=float, default=1.0)
    p.set_defaults(func=run_sdo)

    p = sub.add_parser("nmt", help="send an NMT command")
    add_bus_arguments(p)
    p.add_argument("action", choices=tuple(NMT_COMMANDS))
    p.add_argument("node", type=int, help="node-ID (0 = all nodes)")
    p.set_defaults(func=run_nmt)

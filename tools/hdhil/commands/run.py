"""``hdhil run``: a scenario end to end on the in-process bus, scored against truth."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hdhil.commands.options import (
    DEFAULT_BITRATE,
    add_bus_options,
    add_fault_arguments,
    add_mapping_arguments,
    bus_named,
    drive_dcf_of,
    mapping_metadata,
    open_bus,
    resolve_bus_config,
)
from hdhil.commands.progress import Progress, add_quiet_argument, progress
from hdhil.core.dataconf import from_dict, merge
from hdhil.core.errors import ConfigError, UserError
from hdhil.core.numbers import arg_float, arg_int, arg_seconds
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.odlimits import check_od_limits
from hdhil.hostsim.scenario import list_scenarios, load_scenario
from hdhil.rig.faults import with_fault_flags
from hdhil.rig.realtime import RealtimeConfig
from hdhil.rig.runner import (
    compare_laws,
    format_result,
    format_tracking,
    read_toml,
    run_lockstep,
    stop_on_signals,
)
from hdhil.rig.verdict import format_verdict


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="run a scenario end to end on the in-process bus",
        description="Run the firmware against the drive emulator over CAN in "
        "one process (lockstep, simulated time), log a trace and score the "
        "filtered torque against ground truth.",
    )
    p.add_argument(
        "--scenario",
        default="free-motion",
        help=f"scenario name or TOML file (shipped: {', '.join(list_scenarios())})",
    )
    p.add_argument(
        "--duration",
        type=arg_seconds(),
        default=None,
        help="simulated seconds (default: the scenario's)",
    )
    p.add_argument(
        "--seed",
        type=arg_int(0, 2**63 - 1),
        default=None,
        help="noise seed (default: the scenario's)",
    )
    p.add_argument(
        "--trace",
        default="hdhil-run.blf",
        help="trace file; format from the extension: .blf .asc .log .csv .trc "
        "(default: %(default)s; '' for none)",
    )
    p.add_argument(
        "--start-time",
        default=None,
        metavar="WHEN",
        help="date and time of simulated time 0 in the trace: ISO 8601 "
        "(2026-01-01T00:00:00Z) or Unix seconds (default: now)",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    add_quiet_argument(p)
    p.add_argument(
        "--calibration",
        type=Path,
        default=None,
        help="calibration file written by `hdhil calibrate --out` (the firmware uses its gain)",
    )
    add_fault_arguments(p)
    p.add_argument(
        "--compare-laws",
        action="store_true",
        help="run the scenario once per control law (JTF1, JTF2, JTF3, JTF1 + feedforward) "
        "and print the tracking table (traces get the law in their name)",
    )
    p.add_argument(
        "--no-evaluate",
        dest="evaluate",
        action="store_false",
        help="skip the side-by-side evaluation against truth (keeps memory flat on long runs)",
    )
    p.add_argument(
        "--skip",
        type=arg_seconds(lo_open=False),
        default=None,
        help="seconds at the start left out of the evaluation (default: the scenario's "
        "evaluate_from_s; the whole-run RMS figure is printed as well)",
    )
    p.add_argument(
        "--override",
        type=Path,
        action="append",
        default=[],
        metavar="FILE",
        help="TOML file deep-merged into the scenario, e.g. [firmware.ripple] written by "
        "`hdhil tune --out` (repeatable)",
    )
    p.add_argument(
        "--actuation",
        choices=("next-sync", "immediate"),
        default="next-sync",
        help="when the drive applies a command (default: %(default)s)",
    )
    add_bus_options(
        p,
        title="control bus (default: the simulated bus 'simbus' at 1 Mbit/s; with "
        "--interface, python-can's interfaces, CAN_CHANNEL, CAN_BITRATE and configuration file)",
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="pace SYNC by the wall clock at the sample period (sleep, then spin) instead "
        "of lockstep as fast as possible; reports SYNC jitter, sensor-to-command latency, "
        "interrupt compute time and deadline misses (also under 'realtime' in --json)",
    )
    p.add_argument(
        "--spin-us",
        type=arg_float(0.0, 1e6),
        default=None,
        metavar="US",
        help="--realtime: busy-wait this many µs before each deadline (default: 60 %% of the "
        "period, within the kernel's RT throttling budget)",
    )
    p.add_argument(
        "--mlock",
        action="store_true",
        help="--realtime: lock the process's memory (mlockall, where permitted)",
    )
    p.add_argument(
        "--floor-s",
        type=arg_seconds(lo_open=False),
        default=0.0,
        metavar="S",
        help="--realtime: after the run, measure the machine floor (the bare sleep+spin loop, "
        "no hdhil code) for S seconds (default: none)",
    )
    add_mapping_arguments(p)
    p.set_defaults(func=run)


def _control_bus(
    args: argparse.Namespace,
) -> tuple[str, str | None, int, Callable[[], Any] | None]:
    """Interface, channel, bit rate and bus factory of the run's control bus.

    Without ``--interface`` the run is on the simulated bus at ``--bitrate`` or 1 Mbit/s
    (python-can's environment and configuration file describe real interfaces, not the
    simulation).  With it, python-can's own factory opens the bus, the environment and
    configuration file filling what the command line leaves out."""
    if not bus_named(args):
        bitrate = getattr(args, "bitrate", DEFAULT_BITRATE)
        return "simbus", getattr(args, "channel", None), bitrate, None
    resolved = resolve_bus_config(args)
    interface = str(resolved["interface"])
    if interface == "simbus":
        return interface, resolved.get("channel"), int(resolved["bitrate"]), None

    def factory() -> Any:
        return open_bus(args, "control bus")[0]

    return interface, resolved.get("channel"), int(resolved["bitrate"]), factory


#: How often (in samples) a run on a terminal moves its progress bar.
PROGRESS_EVERY_SAMPLES = 200


def _progress_monitor(bar: Progress) -> Callable[[Any], None] | None:
    """The run's ``monitor``: simulated seconds done, for the progress bar (none if the
    bar is off, so runs without a terminal are untouched)."""
    if not bar.enabled:
        return None

    def monitor(controller: Any) -> None:
        bar.update_to(controller.isr.samplecount * controller.config.sample_period_s)

    return monitor


def parse_start_time(text: str | None) -> float | None:
    """``--start-time``: ISO 8601 (UTC unless a zone is given) or Unix seconds."""
    if text is None:
        return None
    import datetime
    import math

    try:
        value = float(text)
    except ValueError:
        try:
            when = datetime.datetime.fromisoformat(text.replace("Z", "+00:00"))
        except ValueError:
            raise UserError(
                f"--start-time {text!r}: use ISO 8601 (2026-01-01T00:00:00Z) or Unix seconds"
            ) from None
        if when.tzinfo is None:
            when = when.replace(tzinfo=datetime.timezone.utc)
        value = when.timestamp()
    if not math.isfinite(value) or not 0 <= value < 253402300800:  # up to year 9999
        raise UserError(f"--start-time {text!r}: out of range")
    return value


def _strip_source(message: str) -> str:
    """A scenario error without the scenario file's name in front (``path: ...``)."""
    head, sep, rest = message.partition(": ")
    return rest if sep and head.endswith(".toml") else message


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)  # its own mistakes name the scenario file
    overrides: dict[str, Any] = {}
    for path in args.override:
        overrides = merge(overrides, read_toml(path))
        try:  # a mistake an override brings in names the override file
            scenario = load_scenario(args.scenario, overrides)
            check_od_limits(from_dict(FirmwareConfig, scenario.firmware, "firmware"))
        except ConfigError as exc:
            raise ConfigError(f"override file {path}: {_strip_source(str(exc))}") from None
    if args.fault:
        scenario = dataclasses.replace(
            scenario, faults=with_fault_flags(scenario.faults, args.fault)
        )
    if args.calibration is not None:
        from hdhil.rig.calibration import load_calibration

        firmware = merge(scenario.firmware, load_calibration(args.calibration))
        scenario = dataclasses.replace(scenario, firmware=firmware)
    trace = Path(args.trace) if args.trace else None
    start_time = parse_start_time(args.start_time)
    metadata = {
        "scenario_source": args.scenario,
        "overrides": [str(p) for p in args.override],
        "calibration": str(args.calibration) if args.calibration is not None else None,
    }
    drive_dcf, mapping_label = drive_dcf_of(args)
    mapped = mapping_metadata(drive_dcf, mapping_label)
    metadata.update(mapped)
    factories: dict[str, Any] = {}
    if drive_dcf is not None:
        if args.compare_laws:
            raise UserError(
                "--compare-laws runs the default mapping; leave out --drive-dcf/--mapping"
            )
        from hdhil.rig.factories import dcf_controller

        factories["controller_factory"] = dcf_controller(drive_dcf)
    if not args.realtime and (args.spin_us is not None or args.floor_s or args.mlock):
        raise UserError("--spin-us, --floor-s and --mlock need --realtime")
    rt_config = RealtimeConfig(spin_us=args.spin_us, floor_s=args.floor_s, mlock=args.mlock)
    try:
        interface, channel, bitrate, factory = _control_bus(args)
        with stop_on_signals() as stop, contextlib.ExitStack() as stack:
            if args.compare_laws:
                rows = compare_laws(
                    scenario,
                    duration_s=args.duration,
                    seed=args.seed,
                    trace=trace,
                    interface=interface,
                    actuation=args.actuation,
                    bitrate=bitrate,
                    channel=channel,
                    open_control_bus=factory,
                    start_time=start_time,
                    metadata=metadata,
                    stop_requested=stop.is_set,
                    evaluate_skip_s=scenario.evaluate_from_s if args.skip is None else args.skip,
                    realtime=args.realtime,
                    realtime_config=rt_config,
                )
                if args.json:
                    json.dump({"scenario": scenario.name, "laws": rows}, sys.stdout, indent=2)
                    print()
                else:
                    print(f"hdhil run --compare-laws: scenario {scenario.name}")
                    print(format_tracking(rows))
                if stop.is_set():
                    return 130
                stopped = [row for row in rows if "verdict" in row]
                for row in stopped:
                    print(f"hdhil: run {row['law']}: {format_verdict(row['verdict'])}",
                          file=sys.stderr)  # fmt: skip
                return 1 if stopped else 0
            duration = args.duration if args.duration is not None else scenario.duration_s
            bar = progress(args, duration, f"hdhil run {scenario.name}", "s")
            stack.enter_context(bar)
            result = run_lockstep(
                scenario,
                args.duration,
                args.seed,
                trace,
                interface,
                args.actuation,
                bitrate,
                channel,
                open_control_bus=factory,
                start_time=start_time,
                metadata=metadata,
                monitor=_progress_monitor(bar),
                monitor_every=PROGRESS_EVERY_SAMPLES,
                stop_requested=stop.is_set,
                evaluate=args.evaluate,
                evaluate_skip_s=scenario.evaluate_from_s if args.skip is None else args.skip,
                realtime=args.realtime,
                realtime_config=rt_config,
                fault_log=args.fault_log,
                **factories,
            )
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if args.json:
        summary = result.as_dict()
        if mapped:
            summary["mapping"] = mapped["mapping"]
        json.dump(summary, sys.stdout, indent=2)
        print()
    else:
        if mapped:
            print(f"mapping: {mapped['mapping']} (the drive configured from {mapped['drive_dcf']})")
        print(format_result(result))
    if result.interrupted:
        return 130
    if result.verdict is not None:  # stopped by a fault reaction: the reason is printed
        print(f"hdhil: run {format_verdict(result.verdict)}", file=sys.stderr)
        return 1
    return 0

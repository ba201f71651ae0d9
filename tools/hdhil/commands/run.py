"""``hdhil run``: a scenario end to end on the in-process bus, scored against truth."""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hdhil.commands.options import (
    add_bus_options,
    add_drive_node_id_argument,
    add_scenario_arguments,
    bus_named,
    check_outputs,
    open_bus,
    request_from_args,
    resolve_bus_config,
    run_outputs,
    scenario_inputs,
)
from hdhil.commands.progress import Progress, add_quiet_argument, progress
from hdhil.core import jsonout
from hdhil.core.errors import UserError
from hdhil.core.numbers import MAX_UNIX_TIME, arg_float, arg_seconds
from hdhil.core.signals import stop_on_signals
from hdhil.rig.laws import compare_laws
from hdhil.rig.realtime import RealtimeConfig
from hdhil.rig.result import format_result, format_tracking
from hdhil.rig.runner import run_lockstep
from hdhil.rig.verdict import format_verdict


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="run a scenario end to end on the in-process bus",
        description="Run the firmware against the drive emulator over CAN in "
        "one process (lockstep, simulated time), log a trace and score the "
        "filtered torque against ground truth.",
    )
    add_scenario_arguments(p)
    add_drive_node_id_argument(p)
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
        "--actuation",
        choices=("next-sync", "immediate"),
        default=None,
        help="when the drive applies a command (default: the scenario's [link] actuation, "
        "next-sync); sets the control law's delay compensation to match "
        "(firmware.control.delay_samples 1 or 0)",
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
    p.set_defaults(func=run)


def _control_bus(
    args: argparse.Namespace,
) -> tuple[str, str | None, int | None, Callable[[], Any] | None]:
    """Interface, channel, bit rate and bus factory of the run's control bus.

    Without ``--interface`` the run is on the simulated bus at ``--bitrate`` or 1 Mbit/s
    (python-can's environment and configuration file describe real interfaces, not the
    simulation).  With it, python-can's own factory opens the bus, the environment and
    configuration file filling what the command line leaves out."""
    if not bus_named(args):  # the scenario's [bus] bit rate unless --bitrate names one
        return "simbus", getattr(args, "channel", None), getattr(args, "bitrate", None), None
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
    if not math.isfinite(value) or not 0 <= value <= MAX_UNIX_TIME:  # up to year 9999
        raise UserError(f"--start-time {text!r}: out of range")
    return value


def _run_rig(
    args: argparse.Namespace,
    request: Any,
    interface: str,
    trace: Path | None,
) -> int:
    """``hdhil run`` of a rig of several joints (:mod:`hdhil.rig.rigrun`)."""
    from hdhil.analysis.rigplan import plan_scenario
    from hdhil.rig.rigrun import check_rig_options, format_rig_result, run_rig

    check_rig_options(request, interface=interface, realtime=args.realtime,
                      compare_laws=args.compare_laws, fault_log=args.fault_log)  # fmt: skip
    refusal = plan_scenario(request.scenario).refusal()  # a bus over 60 %: as hdhil plan
    if refusal is not None:
        raise UserError(f"{refusal} (hdhil plan --scenario {request.scenario.name})")
    check_outputs(run_outputs([trace] if trace else [], None), scenario_inputs(args))
    with stop_on_signals() as stop:
        result = run_rig(request, trace=trace, start_time=parse_start_time(args.start_time),
                         stop_requested=stop.is_set, evaluate=args.evaluate)  # fmt: skip
    if args.json:
        jsonout.dump(result.as_dict(), sys.stdout, indent=2)
        print()
    else:
        print(format_rig_result(result))
    if result.interrupted:
        return 130
    if result.verdict is not None:
        print(f"hdhil: run stopped in {result.verdict['phase']}: {result.verdict['reason']}",
              file=sys.stderr)  # fmt: skip
        return 1
    return 0


def run(args: argparse.Namespace) -> int:
    if args.compare_laws and (args.mapping or args.drive_dcf):
        raise UserError("--compare-laws runs the default mapping; leave out --drive-dcf/--mapping")
    interface, channel, bitrate, factory = _control_bus(args)
    request = request_from_args(
        args, evaluate_from_s=args.skip, actuation=args.actuation, bitrate=bitrate
    )
    trace = Path(args.trace) if args.trace else None
    if request.scenario.is_rig:
        return _run_rig(args, request, interface, trace)
    traces = [trace] if trace is not None else []
    if trace is not None and args.compare_laws:
        from hdhil.rig.laws import compared_traces

        traces = compared_traces(request, trace)
    # never over an input, nor two outputs into one file: refused before the run
    check_outputs(run_outputs(traces, args.fault_log), scenario_inputs(args))
    start_time = parse_start_time(args.start_time)
    if not args.realtime and (args.spin_us is not None or args.floor_s or args.mlock):
        raise UserError("--spin-us, --floor-s and --mlock need --realtime")
    rt_config = RealtimeConfig(spin_us=args.spin_us, floor_s=args.floor_s, mlock=args.mlock)
    try:
        with stop_on_signals() as stop, contextlib.ExitStack() as stack:
            if args.compare_laws:
                rows = compare_laws(
                    request,
                    trace=trace,
                    interface=interface,
                    channel=channel,
                    open_control_bus=factory,
                    start_time=start_time,
                    stop_requested=stop.is_set,
                    realtime=args.realtime,
                    realtime_config=rt_config,
                )
                if args.json:
                    jsonout.dump({"scenario": request.name, "laws": rows}, sys.stdout, indent=2)
                    print()
                else:
                    print(f"hdhil run --compare-laws: scenario {request.name}")
                    print(format_tracking(rows))
                if stop.is_set():
                    return 130
                stopped = [row for row in rows if "verdict" in row]
                for row in stopped:
                    print(f"hdhil: run {row['law']}: {format_verdict(row['verdict'])}",
                          file=sys.stderr)  # fmt: skip
                return 1 if stopped else 0
            bar = progress(args, request.duration_s, f"hdhil run {request.name}", "s")
            stack.enter_context(bar)
            result = run_lockstep(
                request,
                trace=trace,
                interface=interface,
                channel=channel,
                open_control_bus=factory,
                start_time=start_time,
                monitor=_progress_monitor(bar),
                monitor_every=PROGRESS_EVERY_SAMPLES,
                stop_requested=stop.is_set,
                evaluate=args.evaluate,
                keep_recording=False,  # the summary needs no per-cycle recording
                realtime=args.realtime,
                realtime_config=rt_config,
                fault_log=args.fault_log,
            )
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if args.json:
        summary = result.as_dict()
        if request.mapping.dcf is not None:
            summary["mapping"] = request.mapping.label
        jsonout.dump(summary, sys.stdout, indent=2)
        print()
    else:
        if request.mapping.dcf is not None:
            m = request.mapping
            print(f"mapping: {m.label} (the drive configured from {m.dcf.name})")
        print(format_result(result))
    if result.interrupted:
        return 130
    if result.verdict is not None:  # stopped by a fault reaction: the reason is printed
        print(f"hdhil: run {format_verdict(result.verdict)}", file=sys.stderr)
        return 1
    return 0

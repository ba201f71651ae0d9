"""``hdhil soak``: a long lockstep run with logging, checked block by block
(:mod:`hdhil.analysis.soak`: per-block errors against truth, filter health, memory,
and the verdicts at the end).

This module reads the options, shows progress per block, prints the report or JSON.
Exit codes: 0 when every verdict passes, 1 when one fails, 2 input error (one line),
130 after Ctrl-C/SIGTERM (the blocks done so far are reported).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from hdhil.analysis.soak import (
    STATIONARITY_BLOCKS,
    SoakLimits,
    default_block_s,
    format_report,
    run_soak,
)
from hdhil.commands.options import (
    add_scenario_arguments,
    check_outputs,
    request_from_args,
    run_outputs,
    scenario_inputs,
)
from hdhil.commands.progress import add_quiet_argument, progress
from hdhil.core import jsonout
from hdhil.core.errors import UserError
from hdhil.core.numbers import FLOAT32_MAX, arg_float, arg_seconds
from hdhil.core.signals import stop_on_signals


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "soak",
        help="long lockstep run with logging, checked per block (filter health, errors, memory)",
        description="Run a scenario for a long simulated time in lockstep with a trace; "
        "per block report the errors against truth, the ripple filter's covariance "
        "health, non-finite values, resets, skipped samples, memory and trace size; "
        "end with verdicts (exit 1 if one fails).",
    )
    add_scenario_arguments(p, default="lqg-misalignment", duration=3600.0)
    p.add_argument(
        "--every", type=arg_seconds(), default=None, metavar="S",
        help="block length in simulated seconds (default: 60, shorter for short runs so "
        f"that at least {STATIONARITY_BLOCKS} blocks follow the settling time)",
    )  # fmt: skip
    p.add_argument(
        "--trace",
        default="hdhil-soak.blf",
        help="trace file; format from the extension: .blf .asc .log .csv .trc "
        "(default: %(default)s; '' for none)",
    )
    p.add_argument(
        "--settle", type=arg_seconds(lo_open=False), default=None, metavar="S",
        help="blocks starting before this are left out of the stationarity test "
        "(default: the scenario's evaluate_from_s)",
    )  # fmt: skip
    p.add_argument(
        "--tolerance", type=arg_float(0.0, FLOAT32_MAX, lo_open=True), default=SoakLimits.tolerance,
        help="stationarity: the per-block RMS's fitted change over the tested blocks, with "
        "its 95%% interval, must lie within +-this fraction of their mean (default: %(default)g)",
    )  # fmt: skip
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    add_quiet_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    request = request_from_args(args)
    limits = SoakLimits(
        settle_s=request.evaluate_from_s if args.settle is None else args.settle,
        tolerance=args.tolerance,
    )
    trace = Path(args.trace) if args.trace else None
    check_outputs(run_outputs([trace] if trace else [], args.fault_log), scenario_inputs(args))
    every = args.every if args.every is not None else default_block_s(request.duration_s, limits)
    bar = progress(args, request.duration_s, f"hdhil soak {request.name}", "s")
    progress_kwargs: dict[str, Any] = {}
    if bar.enabled:
        progress_kwargs["after_block"] = lambda _c, block: bar.update_to(block.end_s)
    try:
        with stop_on_signals() as stop, bar:
            report = run_soak(
                request,
                block_s=every,
                trace=trace,
                limits=limits,
                fault_log=args.fault_log,
                stop_requested=stop.is_set,
                **progress_kwargs,
            )
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if args.json:
        jsonout.dump(report.as_dict(), sys.stdout, indent=2)
        print()
    else:
        print(format_report(report))
    if report.interrupted:
        return 130
    return 0 if report.passed else 1

"""``hdhil bench``: throughput, per-stage compute time, memory, real-time jitter,
campaign and start-up figures, as medians with their spread
(:mod:`hdhil.analysis.benchmarks`).

This module reads the options, shows progress per section and prints the report or
JSON.  ``--quick`` shrinks every section (CI and the tests); the default takes about
six minutes on a 2-core machine.  ``--only joints`` runs the joints section alone.
Exit codes: 0 done, 2 input error (one line).
"""

from __future__ import annotations

import argparse
import math
import sys

from hdhil.analysis.benchmarks import format_bench, run_benchmarks
from hdhil.commands.progress import add_quiet_argument, progress
from hdhil.core import jsonout
from hdhil.core.errors import UserError
from hdhil.core.numbers import arg_int, arg_seconds


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench", help="measure throughput, per-stage compute time and memory (medians)"
    )
    p.add_argument(
        "--duration", type=arg_seconds(), default=None,
        help="simulated seconds per lockstep run (default 10, --quick 0.3)",
    )  # fmt: skip
    p.add_argument(
        "--repeat", type=arg_int(1, 10_000), default=None,
        help="runs per figure, median reported (default 3, --quick 1)",
    )  # fmt: skip
    p.add_argument(
        "--realtime-s", type=arg_seconds(lo_open=False), default=None, metavar="S",
        help="seconds of the real-time run (default 60, --quick 1.5; 0 leaves it out)",
    )  # fmt: skip
    p.add_argument(
        "--startup-runs", type=int, default=None, metavar="N",
        help="process starts per start-up figure (default 7, --quick 2)",
    )  # fmt: skip
    p.add_argument("--quick", action="store_true", help="a short version of every section (CI)")
    p.add_argument(
        "--only", choices=("joints",), default=None,
        help="run one section alone (joints: the loop's cost for 1, 2, 4, 7 joints and the "
        "rigs' whole command)",
    )  # fmt: skip
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    add_quiet_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    quick = bool(getattr(args, "quick", False))
    duration = args.duration if args.duration is not None else (0.3 if quick else 10.0)
    repeat = args.repeat if args.repeat is not None else (1 if quick else 3)
    if not duration > 0 or repeat < 1:
        raise UserError("--duration must be > 0 and --repeat >= 1")
    realtime_s = getattr(args, "realtime_s", None)
    if realtime_s is not None and not (math.isfinite(realtime_s) and realtime_s >= 0):
        raise UserError(f"--realtime-s must be >= 0 seconds, got {realtime_s:g}")
    startup_runs = getattr(args, "startup_runs", None)
    if startup_runs is not None and startup_runs < 1:
        raise UserError(f"--startup-runs must be >= 1, got {startup_runs}")
    if getattr(args, "only", None) == "joints":
        from hdhil.analysis.benchmarks import format_joints_only, run_joints_only

        report = run_joints_only(duration, repeat, quick=quick)
        if args.json:
            jsonout.dump(report, sys.stdout, indent=2)
            print()
        else:
            print(format_joints_only(report))
        return 0
    sections = [
        "lockstep", "stages", "filter", "memory", "real time", "campaign", "start-up", "speed",
        "joints", "done",
    ]  # fmt: skip
    with progress(args, len(sections) - 1, "hdhil bench", "section") as bar:

        def on_section(name: str) -> None:
            bar.update_to(sections.index(name))
            bar.describe(f"hdhil bench: {name}")

        report = run_benchmarks(duration, repeat, quick=quick, realtime_s=realtime_s,
                                startup_runs=startup_runs, on_section=on_section)  # fmt: skip
    if args.json:
        jsonout.dump(report, sys.stdout, indent=2)
        print()
    else:
        print(format_bench(report))
    return 0

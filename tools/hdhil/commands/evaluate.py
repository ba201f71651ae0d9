"""``hdhil evaluate``: score a trace as its run was scored, headline first.

The scoring is :func:`hdhil.rig.trace_score.score_trace` (the run's request from the
trace's sidecar, the same evaluation and tracking score a live run uses); this module
prints the headline and the table or JSON, for a rig's trace the table per joint and
the worst joint. Exit codes: 0 done, 1 done on a damaged
trace, 2 input error (one line).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hdhil.core import jsonout
from hdhil.core.numbers import arg_seconds
from hdhil.rig.evaluate import format_evaluation


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="score the filters against ground truth in a trace",
        description="Re-run the firmware's filter chain and the baselines on a "
        "recorded run and score them against the emulator's ground truth.",
    )
    p.add_argument("trace", type=Path, help="trace written by hdhil run")
    p.add_argument(
        "--scenario",
        default=None,
        help="scenario whose firmware configuration was used (default: the run recorded in "
        "the trace's sidecar TRACE.json, else the firmware defaults)",
    )
    p.add_argument(
        "--skip",
        type=arg_seconds(lo_open=False),
        default=None,
        help="seconds at the start left out of the evaluation (default: the run's evaluation "
        "start, as `hdhil run` scored it; 0 without a sidecar)",
    )
    p.add_argument("--json", action="store_true", help="print the evaluation as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hdhil.rig.headline import format_headline
    from hdhil.rig.result import format_tracking
    from hdhil.rig.trace_score import score_trace

    ev, damage = score_trace(args.trace, args.scenario, args.skip)
    if args.json:
        jsonout.dump(ev, sys.stdout, indent=2)
        print()
    elif "joints" in ev:  # a rig's trace: a row per joint, as hdhil run printed it
        from hdhil.rig.rigrun import format_rig_evaluation

        print(format_rig_evaluation(ev))
    else:
        print(format_headline(ev["headline"]))
        if "candidates" in ev:
            print(format_evaluation(ev))
        if ev.get("tracking") is not None:
            print(format_tracking([ev["tracking"]]))
    if damage:
        print(f"hdhil: warning: {damage}", file=sys.stderr)
        return 1
    return 0

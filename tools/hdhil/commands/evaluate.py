"""``hdhil evaluate``: score the firmware's and offline filters against ground truth.

The scores are :func:`hdhil.rig.evaluate.evaluate`'s, plus the torque-control tracking
figures of :func:`hdhil.analysis.tracking.tracking_from_trace` when the trace carries
controller telemetry.  This module finds the trace's scenario, checks that there is
something to score, and prints the table or JSON.  Exit codes: 0 done, 1 done on a
damaged trace, 2 input error (one line).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from hdhil.analysis.tracking import tracking_from_trace
from hdhil.core.errors import UserError
from hdhil.core.numbers import arg_seconds
from hdhil.firmware.config import FirmwareConfig
from hdhil.rig.evaluate import (
    evaluate,
    format_evaluation,
    recording_from_trace,
)


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
        help="scenario whose firmware configuration was used (default: the one in the "
        "trace's sidecar TRACE.json, else the firmware defaults)",
    )
    p.add_argument(
        "--skip", type=arg_seconds(lo_open=False), default=0.0, help="seconds left out at the start"
    )
    p.add_argument("--json", action="store_true", help="print the evaluation as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hdhil.commands.options import scenario_for_trace
    from hdhil.core.dataconf import from_dict

    scenario, _source = scenario_for_trace(args.trace, args.scenario)
    fw = from_dict(FirmwareConfig, scenario.firmware, "firmware") if scenario else FirmwareConfig()
    rec, damage = recording_from_trace(args.trace, fw.sample_period_s)
    if len(rec) == 0:
        raise UserError(f"{args.trace}: no drive sensor frames (DRIVE_TPDO1) to evaluate")
    if not np.isfinite(rec.column("T_true")).any():
        raise UserError(
            f"{args.trace}: no ground truth (TRUTH_TORQUE frames on the truth channel); "
            "nothing to score against (`hdhil filter` runs the filter without truth)"
        )
    ev = evaluate(rec, fw, args.skip)
    tracking = tracking_from_trace(args.trace, fw, args.skip)
    if tracking is not None:
        ev["tracking"] = tracking
    if args.json:
        json.dump(ev, sys.stdout, indent=2)
        print()
    else:
        print(format_evaluation(ev))
        if tracking is not None:
            from hdhil.rig.runner import format_tracking

            print(format_tracking([tracking]))
    if damage:
        print(f"hdhil: warning: {damage}", file=sys.stderr)
        return 1
    return 0

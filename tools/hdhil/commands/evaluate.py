"""``hdhil evaluate``: score the firmware's and offline filters against ground truth."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

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
    tracking = _tracking(args.trace, fw, args.skip)
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


def _tracking(trace: Path, fw: FirmwareConfig, skip_s: float) -> dict | None:
    """[Vertechy] tracking figures from the trace alone (desired torque and estimates from
    the controller's CTRL_TPDO2, truth from the truth channel), or None without
    torque-control telemetry.  The joint's Jl/Jm and whether the law compensates the
    friction (Eq. 5) come from ``--scenario``."""
    from hdhil.can.traces.reader import read_trace
    from hdhil.rig.score import TrackingScorer, trace_time_offset

    c = fw.control
    scorer = TrackingScorer(
        c.joint.Jl / c.joint.Jm, skip_s, c.friction.active, trace_time_offset(trace)
    )
    with read_trace(trace) as frames:
        for msg in frames:
            scorer.on_message_received(msg)
    if not scorer.n:
        return None
    law = c.law.name.lower() if c.active else "(from trace)"
    return {"law": law, **scorer.result().as_dict()}

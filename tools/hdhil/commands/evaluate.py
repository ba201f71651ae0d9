"""``hdhil evaluate``: score the firmware's and offline filters against ground truth."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

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
        help="scenario whose firmware configuration was used (default: defaults)",
    )
    p.add_argument("--skip", type=float, default=0.0, help="seconds left out at the start")
    p.add_argument("--json", action="store_true", help="print the evaluation as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hdhil.core.dataconf import from_dict
    from hdhil.hostsim.scenario import load_scenario

    fw = (from_dict(FirmwareConfig, load_scenario(args.scenario).firmware, "firmware")
          if args.scenario else FirmwareConfig())  # fmt: skip
    rec, damage = recording_from_trace(args.trace, fw.sample_period_s)
    ev = evaluate(rec, fw, args.skip)
    if args.json:
        json.dump(ev, sys.stdout, indent=2)
        print()
    else:
        print(format_evaluation(ev))
    if damage:
        print(f"hdhil: warning: {damage}", file=sys.stderr)
        return 1
    return 0

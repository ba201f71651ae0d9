"""``hdhil tune TRACE``: pick the recommended ripple filter's Q and R from a recorded
trace by maximum innovation likelihood (:mod:`hdhil.analysis.tuning`).

This module reads the options, finds the trace's scenario (``--scenario`` or the
sidecar), prints the report or JSON and writes ``--out`` (the tuned
``[firmware.ripple]`` table).  Exit codes: 0 done, 1 done on a damaged trace, 2 input
error (one line).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from hdhil.analysis.tuning import (
    DEFAULT_MAX_EVALS,
    SKIP_S,
    format_result,
    ripple_toml,
    tune_recording,
)
from hdhil.commands.progress import add_quiet_argument, progress
from hdhil.core import jsonout
from hdhil.core.errors import UserError
from hdhil.core.files import check_output, display_name, write_text
from hdhil.core.numbers import arg_int, arg_seconds
from hdhil.firmware.config import FirmwareConfig


def check_out(path: Path) -> None:
    """``--out`` must be a ``.toml`` file in an existing directory (checked before tuning)."""
    if path.suffix.lower() != ".toml":
        raise UserError(f"--out {path}: must be a .toml file")
    check_output(path, "--out")  # a regular file or a new one, in an existing directory


def write_toml(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` (see :func:`check_out`)."""
    check_out(path)
    write_text(path, text, "--out")


# -------------------------------------------------------------------------------- CLI
def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``hdhil tune`` to the command line."""
    p = subparsers.add_parser(
        "tune",
        help="tune the recommended ripple filter's Q/R on a trace (maximum likelihood)",
        description="Pick the recommended ripple filter's q (motor / output harmonics), "
        "residual_q and r by maximising the likelihood of the filter's innovations on a "
        "recorded trace. Uses only the drive's sensor frames (DRIVE_TPDO1), never ground "
        "truth; truth, when present, is reported as an independent check.",
    )
    p.add_argument("trace", type=Path, help="trace file (.blf, .asc, .log, .csv, .trc)")
    p.add_argument(
        "--scenario",
        default=None,
        help="scenario whose firmware configuration (harmonics, calibration) the trace was "
        "recorded with (default: the sidecar TRACE.json's, else the firmware defaults)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="FILE.toml",
        help="write the tuned [firmware.ripple] table (scenario layout) to FILE.toml",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    add_quiet_argument(p)
    p.add_argument(
        "--max-evals",
        type=arg_int(1, 1_000_000),
        default=DEFAULT_MAX_EVALS,
        metavar="N",
        help=f"budget of likelihood evaluations (default {DEFAULT_MAX_EVALS})",
    )
    p.add_argument(
        "--skip",
        type=arg_seconds(lo_open=False),
        default=SKIP_S,
        metavar="S",
        help=f"seconds left out of the likelihood at the start (default {SKIP_S:g})",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``hdhil tune``: 0 done, 1 done on a damaged trace (2 via UserError)."""
    from hdhil.rig.evaluate import recording_from_trace

    if args.max_evals < 1:
        raise UserError(f"--max-evals must be >= 1, got {args.max_evals}")
    if not (math.isfinite(args.skip) and args.skip >= 0):
        raise UserError(f"--skip must be a finite number >= 0, got {args.skip}")
    if args.out is not None:
        check_out(args.out)
        from hdhil.commands.options import check_outputs, scenario_inputs, trace_inputs

        check_outputs([(args.out, "--out")], [*trace_inputs(args.trace), *scenario_inputs(args)])
    from hdhil.rig.sidecar import request_for_trace

    request = request_for_trace(args.trace, args.scenario)
    if request is not None:
        request.require_one_joint("hdhil tune")
    scenario = request.scenario if request is not None else None
    fw = scenario.firmware if scenario is not None else FirmwareConfig()
    rec, damage = recording_from_trace(args.trace, fw.sample_period_s)
    with progress(args, args.max_evals, "hdhil tune", "eval") as bar:
        res = tune_recording(rec, fw, skip_s=args.skip, max_evals=args.max_evals,
                             on_evaluation=bar.update_to)  # fmt: skip
    label = f"{args.trace}, scenario {scenario.name if scenario else '(firmware defaults)'}"
    if args.out is not None:
        trace = display_name(args.trace)  # a TOML comment: one line of UTF-8
        comments = [
            "hdhil tune: recommended ripple filter tuned by maximum innovation likelihood",
            f"trace {trace}, scenario {scenario.name if scenario else 'defaults'}, "
            f"{res.samples} samples from {res.window[0] * res.sample_period_s:g} s",
            f"log-likelihood per sample (nats): paper {res.loglik_paper:.4f}, "
            f"default {res.loglik_default:.4f}, tuned {res.loglik_tuned:.4f}",
            "merge over a scenario: hdhil run --override THIS_FILE.toml",
        ]
        write_toml(args.out, ripple_toml(res.tuned_ripple, comments))
    if args.json:
        out = res.to_json()
        out["trace"] = str(args.trace)
        out["scenario"] = scenario.name if scenario else None
        out["out"] = str(args.out) if args.out is not None else None
        jsonout.dump(out, sys.stdout, indent=2)
        print()
    else:
        print(format_result(res, label))
        if args.out is not None:
            print(f"  wrote              {args.out}")
    if damage:
        print(f"hdhil: warning: {damage}", file=sys.stderr)
        return 1
    return 0

"""``hdhil filter``: the firmware's torque filter run offline over a CSV or a trace."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hdhil.core.errors import UserError
from hdhil.core.files import display_name
from hdhil.firmware.config import paper_config
from hdhil.rig.offline import (
    OUTPUT_COLUMNS,
    _check_input,
    _CsvTarget,
    _is_can_csv,
    filter_signal_csv,
    filter_trace,
    load_firmware_config,
)


# -------------------------------------------------------------------------------- CLI
def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "filter",
        help="run the firmware's torque filter offline over a signal CSV or a trace",
        description="Run the firmware's torque filter chain (differentiator, expected "
        "torque, ripple Kalman filter) offline.  INPUT is a CSV with columns "
        "time,T_meas,velocity[,encoder] or a trace written by 'hdhil run' (its DRIVE_TPDO1 "
        "frames are filtered exactly as the firmware did).  Output columns: "
        + ",".join(OUTPUT_COLUMNS)
        + ".",
    )
    parser.add_argument("input", metavar="INPUT", help="signal CSV or trace file")
    parser.add_argument(
        "--out", required=True, metavar="OUT.csv", help="output CSV ('-' for stdout)"
    )
    parser.add_argument(
        "--paper",
        action="store_true",
        help="use the seed's paper filter (listing A.1 for the default harmonics) instead "
        "of the recommended one",
    )
    parser.add_argument(
        "--config",
        metavar="FILE.toml",
        help="firmware configuration: a scenario file ([firmware...] tables) or the "
        "firmware tables at top level",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Filter ``args.input`` into ``args.out``; 0 done, 1 damaged trace (2 via UserError)."""
    from hdhil.commands.options import check_outputs, trace_inputs

    path = Path(args.input)
    inputs = trace_inputs(path)
    inputs[:1] = [(path, "input")]
    check_outputs([(args.out, "--out")], [*inputs, (args.config, "--config file")])
    fmt, compressed = _check_input(path)
    cfg = load_firmware_config(args.config)
    if args.paper:
        cfg = paper_config(cfg)
    is_trace = fmt != ".csv" or _is_can_csv(path, compressed)
    target = _CsvTarget(args.out, path)
    try:
        if is_trace:
            from hdhil.commands.options import require_raw_sensor_frames

            require_raw_sensor_frames(path, "filter")
            summary = filter_trace(path, cfg, target.writer)
        else:
            summary = filter_signal_csv(path, compressed, cfg, target.writer)
        target.commit()
    except OSError as exc:
        target.abort()
        if isinstance(exc, BrokenPipeError) or exc.filename is not None:
            raise  # a reader that stopped; an input that could not be read (named)
        raise UserError(f"--out {target.label}: cannot write ({exc.strerror or exc})") from None
    except BaseException:
        target.abort()
        raise
    print(summary.line(target.label), file=sys.stderr)
    for damage in summary.damage[:5]:
        print(f"hdhil: warning: {damage}", file=sys.stderr)
    if len(summary.damage) > 5:
        more = len(summary.damage) - 5
        print(f"hdhil: warning: {display_name(path)}: {more} more damaged spots", file=sys.stderr)
    return 1 if summary.damage else 0

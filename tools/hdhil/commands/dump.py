"""``hdhil dump``: a trace decoded with the DBCs as a table, CSV or timing statistics.

The options, the decoder of the trace and what is printed; reading, decoding and writing
the frames is :mod:`hdhil.can.traces.export`."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
from pathlib import Path

from hdhil.can.traces.clock import trace_clock
from hdhil.can.traces.decode import FrameDecoder
from hdhil.can.traces.export import (
    CycleCsv,
    FrameCsv,
    check_csv_target,
    export,
    parse_id_filter,
)
from hdhil.can.traces.reader import TraceReadResult, read_trace
from hdhil.can.traces.stats import StatsAccumulator, format_stats
from hdhil.core import jsonout
from hdhil.core.errors import UserError
from hdhil.core.files import display_name
from hdhil.core.numbers import arg_int


def trace_decoder(trace: Path) -> FrameDecoder:
    """The decoder of ``trace`` (:func:`hdhil.canopen.mapping.trace_decoder`: the
    project DBCs, with the drive's PDOs from the trace's sidecar for a run in a mapping
    from a DCF); a sidecar whose PDOs cannot be read is a one-line error."""
    from hdhil.canopen.mapping import trace_decoder as decoder_of

    try:
        return decoder_of(trace)
    except ValueError as exc:
        raise UserError(f"{trace}: {exc}") from None


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "dump",
        help="show a CAN trace decoded with the DBCs (table, CSV or timing statistics)",
        description="Read a CAN trace (.blf, .asc, .log, .csv, .trc; optionally .gz) and show "
        "its frames decoded with the control and truth DBCs, one line per frame in aligned "
        "columns: time (seconds since the trace's first frame, whatever the format), bus, "
        "ID, message, signals.  A value in the DBC's value table prints as its name and "
        "number (nmt_state=operational(5)); status/control words, object indices and EMCY "
        "codes in hex (statusword=0x0270, sdo_index=0x6041).  CSV and JSON keep plain "
        "numbers.  Exit code 0: clean read; 1: the "
        "trace is damaged (everything readable is shown, then a warning); 2: not a trace.",
    )
    parser.add_argument("trace", metavar="TRACE", help="trace file")
    parser.add_argument(
        "--absolute",
        action="store_true",
        help="table: wall-clock times (ISO 8601 UTC, microseconds) instead of seconds since "
        "the first frame (ASC: from its header date, else the sidecar's time_offset_s)",
    )
    parser.add_argument(
        "--limit",
        type=arg_int(0),
        metavar="N",
        help="print at most N frames (all are still counted)",
    )
    parser.add_argument(
        "--id",
        action="append",
        default=[],
        metavar="ID",
        help="only frames with this identifier (hex, e.g. 181 or 0x1F0001) or message name "
        "(e.g. CTRL_TPDO1); repeatable",
    )
    parser.add_argument(
        "--csv",
        metavar="OUT",
        help="write decoded signals to OUT as tidy data: one row per control cycle "
        "(time_s, sample, then SIGNAL_UNIT columns such as T_meas_Nm, velocity_radps, only "
        "the signals present; every value a plain decimal number, value-table names are "
        "not written); '-' for stdout",
    )
    parser.add_argument(
        "--per-frame",
        action="store_true",
        help="--csv: one row per decoded frame instead (time, bus, id, one column per "
        "Message.Signal)",
    )
    parser.add_argument(
        "--stats",
        action="store_true",
        help="per-ID rate, period jitter, frame time and per-bus worst-case load",
    )
    parser.add_argument("--json", action="store_true", help="statistics as JSON (implies --stats)")
    parser.add_argument(
        "--bitrate",
        type=arg_int(1, 100_000_000),
        default=1_000_000,
        metavar="BIT/S",
        help="bit rate for frame times and bus load (default: 1000000)",
    )
    parser.set_defaults(func=run)


def _silence_stdout() -> None:
    """After a broken pipe (``hdhil dump x | head``) keep the exit quiet."""
    with contextlib.suppress(Exception):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())


def run(args: argparse.Namespace) -> int:
    """Dump ``args.trace``; exit code 0 clean, 1 damaged (2 via UserError: not a trace)."""
    if args.limit is not None and args.limit < 0:
        raise UserError(f"--limit must be >= 0, got {args.limit}")
    if args.bitrate <= 0:
        raise UserError(f"--bitrate must be > 0, got {args.bitrate}")
    want_stats = bool(args.stats or args.json)
    want_table = args.csv is None and not want_stats
    if args.csv == "-" and want_stats:
        raise UserError("--csv - (stdout) cannot be combined with --stats/--json")
    if args.csv is not None:
        from hdhil.commands.options import check_outputs, trace_inputs

        check_outputs([(args.csv, "--csv")], trace_inputs(args.trace))
    decoder = trace_decoder(Path(args.trace))
    id_filter = names = None
    if args.id:
        try:
            id_filter, names = parse_id_filter(args.id, decoder)
        except ValueError as exc:
            raise UserError(f"--id {exc}") from None
    if args.csv is not None:
        try:
            check_csv_target(str(args.csv), Path(args.trace))
        except ValueError as exc:
            raise UserError(f"--csv {exc}") from None

    trace = read_trace(args.trace)
    from hdhil.can.traces.sidecar import read_metadata

    try:
        clock = trace_clock(trace.path, trace.format, trace.compressed,
                            trace.first_time or 0.0, read_metadata(trace.path),
                            args.absolute)  # fmt: skip
    except ValueError as exc:
        trace.close()
        raise UserError(f"--absolute: {exc}") from None
    if args.per_frame and args.csv is None:
        raise UserError("--per-frame needs --csv OUT")
    csv_out: FrameCsv | None = None
    if args.csv is not None:
        kind = FrameCsv if args.per_frame else CycleCsv
        csv_out = kind(str(args.csv), decoder, names, "--csv")
    stats = StatsAccumulator(args.bitrate, decoder) if want_stats else None
    try:
        result = export(
            trace,
            decoder,
            table=sys.stdout.write if want_table else None,
            limit=math.inf if args.limit is None else args.limit,
            id_filter=id_filter,
            csv_out=csv_out,
            stats=stats,
            clock=clock,
        )
        notes = []
        if id_filter is not None:
            notes.append(f"{result.selected} selected by --id")
        if want_table and result.printed < result.selected:
            notes.append(f"{result.printed} shown")
        _report(args, trace, result.counts.line(", ".join(notes), clock), csv_out, stats)
    except BrokenPipeError:
        _silence_stdout()
    return 1 if trace.damaged else 0


def _report(
    args: argparse.Namespace,
    trace: TraceReadResult,
    summary: str,
    csv_out: FrameCsv | None,
    stats: StatsAccumulator | None,
) -> None:
    """Print statistics, the summary line and damage warnings."""
    err = sys.stderr
    if stats is not None:
        result = stats.result()
        if args.json:
            result["trace"] = str(trace.path)
            result["damage"] = [d.as_dict() for d in trace.damage]
            jsonout.dump(result, sys.stdout, indent=2)
            sys.stdout.write("\n")
        else:
            print(format_stats(result))
            print(summary)
    elif csv_out is None:
        print(summary)
    sys.stdout.flush()
    if csv_out is not None:
        print(f"hdhil: wrote {csv_out.rows} rows to {csv_out.label}", file=err)
    if csv_out is not None or args.json:
        print(summary, file=err)
    for damage in trace.damage[:5]:
        print(f"hdhil: warning: {damage.describe(trace.path)}", file=err)
    name = display_name(trace.path)  # one line whatever the name holds
    if len(trace.damage) > 5:
        print(f"hdhil: warning: {name}: {len(trace.damage) - 5} more damaged spots", file=err)
    lines = [d.line for d in trace.damage if d.line is not None]
    if lines:  # text formats: how many lines could not be read, and where it starts
        print(f"hdhil: warning: {name}: {len(lines)} unreadable line"
              f"{'s' if len(lines) != 1 else ''}, the first at line {min(lines)}",
              file=err)  # fmt: skip

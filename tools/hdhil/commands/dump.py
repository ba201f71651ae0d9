"""``hdhil dump``: a trace decoded with the DBCs as a table, CSV or timing statistics."""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import math
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hdhil.can.traces.decode import DecodedFrame, FrameDecoder, FrameKind
from hdhil.can.traces.reader import TraceReadResult, read_trace
from hdhil.can.traces.stats import StatsAccumulator, format_stats
from hdhil.core.errors import UserError
from hdhil.core.files import AtomicOutput
from hdhil.core.numbers import arg_int


@dataclass
class _Summary:
    """Counts of every frame read (independent of --id and --limit)."""

    counts: dict[FrameKind, int] = field(default_factory=lambda: {k: 0 for k in FrameKind})
    first: float = math.inf
    last: float = -math.inf

    def add(self, frame: DecodedFrame) -> None:
        self.counts[frame.kind] += 1
        t = frame.time
        if t < self.first:
            self.first = t
        if t > self.last:
            self.last = t

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def line(self, note: str = "") -> str:
        c = {k.value: n for k, n in self.counts.items()}
        text = (
            f"{self.total} frames: {c['decoded']} decoded, {c['unknown']} unknown, "
            f"{c['malformed']} malformed, {c['error']} error, {c['remote']} remote"
        )
        if note:
            text += f"; {note}"
        if self.total:
            text += (
                f"; {self.first:.6f} .. {self.last:.6f} s (duration {self.last - self.first:.6f} s)"
            )
        return text


@dataclass(frozen=True)
class _IdFilter:
    keys: frozenset[tuple[bool, int]]
    ids: frozenset[int]

    def __call__(self, frame: DecodedFrame) -> bool:
        if frame.kind is FrameKind.ERROR:
            return False
        return (
            frame.is_extended_id,
            frame.arbitration_id,
        ) in self.keys or frame.arbitration_id in self.ids


def trace_decoder(trace: Path) -> FrameDecoder:
    """The decoder of ``trace`` (:func:`hdhil.canopen.mapping.trace_decoder`: the
    project DBCs, with the drive's PDOs from the trace's sidecar for a run in a mapping
    from a DCF); a sidecar whose PDOs cannot be read is a one-line error."""
    from hdhil.canopen.mapping import trace_decoder as decoder_of

    try:
        return decoder_of(trace)
    except ValueError as exc:
        raise UserError(f"{trace}: {exc}") from None


def _parse_id_filter(values: list[str], decoder: FrameDecoder) -> tuple[_IdFilter, set[str]]:
    """``--id`` values (message names or hex identifiers) -> filter and selected names."""
    keys: set[tuple[bool, int]] = set()
    ids: set[int] = set()
    names: set[str] = set()
    for value in values:
        text = value.strip()
        if text in decoder.by_name:
            _, message = decoder.by_name[text]
            keys.add((bool(message.is_extended_frame), int(message.frame_id)))
            names.add(text)
            continue
        try:
            number = int(text, 16)
        except ValueError:
            raise UserError(
                f"--id {value!r}: neither a message name ({', '.join(decoder.by_name)}) "
                "nor a hex identifier"
            ) from None
        if not 0 <= number <= 0x1FFFFFFF:
            raise UserError(f"--id {value!r}: identifier out of range")
        ids.add(number)
        names.update(m.name for (_, fid), (_, m) in decoder.lookup.items() if fid == number)
    return _IdFilter(frozenset(keys), frozenset(ids)), names


class _CsvOut:
    """Decoded frames as CSV, one row per frame (``--per-frame``), written through
    :class:`hdhil.core.files.AtomicOutput`: a regular file (or ``-``, stdout) only,
    replaced once complete; a device, FIFO, socket or directory is refused before the
    trace is read."""

    def __init__(self, target: str, decoder: FrameDecoder, messages: set[str] | None) -> None:
        self._out = AtomicOutput(target, "--csv")
        self.label = self._out.label
        self.decoder = decoder
        self.columns = decoder.columns(messages)
        self.index = {column: i for i, column in enumerate(self.columns, start=3)}
        self._file = self._out.__enter__().file
        assert self._file is not None
        self._writer = csv.writer(self._file, lineterminator="\n")
        self._width = 3 + len(self.columns)
        self.rows = 0
        self._header()

    def _header(self) -> None:
        self._write(["time", "bus", "id", *self.columns])

    def _write(self, row: list[str]) -> None:
        try:
            self._writer.writerow(row)
        except BrokenPipeError:
            raise
        except OSError as exc:
            self.abort()
            raise UserError(f"cannot write {self.label}: {exc.strerror or exc}") from None

    def add(self, frame: DecodedFrame) -> None:
        if frame.kind is not FrameKind.DECODED or frame.message is None:
            return
        row = [""] * self._width
        row[0] = f"{frame.time:.9f}"
        row[1] = frame.bus
        row[2] = "0x" + frame.id_text
        written = False
        for fmt in self.decoder.formats[frame.message]:
            i = self.index.get(fmt.column)
            if i is not None and fmt.name in frame.signals:
                row[i] = fmt.csv(frame.signals[fmt.name])
                written = True
        if written:
            self._write(row)
            self.rows += 1

    def commit(self) -> None:
        try:
            self._out.__exit__(None, None, None)
        except BrokenPipeError:
            raise
        except OSError as exc:
            self.abort()
            raise UserError(f"cannot write {self.label}: {exc.strerror or exc}") from None

    def abort(self) -> None:
        with contextlib.suppress(OSError):
            self._out.__exit__(RuntimeError, None, None)


class _CycleCsvOut(_CsvOut):
    """Tidy data (the default ``--csv``): one row per control cycle, one column per signal
    with its unit in the name (:mod:`hdhil.can.cycles`), only the signals that occur.

    Rows go to an unnamed spool file first, with a column for every signal a cycle can
    have; at the end the columns that never had a value are dropped while the spool is
    copied to the output (which is written as :class:`_CsvOut` writes it)."""

    def __init__(self, target: str, decoder: FrameDecoder, messages: set[str] | None) -> None:
        from hdhil.can.cycles import CycleBuilder

        self._builder = CycleBuilder(self._emit, decoder)
        self._keep_messages = messages
        self._spool = tempfile.TemporaryFile("w+", newline="", encoding="utf-8")  # noqa: SIM115
        self._spool_writer = csv.writer(self._spool, lineterminator="\n")
        self._formats = {col.name: _cycle_format(decoder, col) for col in self._builder.columns}
        super().__init__(target, decoder, messages)

    def _header(self) -> None:
        pass  # written at commit, once the columns present are known

    def add(self, frame: DecodedFrame) -> None:
        self._builder.add(frame)

    def _emit(self, time_s: float, sample: int, values: list[float | int | None]) -> None:
        fmt = self._formats
        cols = self._builder.columns
        self._spool_writer.writerow(
            [f"{time_s:.6f}", sample]
            + ["" if v is None else fmt[c.name](v) for c, v in zip(cols, values, strict=True)]
        )

    def commit(self) -> None:
        from hdhil.can.cycles import INDEX_COLUMNS

        self._builder.finish()
        cols = self._builder.columns
        keep = [
            i
            for i, col in enumerate(cols)
            if self._builder.present[i]
            and (self._keep_messages is None or col.message in self._keep_messages)
        ]
        self._write([*INDEX_COLUMNS, *(cols[i].name for i in keep)])
        self._spool.seek(0)
        picks = [0, 1, *(2 + i for i in keep)]
        for row in csv.reader(self._spool):
            self._write([row[i] for i in picks])
            self.rows += 1
        self._spool.close()
        super().commit()

    def abort(self) -> None:
        with contextlib.suppress(OSError):
            self._spool.close()
        super().abort()


def _cycle_format(decoder: FrameDecoder, column: Any) -> Any:
    """The CSV text function of a per-cycle column (the DBC signal's resolution)."""
    for fmt in decoder.formats[column.message]:
        if fmt.name == column.signal:
            return fmt.csv
    return str


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "dump",
        help="show a CAN trace decoded with the DBCs (table, CSV or timing statistics)",
        description="Read a CAN trace (.blf, .asc, .log, .csv, .trc; optionally .gz) and show "
        "its frames decoded with the control and truth DBCs.  Exit code 0: clean read; 1: the "
        "trace is damaged (everything readable is shown, then a warning); 2: not a trace.",
    )
    parser.add_argument("trace", metavar="TRACE", help="trace file")
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
        "the signals present); '-' for stdout",
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
    decoder = trace_decoder(Path(args.trace))
    id_filter, names = _parse_id_filter(args.id, decoder) if args.id else (None, None)
    if args.csv is not None:
        _check_csv_target(str(args.csv), Path(args.trace))

    trace = read_trace(args.trace)
    if args.per_frame and args.csv is None:
        raise UserError("--per-frame needs --csv OUT")
    csv_out: _CsvOut | None = None
    per_cycle: _CycleCsvOut | None = None
    if args.csv is not None:
        kind = _CsvOut if args.per_frame else _CycleCsvOut
        csv_out = kind(str(args.csv), decoder, names)
    per_cycle = csv_out if isinstance(csv_out, _CycleCsvOut) else None
    stats = StatsAccumulator(args.bitrate, decoder) if want_stats else None
    summary = _Summary()
    decode = want_table or csv_out is not None
    limit = math.inf if args.limit is None else args.limit
    write = sys.stdout.write
    selected = printed = 0
    try:
        try:
            with trace:
                if want_table:
                    write(f"{'time/s':>12}  {'bus':<7}  {'id':<8}  {'message':<12}  signals\n")
                for msg in trace:
                    frame = decoder.classify(msg, decode)
                    summary.add(frame)
                    if per_cycle is not None:
                        per_cycle.add(frame)  # every frame: --id selects its columns
                    if id_filter is not None and not id_filter(frame):
                        continue
                    selected += 1
                    if want_table and printed < limit:
                        write(decoder.describe(frame) + "\n")
                        printed += 1
                    if csv_out is not None and per_cycle is None:
                        csv_out.add(frame)
                    if stats is not None:
                        stats.add(frame)
            if csv_out is not None:
                csv_out.commit()
        except BaseException:
            if csv_out is not None:
                csv_out.abort()
            raise
        notes = []
        if id_filter is not None:
            notes.append(f"{selected} selected by --id")
        if want_table and printed < selected:
            notes.append(f"{printed} shown")
        _report(args, trace, summary.line(", ".join(notes)), csv_out, stats)
    except BrokenPipeError:
        _silence_stdout()
    return 1 if trace.damaged else 0


def _check_csv_target(target: str, trace: Path) -> None:
    if target == "-":
        return
    out = Path(target)
    if out.is_dir():
        raise UserError(f"--csv {out}: is a directory")
    if not out.parent.is_dir():
        raise UserError(f"--csv {out}: directory {out.parent} does not exist")
    try:
        same = out.exists() and out.resolve() == trace.resolve()
    except OSError:
        same = False
    if same:
        raise UserError(f"--csv {out}: would overwrite the trace being read")


def _report(
    args: argparse.Namespace,
    trace: TraceReadResult,
    summary: str,
    csv_out: _CsvOut | None,
    stats: StatsAccumulator | None,
) -> None:
    """Print statistics, the summary line and damage warnings."""
    err = sys.stderr
    if stats is not None:
        result = stats.result()
        if args.json:
            result["trace"] = str(trace.path)
            result["damage"] = [d.as_dict() for d in trace.damage]
            json.dump(result, sys.stdout, indent=2)
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
    if len(trace.damage) > 5:
        print(f"hdhil: warning: {trace.path}: {len(trace.damage) - 5} more damaged spots", file=err)
    lines = [d.line for d in trace.damage if d.line is not None]
    if lines:  # text formats: how many lines could not be read, and where it starts
        print(f"hdhil: warning: {trace.path}: {len(lines)} unreadable line"
              f"{'s' if len(lines) != 1 else ''}, the first at line {min(lines)}",
              file=err)  # fmt: skip

"""A decoded trace written out: the frame table, CSV and the counts of ``hdhil dump``.

:func:`export` reads a trace once, frame by frame, and hands every frame to what was
asked for: the table (one line per frame in aligned columns, its header first, times
from a :class:`~hdhil.can.traces.clock.TraceClock`), a CSV writer
(:class:`CycleCsv`, tidy data with one row per control cycle, or :class:`FrameCsv`, one
row per decoded frame) and the timing statistics (:mod:`~hdhil.can.traces.stats`), while
:class:`TraceCounts` counts every frame read. An :class:`IdFilter` selects the frames
shown, written and timed. A CSV file is written atomically: complete, or not at all.
"""

from __future__ import annotations

import contextlib
import csv
import math
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hdhil.can.traces.clock import TraceClock
from hdhil.can.traces.decode import DecodedFrame, FrameDecoder, FrameKind
from hdhil.can.traces.reader import TraceReadResult
from hdhil.can.traces.stats import StatsAccumulator
from hdhil.core.errors import UserError
from hdhil.core.files import AtomicOutput


def table_header(decoder: FrameDecoder, clock: TraceClock) -> str:
    """The first line of the frame table (:meth:`FrameDecoder.describe` gives the others)."""
    return decoder.header(clock.width, clock.label)


@dataclass
class TraceCounts:
    """Counts of every frame read (independent of the filter and the table's limit)."""

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

    def line(self, note: str = "", clock: TraceClock | None = None) -> str:
        """The summary line; first and last time as ``clock`` prints them (else as read)."""
        c = {k.value: n for k, n in self.counts.items()}
        text = (
            f"{self.total} frames: {c['decoded']} decoded, {c['unknown']} unknown, "
            f"{c['malformed']} malformed, {c['error']} error, {c['remote']} remote"
        )
        if note:
            text += f"; {note}"
        if self.total:
            if clock is None:
                span = f"{self.first:.6f} .. {self.last:.6f} s"
            elif clock.absolute:
                span = f"{clock.text(self.first)} .. {clock.text(self.last)}"
            else:
                span = f"{clock.seconds(self.first):.6f} .. {clock.seconds(self.last):.6f} s"
            text += f"; {span} (duration {self.last - self.first:.6f} s)"
        return text


@dataclass(frozen=True)
class IdFilter:
    """The frames with one of ``keys`` (extended flag, identifier) or ``ids`` (an
    identifier in either format); error frames never pass."""

    keys: frozenset[tuple[bool, int]]
    ids: frozenset[int]

    def __call__(self, frame: DecodedFrame) -> bool:
        if frame.kind is FrameKind.ERROR:
            return False
        return (
            frame.is_extended_id,
            frame.arbitration_id,
        ) in self.keys or frame.arbitration_id in self.ids


def parse_id_filter(values: list[str], decoder: FrameDecoder) -> tuple[IdFilter, set[str]]:
    """Message names or hex identifiers -> the filter and the names of the messages it
    selects; a value that is neither (or out of range) is a ValueError."""
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
            raise ValueError(
                f"{value!r}: neither a message name ({', '.join(decoder.by_name)}) "
                "nor a hex identifier"
            ) from None
        if not 0 <= number <= 0x1FFFFFFF:
            raise ValueError(f"{value!r}: identifier out of range")
        ids.add(number)
        names.update(m.name for (_, fid), (_, m) in decoder.lookup.items() if fid == number)
    return IdFilter(frozenset(keys), frozenset(ids)), names


def check_csv_target(target: str, trace: Path) -> None:
    """Refuse a CSV target (``-``: stdout) that is a directory, lies in a directory that
    does not exist, or is ``trace`` itself (ValueError naming it)."""
    if target == "-":
        return
    out = Path(target)
    if out.is_dir():
        raise ValueError(f"{out}: is a directory")
    if not out.parent.is_dir():
        raise ValueError(f"{out}: directory {out.parent} does not exist")
    try:
        same = out.exists() and out.resolve() == trace.resolve()
    except OSError:
        same = False
    if same:
        raise ValueError(f"{out}: would overwrite the trace being read")


class FrameCsv:
    """Decoded frames as CSV, one row per frame, written through
    :class:`hdhil.core.files.AtomicOutput` (``what`` names the target in its errors): a
    regular file (or ``-``, stdout) only, replaced once complete; a device, FIFO, socket
    or directory is refused here, before the trace is read."""

    def __init__(
        self, target: str, decoder: FrameDecoder, messages: set[str] | None, what: str = ""
    ) -> None:
        self._out = AtomicOutput(target, what)
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


class CycleCsv(FrameCsv):
    """Tidy data: one row per control cycle, one column per signal with its unit in the
    name (:mod:`hdhil.can.cycles`), only the signals that occur (of ``messages``, if
    given). Every frame goes to :meth:`add`: ``messages`` selects the columns.

    Rows go to an unnamed spool file first, with a column for every signal a cycle can
    have; at the end the columns that never had a value are dropped while the spool is
    copied to the output (which is written as :class:`FrameCsv` writes it)."""

    def __init__(
        self, target: str, decoder: FrameDecoder, messages: set[str] | None, what: str = ""
    ) -> None:
        from hdhil.can.cycles import CycleBuilder

        self._builder = CycleBuilder(self._emit, decoder)
        self._keep_messages = messages
        self._spool = tempfile.TemporaryFile("w+", newline="", encoding="utf-8")  # noqa: SIM115
        self._spool_writer = csv.writer(self._spool, lineterminator="\n")
        self._formats = {col.name: _cycle_format(decoder, col) for col in self._builder.columns}
        super().__init__(target, decoder, messages, what)

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


@dataclass
class Exported:
    """What :func:`export` read: the counts of every frame, the frames the filter
    selected, and the table lines written."""

    counts: TraceCounts
    selected: int = 0
    printed: int = 0


def export(
    trace: TraceReadResult,
    decoder: FrameDecoder,
    *,
    table: Callable[[str], Any] | None = None,
    limit: float = math.inf,
    id_filter: IdFilter | None = None,
    csv_out: FrameCsv | None = None,
    stats: StatsAccumulator | None = None,
    clock: TraceClock | None = None,
) -> Exported:
    """Read ``trace`` (closing it) and hand its frames out: the frame table to ``table``
    (header first, at most ``limit`` frame lines, times by ``clock``: default relative to
    the first frame), the selected frames (``id_filter``) to
    ``csv_out`` (a :class:`CycleCsv` gets every frame) and to ``stats``. The CSV is
    committed at the end and removed on any exception, Ctrl-C included."""
    per_cycle = csv_out if isinstance(csv_out, CycleCsv) else None
    decode = table is not None or csv_out is not None
    result = Exported(TraceCounts())
    if clock is None:
        clock = TraceClock(trace.first_time or 0.0)
    try:
        with trace:
            if table is not None:
                table(table_header(decoder, clock) + "\n")
            for msg in trace:
                frame = decoder.classify(msg, decode)
                result.counts.add(frame)
                if per_cycle is not None:
                    per_cycle.add(frame)  # every frame: the filter selects its columns
                if id_filter is not None and not id_filter(frame):
                    continue
                result.selected += 1
                if table is not None and result.printed < limit:
                    table(decoder.describe(frame, clock.text(frame.time)) + "\n")
                    result.printed += 1
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
    return result

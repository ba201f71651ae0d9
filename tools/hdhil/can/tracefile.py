"""``hdhil dump TRACE``: read a CAN trace and show what was on the bus, decoded with the DBCs.

Traces are whatever python-can writes, chosen by extension: ``.blf``, ``.asc``, ``.log``
(candump), ``.csv``, ``.trc``, the text formats optionally gzip-compressed (``.asc.gz``),
and ``.mf4`` (ASAM MDF 4, through asammdf).  Decoding
never needs channel numbers: control frames use 11-bit identifiers and truth frames
29-bit ones, so a frame is looked up by ``(is_extended_id, arbitration_id)`` across
both DBCs.  Channel numbers, where the format stores them, only label the bus.

Library API (no CLI needed; plot/tune/score tools reuse it):

* :func:`read_trace` opens and checks a trace and returns a :class:`TraceReadResult`,
  a one-shot stream of :class:`can.Message` that records damage (:class:`TraceDamage`)
  instead of dying on it.
* :func:`classify_frame` / :func:`decode_frame` turn a message into a
  :class:`DecodedFrame` (or ``None`` when it is not a decodable data frame).
* :func:`compute_stats` (or the streaming :class:`StatsAccumulator`) gives per-ID
  timing and per-bus worst-case load as a JSON-ready ``dict`` (keys documented on
  :meth:`StatsAccumulator.result`).

How the python-can readers (4.6) behave on damage, and what :func:`read_trace` does:

* BLF: a cut file ends *silently* (the reader decompresses what is there and stops), so
  the header's file size is compared with the bytes actually read; a corrupted container
  raises ``zlib.error``/``BLFParseError`` mid-iteration.  Reading stops at the first
  damage (no resynchronisation).  A header never finalised (writer not closed) is
  reported as damage too: the last container may be missing.
* CSV and candump ``.log``: a bad line raises ``ValueError`` (or ``binascii.Error``).
* ASC: lines that do not look like frames are skipped silently by the reader, lines
  that look like frames but do not parse raise ``ValueError``.
* TRC: lines with too few columns are skipped with a logged warning, bad numbers raise
  ``ValueError``.

For the line-based formats the lines are fed to the reader through a counting
wrapper: a line that makes the reader raise is reported with its line number and
reading resumes on the next line (the reader is restarted, with a synthetic header
line where it would otherwise eat one); a line the reader skipped although it is not a
legitimate non-frame line (comment, header, event) is reported as well; so is a last
line without a line end (a cut file).  At most :data:`MAX_DAMAGE` spots are recorded,
then reading stops.  python-can's own log warnings during reading become damage
entries instead of stray stderr output.
"""

from __future__ import annotations

import contextlib
import enum
import gzip
import itertools
import logging
import math
import os
import re
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import can

if TYPE_CHECKING:
    from cantools.database.can import Database
    from cantools.database.can import Message as DbcMessage

from hdhil.can.bittiming import frame_bits
from hdhil.can.busload import LOAD_LIMIT
from hdhil.core.errors import UserError
from hdhil.core.files import check_input
from hdhil.dbc import CHANNEL_NUMBER, codec, database, worst_case_frame_bits

#: Reader class per (lower-case) file extension.
READERS: dict[str, type[can.io.generic.MessageReader]] = {
    ".blf": can.BLFReader,
    ".asc": can.ASCReader,
    ".log": can.CanutilsLogReader,
    ".csv": can.CSVReader,
    ".trc": can.TRCReader,
    ".mf4": can.MF4Reader,
}

#: Formats read from a file name rather than a stream (no gzip, no byte counting).
_PATH_READERS = frozenset({".mf4"})

#: Bus label per python-can channel number (inverse of :data:`hdhil.dbc.CHANNEL_NUMBER`).
BUS_OF_CHANNEL: dict[int, str] = {number: name for name, number in CHANNEL_NUMBER.items()}

#: Reading stops after this many damaged spots (bad or wrongly skipped lines).
MAX_DAMAGE = 100

#: Bus label of a frame with neither channel information nor a known identifier.
UNKNOWN_BUS = "?"

_BLF_HEADER_SIZE = 144  # python-can BLFWriter: header as written before the file is closed
_CSV_HEADER = "timestamp,arbitration_id,extended,remote,error,dlc,data\n"
_ASC_FRAME = re.compile(r"\d+\.\d+\s+(\d+\s+(\w+\s+(Tx|Rx)|ErrorFrame)|CANFD)", re.I | re.A)
_ASC_HEADER = re.compile(
    r"(//|date\s|base\s|(no\s+)?internal\s+events|begin\s+triggerblock|end\s+triggerblock)",
    re.I,
)
_ASC_EVENT = re.compile(r"\d+\.\d+\s")
_TRC_FRAME_TYPES = frozenset({"DT", "FD", "FB", "FE", "BI", "RR"})
#: TRC record types that are not frames (PEAK TRC 2.x: status, error counter, event,
#: error frame): skipping them is not damage.
_TRC_OTHER_TYPES = frozenset({"ST", "EC", "EV", "ER"})
#: ASC: a token only a frame line carries (a skipped line with it is a damaged frame).
_ASC_DIRECTION = re.compile(r"(?:^|\s)(?:Rx|Tx)(?:\s|$)", re.I)
#: ASC: the shape of a frame line whatever its direction token ("t ch id dir d|r dlc").
_ASC_FRAMEISH = re.compile(r"\d+\.\d+\s+\d+\s+[0-9a-f]+x?\s+\S+\s+[dr]\s+[0-9a-f]", re.I | re.A)
#: Printable ASCII plus tab: a writer of these text formats writes nothing else.
_PRINTABLE = re.compile(r"[\t\x20-\x7e]*")


class TraceError(UserError):
    """The trace cannot be read at all (missing, empty, wrong format): one-line error."""


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class TraceDamage:
    """One damaged spot of a trace.

    ``frames_before`` frames were read before it; ``last_time`` is the timestamp of the
    last of them (``None`` if there was none); ``line`` is the 1-based line number for
    text formats; ``resumed`` tells whether frames after the spot were still read.
    """

    frames_before: int
    last_time: float | None
    reason: str
    line: int | None = None
    resumed: bool = False

    def describe(self, path: str | os.PathLike[str]) -> str:
        """One line: ``PATH: damaged after frame N (t=...s): reason``."""
        when = "n/a" if self.last_time is None else f"{self.last_time:.6f}s"
        where = f"line {self.line}: " if self.line is not None else ""
        tail = "; skipped, reading resumed" if self.resumed else ""
        head = f"{path}: damaged after frame {self.frames_before} (t={when})"
        return f"{head}: {where}{self.reason}{tail}"

    def as_dict(self) -> dict[str, Any]:
        return {
            "frames_before": self.frames_before,
            "last_time": self.last_time,
            "line": self.line,
            "reason": self.reason,
            "resumed": self.resumed,
        }


class _StreamError(Exception):
    """Reading the file itself failed (e.g. a cut gzip stream): no line to skip."""


class _LineSource:
    """The file object handed to a python-can text reader: counts lines, allows injection.

    Blank lines are dropped (every reader ignores them, the CSV reader would choke on
    them).  ``pending`` holds the lines handed out since the last frame, so lines the
    reader skipped can be checked afterwards.
    """

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream
        self._inject: list[str] = []
        self.lineno = 0
        self.pending: list[tuple[int | None, str]] = []
        self.last_line_terminated = True

    def __iter__(self) -> _LineSource:
        return self

    def __next__(self) -> str:
        if self._inject:
            line = self._inject.pop(0)
            self.pending.append((None, line))
            return line
        while True:
            try:
                line = next(self._stream)
            except StopIteration:
                raise
            except Exception as exc:
                raise _StreamError(f"{type(exc).__name__}: {exc}") from exc
            self.lineno += 1
            self.last_line_terminated = line.endswith("\n")
            if line.strip():
                break
        self.pending.append((self.lineno, line))
        return line

    def inject(self, *lines: str) -> None:
        """Hand out ``lines`` (synthetic, no line number) before the rest of the file."""
        self._inject.extend(lines)

    def close(self) -> None:
        self._stream.close()


class _CountingReader:
    """The binary file object handed to the BLF reader: counts the bytes it reads."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream
        self.bytes_read = 0

    def read(self, size: int = -1) -> bytes:
        data = self._stream.read(size)
        self.bytes_read += len(data)
        return data

    def close(self) -> None:
        self._stream.close()


class _LogCapture(logging.Handler):
    """Turns python-can reader warnings into damage entries while a trace is read."""

    def __init__(self, sink: Callable[[str], None]) -> None:
        super().__init__(logging.WARNING)
        self._sink = sink

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if message.startswith("TRCReader: Failed to parse message"):
            return  # the skipped line itself is checked and reported with its number
        self._sink(message)


def _one_line(text: str, limit: int = 160) -> str:
    """``text`` as one printable ASCII line of at most ``limit`` characters."""
    text = " ".join(text.split()).encode("ascii", "backslashreplace").decode("ascii")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _split_suffix(path: Path) -> tuple[str, bool]:
    """``(format extension, gzip-compressed)`` of ``path``, e.g. ``(".asc", True)``."""
    suffixes = [s.lower() for s in path.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        return (suffixes[-2] if len(suffixes) >= 2 else ""), True
    return (suffixes[-1] if suffixes else ""), False


def supported_extensions() -> str:
    return ", ".join(READERS) + " (optionally .gz)"


class TraceReadResult:
    """A trace being read: iterate it once to get its frames as :class:`can.Message`.

    Channels are normalised to python-can channel numbers (control 0, truth 1) where the
    format stores them, else ``None``: candump names like ``can1`` become ``1``, TRC's
    1-based bus column is shifted to 0-based.  ``damage`` and ``frame_count`` are
    complete once the iteration has ended.  Use it as a context manager (or exhaust it)
    to close the file.
    """

    def __init__(self, path: Path, fmt: str, compressed: bool) -> None:
        self.path = path
        self.format = fmt
        self.compressed = compressed
        self.damage: list[TraceDamage] = []
        self.frame_count = 0
        self.last_time: float | None = None
        self.first_time: float | None = None
        self._reader: can.io.generic.MessageReader | None = None
        self._source: _LineSource | None = None
        self._binary: _CountingReader | None = None
        self._prev_time: float | None = None  # timestamp of the frame before the last one
        self._last_frame_line: int | None = None  # text line that gave the last frame
        self._frames: Iterator[can.Message] = iter(())
        self._generator: Iterator[can.Message] | None = None
        self._stopped = False

    # -- public

    @property
    def damaged(self) -> bool:
        return bool(self.damage)

    def __iter__(self) -> Iterator[can.Message]:
        return self._frames

    def __enter__(self) -> TraceReadResult:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        close = getattr(self._generator, "close", None)
        if close is not None:
            close()
        self._close_file()

    # -- internals

    def _add_damage(self, reason: str, line: int | None = None, resumed: bool = False) -> None:
        if self._stopped:
            return
        self.damage.append(
            TraceDamage(self.frame_count, self.last_time, reason, line, resumed=resumed)
        )
        if len(self.damage) >= MAX_DAMAGE:
            self.damage.append(
                TraceDamage(
                    self.frame_count,
                    self.last_time,
                    f"{MAX_DAMAGE} damaged spots, stopped reading",
                    line,
                )
            )
            self._stopped = True

    def _open(self) -> None:
        reader_cls = READERS[self.format]
        if self.format in _PATH_READERS:
            if self.compressed:
                raise ValueError(f"{self.format} traces cannot be read gzip-compressed")
            if self.format == ".mf4":
                from hdhil.can.traces.formats import MF4_MISSING, mf4_available

                if not mf4_available():
                    raise TraceError(MF4_MISSING)
            self._reader = reader_cls(str(self.path))
            return
        opener: Callable[..., Any] = gzip.open if self.compressed else open
        if issubclass(reader_cls, can.io.generic.BinaryIOMessageReader):
            self._binary = _CountingReader(opener(self.path, "rb"))
            self._reader = reader_cls(self._binary)
        else:
            stream = opener(self.path, "rt", encoding="utf-8", errors="replace", newline=None)
            self._source = _LineSource(stream)
            self._reader = reader_cls(self._source)

    def _close_file(self) -> None:
        if self.format in _PATH_READERS and self._reader is not None:
            with contextlib.suppress(Exception):
                self._reader.stop()
        for handle in (self._source, self._binary):
            if handle is not None:
                with contextlib.suppress(Exception):
                    handle.close()

    def _normalise_channel(self, msg: can.Message) -> None:
        channel = msg.channel
        if self.format == ".csv":
            msg.channel = None
        elif self.format == ".trc":
            columns = getattr(self._reader, "columns", {})
            msg.channel = channel - 1 if "B" in columns and isinstance(channel, int) else None
        elif not isinstance(channel, int):
            msg.channel = can.util.channel2int(channel)

    def _skipped_line_problem(self, text: str) -> str | None:
        """Why a line the reader skipped without complaint is damage (``None``: it is not)."""
        line = text.strip()
        invalid = f"not a valid {self.format[1:].upper()} line"
        if not _PRINTABLE.fullmatch(line):
            return f"{invalid} (a byte outside printable ASCII)"
        if self.format == ".asc":
            if _ASC_FRAME.match(line):
                return "frame line skipped by the reader"
            if _ASC_HEADER.match(line):
                return None  # header, comment, trigger block
            if _ASC_EVENT.match(line):
                # A timestamped event ("Start of measurement", a status): no direction
                # token.  A skipped line with Rx/Tx is a frame line the reader lost.
                lost = _ASC_DIRECTION.search(line) or _ASC_FRAMEISH.match(line)
                return "frame line skipped by the reader" if lost else None
            return invalid
        if self.format == ".trc":
            if line.startswith(";"):
                return None
            tokens = line.split()
            columns: dict[str, int] = getattr(self._reader, "columns", {})
            if "T" not in columns or "O" not in columns:
                return None if "FFFFFFFF" in tokens else invalid  # v1.x: bus information
            try:  # a well-formed record of a type that is no frame (status, event, ...)
                float(tokens[columns["O"]])
                kind = tokens[columns["T"]]
            except (IndexError, ValueError):
                return invalid
            if kind in _TRC_FRAME_TYPES:
                return "frame line with missing columns"
            return None if kind in _TRC_OTHER_TYPES else f"{invalid} (record type {kind!r})"
        return invalid  # CSV and candump readers never skip a non-blank line on purpose

    def _check_skipped(self, keep_last: bool) -> None:
        source = self._source
        if source is None or not source.pending:
            return
        lines = source.pending[:-1] if keep_last else source.pending
        for lineno, text in lines:
            if lineno is None:
                continue
            if self.format == ".csv" and lineno == 1:
                continue  # the header line
            problem = self._skipped_line_problem(text)
            if problem is not None:
                self._add_damage(problem, lineno, resumed=True)
        source.pending.clear()

    def _restart_text(self) -> Iterator[can.Message]:
        """A fresh iterator of the same text reader, continuing after the bad line."""
        assert self._reader is not None and self._source is not None
        if self.format == ".csv":
            self._source.inject(_CSV_HEADER)  # the reader skips one header line
        elif self.format == ".asc":
            self._source.inject("no internal events logged\n")  # ends its header scan
        return iter(self._reader)

    def _generate(self) -> Iterator[can.Message]:
        assert self._reader is not None
        capture = _LogCapture(self._add_damage)
        can_logger = logging.getLogger("can.io")
        can_logger.addHandler(capture)
        try:
            it = iter(self._reader)
            while not self._stopped:
                try:
                    msg = next(it)
                except StopIteration:
                    self._check_skipped(keep_last=False)
                    self._check_end()
                    break
                except Exception as exc:
                    if not self._on_exception(exc) or self._stopped:
                        break
                    it = self._restart_text()
                    continue
                if self._source is not None:
                    self._last_frame_line = (
                        self._source.pending[-1][0] if self._source.pending else None
                    )
                self._check_skipped(keep_last=True)
                self._normalise_channel(msg)
                if self.first_time is None:
                    self.first_time = msg.timestamp
                self.frame_count += 1
                self._prev_time, self.last_time = self.last_time, msg.timestamp
                yield msg
        finally:
            can_logger.removeHandler(capture)
            self._close_file()

    def _on_exception(self, exc: Exception) -> bool:
        """Record a reader exception; return whether reading can resume after it.

        Only a line of a text trace that made the reader raise can be skipped; an error
        of the file itself (BLF container, gzip stream) ends the reading.
        """
        if isinstance(exc, _StreamError):
            reason = _one_line(str(exc))
        else:
            reason = _one_line(f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__)
        source = self._source
        if (
            source is None
            or isinstance(exc, _StreamError)
            or not source.pending
            or source.pending[-1][0] is None
        ):
            self._check_skipped(keep_last=False)
            self._add_damage(reason)
            return False
        lineno, _ = source.pending.pop()
        self._check_skipped(keep_last=False)
        self._add_damage(reason, lineno, resumed=True)
        return True

    def _check_end(self) -> None:
        """After a clean end of iteration: a cut BLF, a text file cut mid-line."""
        source = self._source
        if source is not None and not source.last_line_terminated:
            last = source.lineno
            if self.damage and self.damage[-1].line == last:
                return  # that line is already reported
            if self._last_frame_line == last:  # the cut line still gave a frame: suspect it
                self.damage.append(
                    TraceDamage(
                        self.frame_count - 1,
                        self._prev_time,
                        "last line has no line end (file cut?)",
                        last,
                    )
                )
            else:
                self._add_damage("last line has no line end (file cut?)", last)
            return
        reader = self._reader
        if isinstance(reader, can.BLFReader) and self._binary is not None:
            read, expected = self._binary.bytes_read, int(reader.file_size)
            if expected == _BLF_HEADER_SIZE and read > expected:
                self._add_damage(
                    "BLF header never finalised (writer not closed); the last frames may be missing"
                )
            elif read < expected:
                self._add_damage(f"file truncated: {read} of {expected} bytes")

    def _start(self) -> None:
        """Open the reader and read up to the first frame; raise TraceError if there is none."""
        label = f"{self.format[1:].upper()}{' (gzip)' if self.compressed else ''}"
        try:
            self._open()
        except TraceError:
            raise
        except Exception as exc:
            self._close_file()
            reason = _one_line(str(exc)) or type(exc).__name__
            raise TraceError(f"{self.path}: not a readable {label} trace ({reason})") from None
        generator = self._generator = self._generate()
        try:
            first = next(generator)
        except StopIteration:
            first = None
        except Exception as exc:  # pragma: no cover - _generate catches reader errors
            generator.close()
            raise TraceError(f"{self.path}: not a readable {label} trace ({exc})") from None
        if first is None:
            generator.close()
            if self.damage:
                d = self.damage[0]
                where = f"line {d.line}: " if d.line is not None else ""
                raise TraceError(f"{self.path}: not a readable {label} trace ({where}{d.reason})")
            raise TraceError(f"{self.path}: no CAN frames in this {label} trace")
        self._frames = itertools.chain((first,), generator)


def read_trace(path: str | os.PathLike[str]) -> TraceReadResult:
    """Open the trace at ``path`` and check it holds frames.

    Returns a :class:`TraceReadResult` to iterate once (frames are streamed, not loaded).
    Raises :class:`TraceError` (a :class:`hdhil.cli.UserError`) for a missing file, a
    directory, an empty file, an unsupported extension, or a file that yields no frame.
    Damage after the first frame is recorded in ``result.damage``, never raised.
    """
    p = Path(path)
    fmt, compressed = _split_suffix(p)
    try:
        check_input(p)  # a regular file (a FIFO or a device would block or never end)
    except UserError as exc:
        raise TraceError(str(exc)) from None
    if fmt not in READERS:
        raise TraceError(
            f"{p}: unsupported trace format {fmt or '(no extension)'!r}; "
            f"use {supported_extensions()}"
        )
    try:
        size = p.stat().st_size
    except OSError as exc:
        raise TraceError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if size == 0:
        raise TraceError(f"{p}: empty file")
    if not os.access(p, os.R_OK):
        raise TraceError(f"{p}: permission denied")
    result = TraceReadResult(p, fmt, compressed)
    result._start()
    return result


# -------------------------------------------------------------------------- decoding


class FrameKind(enum.Enum):
    """What a frame turned out to be."""

    DECODED = "decoded"  #: known identifier, right length, decoded
    UNKNOWN = "unknown"  #: identifier in neither DBC
    MALFORMED = "malformed"  #: known identifier, payload length differs from the DBC
    ERROR = "error"  #: error frame
    REMOTE = "remote"  #: remote frame

    __hash__ = object.__hash__  # members are singletons; Enum's hash is slow Python code


@dataclass(frozen=True, slots=True)
class DecodedFrame:
    """One frame, classified and (if ``kind`` is DECODED) decoded to physical values.

    ``bus`` is the label used for grouping: from the channel when the trace has one
    (``control``/``truth``, ``chN`` for other numbers), else from the DBC that defines
    the identifier, else ``"?"``.  ``message_bus`` is the DBC the identifier belongs to
    (``None`` if unknown); a frame whose channel disagrees is ``on_wrong_bus``.
    """

    time: float
    bus: str
    arbitration_id: int
    is_extended_id: bool
    kind: FrameKind
    data: bytes
    message: str | None = None
    message_bus: str | None = None
    signals: dict[str, float | int] = field(default_factory=dict)
    definition: DbcMessage | None = field(default=None, repr=False, compare=False)

    @property
    def id_text(self) -> str:
        """Identifier as hex: 3 digits for base frames, 8 for extended ones."""
        return format_id(self.arbitration_id, self.is_extended_id)

    @property
    def on_wrong_bus(self) -> bool:
        return (
            self.message_bus is not None
            and self.bus in CHANNEL_NUMBER
            and self.bus != self.message_bus
        )


def format_id(arbitration_id: int, extended: bool) -> str:
    return f"{arbitration_id:08X}" if extended else f"{arbitration_id:03X}"


def _decimals(value: float) -> int:
    """Decimal places needed to print multiples of ``value`` exactly (at most 9)."""
    for digits in range(10):
        scaled = abs(value) * 10**digits
        if abs(scaled - round(scaled)) < 1e-9 * max(1.0, scaled):
            return digits
    return 9


@dataclass(frozen=True)
class _SignalFormat:
    name: str
    column: str  # "Message.Signal"
    unit: str
    decimals: int | None  # None: IEEE float signal
    is_float32: bool
    unit_suffix: str  # " Nm", or "" without a unit

    def text(self, value: float | int) -> str:
        """Table text: resolution-exact for scaled integers, 6 significant digits for floats."""
        if self.decimals is None:
            return f"{value:.6g}"
        if self.decimals == 0:
            return str(round(value))
        return f"{value:.{self.decimals}f}"

    def csv(self, value: float | int) -> str:
        """CSV text: exact (shortest round-trip repr for IEEE floats)."""
        if self.decimals is None:
            if self.is_float32:  # the shortest text that reads back as the same float32
                import numpy as np

                return str(np.float32(value))
            return repr(float(value))
        return self.text(value)


def _signal_formats(message: DbcMessage) -> tuple[_SignalFormat, ...]:
    formats = []
    for sig in message.signals:
        if sig.is_float:
            decimals = None
        else:
            decimals = max(_decimals(float(sig.scale)), _decimals(float(sig.offset)))
        formats.append(
            _SignalFormat(
                name=sig.name,
                column=f"{message.name}.{sig.name}",
                unit=sig.unit or "",
                decimals=decimals,
                is_float32=sig.is_float and sig.length == 32,
                unit_suffix=f" {sig.unit}" if sig.unit else "",
            )
        )
    return tuple(formats)


class FrameDecoder:
    """Classifies and decodes frames against a set of DBCs (default: control and truth).

    The lookup ``(is_extended_id, arbitration_id) -> (bus, message)`` is built once; an
    identifier defined in two DBCs is refused.
    """

    def __init__(self, databases: Mapping[str, Database] | None = None) -> None:
        if databases is None:
            databases = {bus: database(bus) for bus in CHANNEL_NUMBER}
        self.databases = dict(databases)
        self.lookup: dict[tuple[bool, int], tuple[str, DbcMessage]] = {}
        self.formats: dict[str, tuple[_SignalFormat, ...]] = {}
        for bus, db in self.databases.items():
            for message in db.messages:
                key = (bool(message.is_extended_frame), int(message.frame_id))
                if key in self.lookup:
                    other = self.lookup[key]
                    raise ValueError(
                        f"identifier {format_id(key[1], key[0])} is defined twice: "
                        f"{other[0]}.{other[1].name} and {bus}.{message.name}"
                    )
                self.lookup[key] = (bus, message)
                self.formats[message.name] = _signal_formats(message)
        self.by_name: dict[str, tuple[str, DbcMessage]] = {
            m.name: (bus, m) for bus, m in self.lookup.values()
        }

    def columns(self, messages: Iterable[str] | None = None) -> list[str]:
        """``Message.Signal`` column names in DBC order (optionally only ``messages``)."""
        wanted = None if messages is None else set(messages)
        return [
            fmt.column
            for name, formats in self.formats.items()
            if wanted is None or name in wanted
            for fmt in formats
        ]

    def classify(self, msg: can.Message, decode: bool = True) -> DecodedFrame:
        """Classify ``msg`` and, if ``decode`` and it is a well-formed known frame, decode it."""
        ext = bool(msg.is_extended_id)
        arb = int(msg.arbitration_id)
        data = bytes(msg.data or b"")
        entry = None if msg.is_error_frame else self.lookup.get((ext, arb))
        message_bus, definition = entry if entry is not None else (None, None)
        channel = msg.channel
        if isinstance(channel, int):
            bus = BUS_OF_CHANNEL.get(channel, f"ch{channel}")
        else:
            bus = message_bus or UNKNOWN_BUS
        if msg.is_error_frame:
            kind = FrameKind.ERROR
        elif msg.is_remote_frame:
            kind = FrameKind.REMOTE
        elif definition is None:
            kind = FrameKind.UNKNOWN
        elif len(data) != definition.length:
            kind = FrameKind.MALFORMED
        else:
            kind = FrameKind.DECODED
        signals: dict[str, float | int] = {}
        if kind is FrameKind.DECODED and decode:
            try:
                signals = dict(definition.decode(data, decode_choices=False))  # type: ignore[union-attr, arg-type]
            except Exception:
                kind = FrameKind.MALFORMED
        return DecodedFrame(
            time=float(msg.timestamp),
            bus=bus,
            arbitration_id=arb,
            is_extended_id=ext,
            kind=kind,
            data=data,
            message=definition.name if definition is not None else None,
            message_bus=message_bus,
            signals=signals,
            definition=definition,
        )

    def decode(self, msg: can.Message) -> DecodedFrame | None:
        """The decoded frame, or ``None`` if ``msg`` is not a well-formed known data frame."""
        frame = self.classify(msg)
        return frame if frame.kind is FrameKind.DECODED else None

    def describe(self, frame: DecodedFrame) -> str:
        """The table line of ``frame``: time, bus, ID, name, signals (or raw data and a flag)."""
        name = frame.message or ""
        kind = frame.kind
        if kind is FrameKind.DECODED:
            signals = frame.signals
            body = "  ".join(
                f"{fmt.name}={fmt.text(signals[fmt.name])}{fmt.unit_suffix}"
                for fmt in self.formats[name]
                if fmt.name in signals
            )
        else:
            raw = frame.data.hex(" ").upper()
            if kind is FrameKind.UNKNOWN:
                name, body = "UNKNOWN", f"[{len(frame.data)}] {raw}"
            elif kind is FrameKind.MALFORMED:
                expected = frame.definition.length if frame.definition is not None else "?"
                body = f"MALFORMED: {len(frame.data)} bytes, DBC says {expected}: {raw}"
            elif kind is FrameKind.ERROR:
                name, body = "ERROR FRAME", raw
            else:
                body = "REMOTE frame request"
        if frame.on_wrong_bus:
            body += f"  (WRONG BUS: defined in {frame.message_bus}.dbc)"
        id_text = "-" if kind is FrameKind.ERROR else frame.id_text
        return f"{frame.time:12.6f}  {frame.bus:<7}  {id_text:<8}  {name:<12}  {body}".rstrip()


_DEFAULT_DECODER: FrameDecoder | None = None


def default_decoder() -> FrameDecoder:
    """The shared decoder for the project's control and truth DBCs."""
    global _DEFAULT_DECODER
    if _DEFAULT_DECODER is None:
        _DEFAULT_DECODER = FrameDecoder()
    return _DEFAULT_DECODER


def classify_frame(msg: can.Message, decode: bool = True) -> DecodedFrame:
    """Classify (and decode) ``msg`` with the project DBCs; see :meth:`FrameDecoder.classify`."""
    return default_decoder().classify(msg, decode)


def decode_frame(msg: can.Message) -> DecodedFrame | None:
    """Decode ``msg`` with the project DBCs; ``None`` unless it is a well-formed known frame."""
    return default_decoder().decode(msg)


# ----------------------------------------------------------------------------- stats


@dataclass
class _IdStats:
    bus: str
    arbitration_id: int
    is_extended_id: bool
    name: str | None
    count: int = 0
    first: float = 0.0
    last: float = 0.0
    payload: int = 0
    malformed: int = 0
    # Welford accumulation of the periods
    n_periods: int = 0
    mean_period: float = 0.0
    m2_period: float = 0.0
    min_period: float = math.inf
    max_period: float = -math.inf

    def add(self, time: float, payload: int, malformed: bool) -> None:
        if self.count:
            period = time - self.last
            self.n_periods += 1
            delta = period - self.mean_period
            self.mean_period += delta / self.n_periods
            self.m2_period += delta * (period - self.mean_period)
            if period < self.min_period:
                self.min_period = period
            if period > self.max_period:
                self.max_period = period
        else:
            self.first = time
        self.count += 1
        self.last = time
        if payload > self.payload:
            self.payload = payload
        self.malformed += malformed


class _CounterTrack:
    """One cycle counter as one sender sends it on one channel: which counts went
    missing for good (lost), which came late (reordered) and which came twice.

    ``last`` is the highest count seen (modulo ``modulus``).  A count one ahead is in
    order; further ahead is a jump whose skipped counts become *pending*; a count behind
    ``last`` that is pending arrived late (reordered, no longer missing), one seen
    recently is a duplicate.  Pending counts older than :data:`REORDER_WINDOW` frames
    are lost for good; at the end every pending count is lost.
    """

    __slots__ = ("frames", "gaps", "last", "lost", "modulus", "pending", "recent",
                 "reordered", "repeats")  # fmt: skip

    def __init__(self, modulus: int) -> None:
        self.modulus = modulus
        self.last: int | None = None
        self.pending: dict[int, int] = {}  # count -> frame number when it went missing
        self.recent: dict[int, int] = {}  # count -> frame number last seen
        self.frames = self.gaps = self.lost = self.reordered = self.repeats = 0

    def add(self, value: int) -> None:
        self.frames += 1
        n = self.frames
        value %= self.modulus  # SYNC counts 1..240: 240 is 0 here, so steps wrap right
        last = self.last
        if last is None:
            self.last = value
            self.recent[value] = n
            return
        step = (value - last) % self.modulus
        if step == 0:
            self.repeats += 1  # the newest count again: a duplicate
        elif step <= self.modulus // 2:
            if step > 1:  # a jump: the skipped counts are missing (for now)
                self.gaps += 1
                for i in range(1, step):
                    self.pending[(last + i) % self.modulus] = n
            self.last = value
        elif value in self.pending:
            del self.pending[value]  # a count given up as missing arrived late
            self.reordered += 1
        elif n - self.recent.get(value, -REORDER_WINDOW - 1) <= REORDER_WINDOW:
            self.repeats += 1  # an older count seen again: a duplicate
        else:
            self.last = value  # far behind, never missed: the sender restarted its count
        self.recent[value] = n
        if len(self.recent) > 2 * REORDER_WINDOW:
            self.recent = {k: v for k, v in self.recent.items() if n - v <= REORDER_WINDOW}
        if self.pending and n - min(self.pending.values()) > REORDER_WINDOW:
            expired = [k for k, v in self.pending.items() if n - v > REORDER_WINDOW]
            for k in expired:
                del self.pending[k]
            self.lost += len(expired)

    def result(self) -> dict[str, int]:
        return {"gaps": self.gaps, "missing": self.lost + len(self.pending),
                "reordered": self.reordered, "repeats": self.repeats}  # fmt: skip


#: Frames of one counter after which a count still missing is lost for good (a
#: reordered frame arrives at most a few frames late).
REORDER_WINDOW = 32


@dataclass
class _BusStats:
    frames: int = 0
    first: float = math.inf
    last: float = -math.inf
    actual_bits: int = 0
    unknown_frames: int = 0
    unknown_ids: set[tuple[bool, int]] = field(default_factory=set)
    malformed: int = 0
    errors: int = 0
    remote: int = 0


_BUS_ORDER = {name: i for i, name in enumerate(CHANNEL_NUMBER)}


def _bus_share(
    load: float | None, count: int, span: float, frame_percent: float, bus_span: float
) -> float:
    """One identifier's share of its bus's worst-case load (``load_percent`` of a bus).

    A cyclic identifier, seen over at least half the bus's duration, counts with its own
    rate.  A sporadic one (an SDO exchange, a burst of configuration writes at boot, a
    single EMCY) would count with the rate inside its burst, which can exceed the whole
    bus; it counts with its frames spread over the bus's duration instead.
    """
    if load is not None and span >= 0.5 * bus_span:
        return load
    if bus_span <= 0.0:
        return 0.0
    return count * frame_percent / bus_span


def _bus_sort_key(bus: str) -> tuple[int, str]:
    return (_BUS_ORDER.get(bus, len(_BUS_ORDER) + (bus == UNKNOWN_BUS)), bus)


class StatsAccumulator:
    """Streaming per-(bus, ID) timing statistics and per-bus worst-case load."""

    def __init__(self, bitrate: int = 1_000_000, decoder: FrameDecoder | None = None) -> None:
        if bitrate <= 0:
            raise ValueError(f"bitrate must be > 0, got {bitrate}")
        self.bitrate = bitrate
        self.decoder = decoder or default_decoder()
        self._ids: dict[tuple[str, bool, int], _IdStats] = {}
        self._buses: dict[str, _BusStats] = {}
        self.counts = {kind: 0 for kind in FrameKind}
        self.first = math.inf
        self.last = -math.inf
        # Cycle counters whose gaps show lost frames: (name, signal index, modulus).
        self._counters = {
            (codec("control", "SYNC").frame_id, False): ("SYNC.sync_counter", 0, 240),
            (codec("control", "DRIVE_RPDO1").frame_id, False): ("DRIVE_RPDO1.cycle", 2, 256),
        }
        self._counter_codecs = {key: codec("control", name.split(".")[0])
                                for key, (name, *_rest) in self._counters.items()}  # fmt: skip
        # One track per (channel, sender's identifier, counter): frames logged on two
        # channels, or two senders of one counter, are never mixed into one sequence.
        self._tracks: dict[tuple[str, int, str], _CounterTrack] = {}

    def _count(self, frame: DecodedFrame) -> None:
        key = (frame.arbitration_id, frame.is_extended_id)
        name, index, modulus = self._counters[key]
        try:
            value = int(self._counter_codecs[key].decode(frame.data)[index])
        except ValueError:
            return
        # Works for both counters: SYNC runs 1..240 and wraps to 1, so (value - last) mod
        # 240 is 1 across the wrap as well; the command's cycle counter runs mod 256.
        track_key = (frame.bus, frame.arbitration_id, name)
        track = self._tracks.get(track_key)
        if track is None:
            track = self._tracks[track_key] = _CounterTrack(modulus)
        track.add(value)

    @property
    def gaps(self) -> dict[str, dict[str, int]]:
        """Per counter, summed over channels and senders: ``gaps`` (jumps forward),
        ``missing`` (counts never seen: lost frames), ``reordered`` (counts that came
        late), ``repeats`` (duplicates)."""
        out = {name: dict.fromkeys(("gaps", "missing", "reordered", "repeats"), 0)
               for name, *_rest in self._counters.values()}  # fmt: skip
        for (_, _, name), track in self._tracks.items():
            for k, v in track.result().items():
                out[name][k] += v
        return out

    @property
    def gaps_by_channel(self) -> list[dict[str, Any]]:
        """One entry per channel, sender and counter (see :attr:`gaps`)."""
        return [
            {"bus": bus, "sender": format_id(frame_id, False), "counter": name, "frames": t.frames,
             **t.result()}
            for (bus, frame_id, name), t in sorted(
                self._tracks.items(), key=lambda kv: (_bus_sort_key(kv[0][0]), kv[0][1:])
            )
        ]  # fmt: skip

    def add(self, frame: DecodedFrame | can.Message) -> None:
        if isinstance(frame, can.Message):
            frame = self.decoder.classify(frame, decode=False)
        self.counts[frame.kind] += 1
        t = frame.time
        if t < self.first:
            self.first = t
        if t > self.last:
            self.last = t
        bus = self._buses.get(frame.bus)
        if bus is None:
            bus = self._buses[frame.bus] = _BusStats()
        bus.frames += 1
        if t < bus.first:
            bus.first = t
        if t > bus.last:
            bus.last = t
        if frame.kind is FrameKind.ERROR:
            bus.errors += 1
            return  # error frames have no identifier and no schedule
        if frame.kind is FrameKind.UNKNOWN:
            bus.unknown_frames += 1
            bus.unknown_ids.add((frame.is_extended_id, frame.arbitration_id))
        elif frame.kind is FrameKind.MALFORMED:
            bus.malformed += 1
        elif frame.kind is FrameKind.REMOTE:
            bus.remote += 1
        key = (frame.bus, frame.is_extended_id, frame.arbitration_id)
        stats = self._ids.get(key)
        if stats is None:
            stats = self._ids[key] = _IdStats(
                frame.bus, frame.arbitration_id, frame.is_extended_id, frame.message
            )
        payload = 0 if frame.kind is FrameKind.REMOTE else len(frame.data)
        stats.add(t, payload, frame.kind is FrameKind.MALFORMED)
        remote = frame.kind is FrameKind.REMOTE
        ident = (frame.arbitration_id, frame.is_extended_id)
        bus.actual_bits += frame_bits(*ident, remote, bytes(frame.data[:8]))
        if frame.kind is FrameKind.DECODED and ident in self._counters:
            self._count(frame)

    def result(self) -> dict[str, Any]:
        """The statistics as a JSON-ready dict.

        Top level: ``bitrate`` (bit/s), ``load_limit_percent`` (the 60 % budget),
        ``frames``, ``decoded``, ``unknown``, ``malformed``, ``error``, ``remote`` (frame
        counts), ``start``/``end``/``duration`` (s; ``None`` without frames), ``ids`` and
        ``buses``.

        ``ids``: one entry per (bus, identifier), ordered by bus then identifier, with
        ``bus``, ``id`` (int), ``id_hex``, ``extended``, ``name`` (``None`` if unknown),
        ``count``, ``malformed`` (count), ``rate_hz`` ((count - 1) / time span),
        ``period_ms`` (mean period), ``jitter_std_us`` (population std of the periods),
        ``jitter_max_us`` (max |period - mean period|), ``payload_bytes`` (largest seen),
        ``worst_case_bits`` and ``frame_time_us`` (worst case incl. stuffing and
        interframe space, :func:`hdhil.dbc.worst_case_frame_bits`), ``load_percent``
        (rate x worst-case bits / bitrate).  Rate, period, jitter and load are ``None``
        for an identifier seen once (or with no time span).

        ``buses``: per bus label: ``duration`` (s, first to last frame of that bus),
        ``frames``, ``load_percent`` (worst-case load, sum over its identifiers; an
        identifier seen over less than half the bus's duration, such as a burst of SDO
        frames at boot, counts with its frames spread over the bus's duration rather
        than with the rate inside its burst),
        ``actual_load_percent`` (the frames' exact bits incl. real stuff bits,
        :mod:`hdhil.can.bittiming`, over the duration),
        ``over_limit`` (load above ``load_limit_percent``), ``unknown_ids`` (distinct),
        ``unknown_frames``, ``malformed``, ``error_frames``, ``remote_frames``.
        """
        ids = []
        loads: dict[str, float] = {}
        bus_spans = {name: b.last - b.first for name, b in self._buses.items()}
        for key in sorted(self._ids, key=lambda k: (_bus_sort_key(k[0]), k[1], k[2])):
            s = self._ids[key]
            bits = worst_case_frame_bits(s.payload, s.is_extended_id)
            span = s.last - s.first
            if s.count >= 2 and span > 0:
                rate = (s.count - 1) / span
                mean = s.mean_period
                std = math.sqrt(max(s.m2_period, 0.0) / s.n_periods)
                jmax = max(s.max_period - mean, mean - s.min_period)
                load = rate * bits / self.bitrate * 100.0
                period_ms, std_us, jmax_us = mean * 1e3, std * 1e6, jmax * 1e6
            else:
                rate = period_ms = std_us = jmax_us = load = None
            loads[s.bus] = loads.get(s.bus, 0.0) + _bus_share(
                load, s.count, span, bits / self.bitrate * 100.0, bus_spans.get(s.bus, 0.0)
            )
            ids.append(
                {
                    "bus": s.bus,
                    "id": s.arbitration_id,
                    "id_hex": format_id(s.arbitration_id, s.is_extended_id),
                    "extended": s.is_extended_id,
                    "name": s.name,
                    "count": s.count,
                    "malformed": s.malformed,
                    "rate_hz": rate,
                    "period_ms": period_ms,
                    "jitter_std_us": std_us,
                    "jitter_max_us": jmax_us,
                    "payload_bytes": s.payload,
                    "worst_case_bits": bits,
                    "frame_time_us": bits / self.bitrate * 1e6,
                    "load_percent": load,
                }
            )
        buses = {}
        for name in sorted(self._buses, key=_bus_sort_key):
            b = self._buses[name]
            load = loads.get(name, 0.0)
            span = b.last - b.first
            buses[name] = {
                "duration": span,
                "frames": b.frames,
                "load_percent": load,
                "actual_load_percent": (
                    b.actual_bits / self.bitrate / span * 100.0 if span > 0 else None
                ),
                "over_limit": load > LOAD_LIMIT * 100.0,
                "unknown_ids": len(b.unknown_ids),
                "unknown_frames": b.unknown_frames,
                "malformed": b.malformed,
                "error_frames": b.errors,
                "remote_frames": b.remote,
            }
        any_frames = self.last >= self.first
        return {
            "bitrate": self.bitrate,
            "load_limit_percent": LOAD_LIMIT * 100.0,
            "frames": sum(self.counts.values()),
            **{kind.value: n for kind, n in self.counts.items()},
            "start": self.first if any_frames else None,
            "end": self.last if any_frames else None,
            "duration": self.last - self.first if any_frames else None,
            "ids": ids,
            "buses": buses,
            # Gaps in the cycle counters (lost frames): per counter, the number of jumps and
            # of counts missing: SYNC.sync_counter (CiA 301, 1..240), DRIVE_RPDO1.cycle.
            "counter_gaps": self.gaps,
            # The same per channel and sender (two channels logging the same frames, or a
            # counter sent by two nodes, each checked on its own).
            "counter_gaps_by_channel": self.gaps_by_channel,
        }


def compute_stats(
    frames: Iterable[can.Message | DecodedFrame], bitrate: int = 1_000_000
) -> dict[str, Any]:
    """Per-ID timing and per-bus worst-case load of ``frames`` (streamed); see
    :meth:`StatsAccumulator.result` for the keys."""
    acc = StatsAccumulator(bitrate)
    for frame in frames:
        acc.add(frame)
    return acc.result()


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def format_stats(stats: Mapping[str, Any]) -> str:
    """Human-readable text of a :func:`compute_stats` result."""
    lines = [
        f"{'bus':<7}  {'id':<8}  {'name':<12}  {'count':>8}  {'rate/Hz':>9}  "
        f"{'period/ms':>9}  {'jit.std/us':>10}  {'jit.max/us':>10}  {'bytes':>5}  "
        f"{'frame/us':>8}  {'load/%':>6}"
    ]
    for s in stats["ids"]:
        name = s["name"] or "UNKNOWN"
        if s["malformed"]:
            name += f" ({s['malformed']} malformed)"
        lines.append(
            f"{s['bus']:<7}  {s['id_hex']:<8}  {name:<12}  {s['count']:>8}  "
            f"{_fmt(s['rate_hz'], '9.2f')}  {_fmt(s['period_ms'], '9.4f')}  "
            f"{_fmt(s['jitter_std_us'], '10.2f')}  {_fmt(s['jitter_max_us'], '10.2f')}  "
            f"{s['payload_bytes']:>5}  {s['frame_time_us']:>8.1f}  "
            f"{_fmt(s['load_percent'], '6.2f')}"
        )
    kbit = stats["bitrate"] / 1000
    for bus, b in stats["buses"].items():
        flag = f"  OVER THE {stats['load_limit_percent']:.0f} % BUDGET" if b["over_limit"] else ""
        extras = [f"unknown IDs {b['unknown_ids']} ({b['unknown_frames']} frames)"]
        if b["malformed"]:
            extras.append(f"malformed {b['malformed']}")
        if b["error_frames"]:
            extras.append(f"error frames {b['error_frames']}")
        if b["remote_frames"]:
            extras.append(f"remote frames {b['remote_frames']}")
        lines.append(
            f"bus {bus}: {b['duration']:.6f} s, {b['frames']} frames, worst-case load "
            f"{b['load_percent']:.1f} % of {kbit:g} kbit/s{flag}, actual "
            f"{_fmt(b.get('actual_load_percent'), '.1f')} %; {', '.join(extras)}"
        )
    for g in stats.get("counter_gaps_by_channel", []):
        lines.append(
            f"cycle counter {g['counter']} on {g['bus']} from {g['sender']}: {g['frames']} "
            f"frames, {g['missing']} lost ({g['gaps']} gaps), {g['reordered']} reordered, "
            f"{g['repeats']} duplicated"
        )
    return "\n".join(lines)


# ------------------------------------------------------------------------------- CLI

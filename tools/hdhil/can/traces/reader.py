"""Reading a trace: every frame it holds, and where it is damaged.

:func:`read_trace` opens and checks a file of any format python-can reads
(:mod:`hdhil.can.traces.formats`) and returns a :class:`TraceReadResult`, a one-shot
stream of :class:`can.Message` that records damage (:class:`TraceDamage`) instead of
dying on it.  python-can's readers stop, skip silently or raise on damage, depending on
the format; a trace cut by a crash or edited by hand must still show what it holds and
say where it is damaged.  So the reader is fed through counting wrappers: a bad text
line is reported with its number and reading resumes after it; a skipped line that is
no legitimate non-frame line, a cut last line, a truncated or never finalised BLF and
python-can's own warnings are reported too (per format: :class:`TraceReadResult`).
Channels come out as python-can channel numbers (control 0, truth 1).

Memory stays bounded whatever the file holds: text is read line by line, a line at most
:data:`hdhil.core.files.MAX_LINE_CHARS` long (a longer one ends the reading as damage);
lines the reader skipped are checked as they go; reading gives up on a file with no
frame in its first :data:`MAX_LEADING_CHARS` characters; a BLF object or container
larger than :data:`MAX_BLF_OBJECT_BYTES` (also once decompressed) ends the reading as
damage.
"""

from __future__ import annotations

import contextlib
import gc
import gzip
import itertools
import logging
import os
import re
import sys
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import can
from can.io.player import MESSAGE_READERS

from hdhil.can.traces import formats
from hdhil.can.traces.formats import (
    MF4_MISSING,
    SUPPORTED_SUFFIXES,
    supported_extensions,
    trace_format,
)
from hdhil.core.errors import UserError
from hdhil.core.files import MAX_LINE_CHARS, check_input, display_name

#: Reader class per (lower-case) file extension: python-can's own table, the one
#: :class:`can.LogReader` picks from, for the formats hdhil writes.
READERS: dict[str, type[can.io.generic.MessageReader]] = {
    suffix: MESSAGE_READERS[suffix] for suffix in SUPPORTED_SUFFIXES
}

#: Formats read from a file name rather than a stream (no gzip, no byte counting).
_PATH_READERS = frozenset({".mf4"})

#: Reading stops after this many damaged spots (bad or wrongly skipped lines).
MAX_DAMAGE = 100
#: A text trace with no frame in its first this many characters is refused.
MAX_LEADING_CHARS = 1024 * 1024
#: Largest BLF object, and largest decompressed log container, read (python-can writes
#: containers of 128 KiB); a larger one ends the reading as damage.
MAX_BLF_OBJECT_BYTES = 16 * 1024 * 1024
#: Skipped lines held before they are checked.
_PENDING_MAX = 32

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
        head = f"{display_name(path)}: damaged after frame {self.frames_before} (t={when})"
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
    """Reading the file itself failed (e.g. a cut gzip stream, a line longer than any
    trace line): no line to skip, reading ends.  ``line``: where, if known."""

    def __init__(self, message: str, line: int | None = None) -> None:
        super().__init__(message)
        self.line = line


class _LineSource:
    """The file object handed to a python-can text reader: counts lines, allows injection.

    Blank lines are dropped (every reader ignores them, the CSV reader would choke on
    them).  ``pending`` holds the lines handed out since the last frame, so lines the
    reader skipped can be checked afterwards.
    """

    def __init__(
        self,
        stream: TextIO,
        check_skipped: Callable[[list[tuple[int | None, str]]], bool] | None = None,
    ) -> None:
        self._stream = stream
        self._inject: list[str] = []
        self._check = check_skipped
        self.lineno = 0
        self.pending: list[tuple[int | None, str]] = []
        self.last_line_terminated = True
        #: Characters read while ``leading_limit`` is set (until the first frame); more
        #: than that ends the reading.
        self.chars = 0
        self.leading_limit: int | None = MAX_LEADING_CHARS

    def __iter__(self) -> _LineSource:
        return self

    def __next__(self) -> str:
        if self._inject:
            line = self._inject.pop(0)
            self.pending.append((None, line))
            return line
        if len(self.pending) >= _PENDING_MAX and self._check is not None:
            # Every line handed out before this request was skipped by the reader (the
            # readers read no line ahead): check them now rather than hold them all.
            lines, self.pending = self.pending, []
            if not self._check(lines):
                raise StopIteration  # too much damage: reading ends
        readline = self._stream.readline
        while True:
            try:
                line = readline(MAX_LINE_CHARS + 1)
            except Exception as exc:
                raise _StreamError(f"{type(exc).__name__}: {exc}") from exc
            if not line:
                raise StopIteration
            self.lineno += 1
            terminated = self.last_line_terminated = line[-1] == "\n"
            if not terminated and len(line) > MAX_LINE_CHARS:
                raise _StreamError(
                    f"line longer than {MAX_LINE_CHARS} characters (no text trace line)",
                    self.lineno,
                )
            if self.leading_limit is not None:
                self.chars += len(line)
                if self.chars > self.leading_limit:
                    raise _StreamError(
                        f"no CAN frame in the first {self.leading_limit} characters",
                        self.lineno,
                    )
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
    """The binary file object handed to the BLF reader: counts the bytes it reads, and
    refuses a read larger than :data:`MAX_BLF_OBJECT_BYTES` (an object size read from a
    damaged header)."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream
        self.bytes_read = 0

    def read(self, size: int = -1) -> bytes:
        if size is None or not 0 <= size <= MAX_BLF_OBJECT_BYTES:
            raise _StreamError(
                f"a damaged BLF size field: {size} bytes to read at byte {self.bytes_read} "
                f"(accepted: 0 to {MAX_BLF_OBJECT_BYTES})"
            )
        data = self._stream.read(size)
        self.bytes_read += len(data)
        return data

    def close(self) -> None:
        self._stream.close()


class _BoundedBLFReader(can.BLFReader):
    """python-can's BLF reader with its memory bounded: a log container decompresses to
    at most :data:`MAX_BLF_OBJECT_BYTES` and the part of an object carried over into the
    next container (``_tail``) stays under that size too; beyond, :class:`_StreamError`.
    The loop is python-can's own (4.6), with those two checks."""

    def __iter__(self) -> Iterator[can.Message]:
        from can.io import blf

        header_size = blf.OBJ_HEADER_BASE_STRUCT.size
        while True:
            data = self.file.read(header_size)
            if not data:
                break
            signature, _, _, obj_size, obj_type = blf.OBJ_HEADER_BASE_STRUCT.unpack(data)
            if signature != b"LOBJ":
                raise blf.BLFParseError()
            obj_data = self.file.read(obj_size - header_size)
            self.file.read(obj_size % 4)  # padding
            if obj_type != blf.LOG_CONTAINER:
                continue
            method, _ = blf.LOG_CONTAINER_STRUCT.unpack_from(obj_data)
            container = obj_data[blf.LOG_CONTAINER_STRUCT.size :]
            if method == blf.NO_COMPRESSION:
                data = container
            elif method == blf.ZLIB_DEFLATE:
                inflate = zlib.decompressobj()
                data = inflate.decompress(container, MAX_BLF_OBJECT_BYTES)
                if inflate.unconsumed_tail:
                    raise _StreamError(
                        f"a BLF log container decompressing to more than "
                        f"{MAX_BLF_OBJECT_BYTES} bytes"
                    )
            else:
                logging.getLogger("can.io.blf").warning("Unknown compression method (%d)", method)
                continue
            yield from self._parse_container(data)
            if len(self._tail) > MAX_BLF_OBJECT_BYTES:
                raise _StreamError(
                    f"a BLF object spanning more than {MAX_BLF_OBJECT_BYTES} bytes of containers"
                )
        self.stop()


READERS[".blf"] = _BoundedBLFReader


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


def _open_by_name(
    reader_cls: type[can.io.generic.MessageReader], path: Path
) -> can.io.generic.MessageReader:
    """``reader_cls(path)`` for a reader that opens the file itself (MF4: asammdf).  On a
    damaged file the half-built reader is collected at once with its finaliser's errors
    silenced (asammdf's ``MDF4.__del__`` raises on an object its constructor left
    incomplete, which Python would print as "Exception ignored in ..."); the error is
    raised as :class:`ValueError` with the library's one-line message."""
    hook = sys.unraisablehook
    sys.unraisablehook = lambda unraisable: None
    try:
        try:
            return reader_cls(os.fspath(path))
        except Exception as exc:  # any library error: the file is not readable
            reason = _one_line(str(exc)) or type(exc).__name__
        gc.collect()  # the reader left by the exception, while the hook is silent
        raise ValueError(reason)
    finally:
        sys.unraisablehook = hook


class TraceReadResult:
    """A trace being read: iterate it once to get its frames as :class:`can.Message`.

    Channels are normalised to python-can channel numbers (control 0, truth 1) where the
    format stores them, else ``None``: candump names like ``can1`` become ``1``, TRC's
    1-based bus column is shifted to 0-based.  ``damage`` and ``frame_count`` are
    complete once the iteration has ended.  Use it as a context manager (or exhaust it)
    to close the file.

    How the python-can readers (4.6) behave on damage, and what is done about it:

    * BLF: a cut file ends *silently* (the reader decompresses what is there and stops),
      so the header's file size is compared with the bytes actually read; a corrupted
      container raises ``zlib.error``/``BLFParseError`` mid-iteration.  Reading stops at
      the first damage (no resynchronisation).  A header never finalised (writer not
      closed) is reported as damage too: the last container may be missing.
    * CSV and candump ``.log``: a bad line raises ``ValueError`` (or ``binascii.Error``).
    * ASC: lines that do not look like frames are skipped silently by the reader, lines
      that look like frames but do not parse raise ``ValueError``.
    * TRC: lines with too few columns are skipped with a logged warning, bad numbers raise
      ``ValueError``.

    For the line-based formats the lines are fed to the reader through a counting
    wrapper: a line that makes the reader raise is reported with its line number and
    reading resumes on the next line (the reader is restarted, with a synthetic header
    line where it would otherwise eat one); a line the reader skipped although it is not
    a legitimate non-frame line (comment, header, event) is reported as well; so is a
    last line without a line end (a cut file).  At most :data:`MAX_DAMAGE` spots are
    recorded, then reading stops.  python-can's own log warnings during reading become
    damage entries instead of stray stderr output.
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
            if self.format == ".mf4" and not formats.mf4_available():
                raise TraceError(MF4_MISSING)
            self._reader = _open_by_name(reader_cls, self.path)
            return
        opener: Callable[..., Any] = gzip.open if self.compressed else open
        if issubclass(reader_cls, can.io.generic.BinaryIOMessageReader):
            self._binary = _CountingReader(opener(self.path, "rb"))
            self._reader = reader_cls(self._binary)
        else:
            stream = opener(self.path, "rt", encoding="utf-8", errors="replace", newline=None)
            self._source = _LineSource(stream, self._check_lines)
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
        self._check_lines(source.pending[:-1] if keep_last else source.pending)
        source.pending.clear()

    def _check_lines(self, lines: list[tuple[int | None, str]]) -> bool:
        """Record the lines among ``lines`` (skipped by the reader) that are damage;
        whether reading goes on (not after :data:`MAX_DAMAGE` spots)."""
        for lineno, text in lines:
            if lineno is None:
                continue
            if self.format == ".csv" and lineno == 1:
                continue  # the header line
            problem = self._skipped_line_problem(text)
            if problem is not None:
                self._add_damage(problem, lineno, resumed=True)
        return not self._stopped

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
                    if self._source is not None:
                        self._source.leading_limit = None
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
            if exc.line is not None:
                self._check_skipped(keep_last=False)
                self._add_damage(reason, exc.line)
                return False
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
    fmt, compressed = trace_format(p)
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

"""The trace writer: every frame a run's tap hands over, into one file.

The writer is python-can's :func:`can.Logger`, chosen by the file extension
(:mod:`hdhil.can.traces.formats`).  A simulated run stamps its frames with simulated time
plus the wall-clock time at its start (``time_offset``), so traces carry real dates and
tools that expect them (can-utils, asammdf, Vector's) read them as any logger's.

:class:`WriterProcess` runs that writer in a child process: the run hands it frames in
batches through a pipe, so formatting and compressing the file happens on the other core,
off the 1 kHz loop.  The pipe is bounded (:data:`PIPE_BYTES`, large enough to ride out a
writer that gets no CPU for a while): a writer that falls behind makes the run wait,
it never drops a frame.  Handing a batch on is safe against Ctrl-C (a batch goes whole or
not at all, and is counted with it).  If the run dies (even by SIGKILL) the child reads
what was sent up to then and closes the file properly.

A run may also hand the child a listener of its own (``child_listener``: a factory the
child calls, e.g. the rig's live evaluation), so that what it does per frame runs on the
writer's core too.  The child feeds it exactly the frames it writes, in order, as
:class:`FrameRecord` (read-only, with :class:`can.Message`'s field names, the timestamps
without the trace's offset), and sends its ``result()`` back when the input ends
(:meth:`WriterProcess.child_result`; the protocol is described at :func:`_writer_main`).

Traces are written atomically: to a temporary beside the target, renamed into place when
complete together with the sidecar (:mod:`hdhil.can.traces.sidecar`) and any companion
file of the run (its fault log), as one output: all of them or none, the old files left
as they were (:func:`hdhil.core.files.commit_together`).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.util
import operator
import os
import pickle
import struct
import time
import traceback
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, NamedTuple

import can

from hdhil.can.groups import FrameGroup
from hdhil.can.simbus import _snapshot_fast, received_copy
from hdhil.can.traces import formats
from hdhil.can.traces.blfobjects import bulk_blf_writer
from hdhil.can.traces.formats import (
    GZIP_SUFFIXES,
    MF4_MISSING,
    SUPPORTED_SUFFIXES,
    supported_formats,
    trace_format,
)
from hdhil.can.traces.sidecar import metadata_path, metadata_text
from hdhil.core.errors import UserError
from hdhil.core.files import (
    check_output,
    commit_together,
    discard_temporary,
    release_temporary,
    temporary_dir_for,
    temporary_for,
)
from hdhil.core.signals import (
    leave_stopping_signals_to_parent,
    signals_deferred,
    stopping_signals_blocked,
)

try:
    import fcntl
except ImportError:  # not on Windows
    fcntl = None  # type: ignore[assignment]


def check_trace_path(path: Path) -> None:
    """Refuse unsupported formats and unwritable places before a run starts."""
    fmt, compressed = trace_format(path)
    if fmt not in SUPPORTED_SUFFIXES or (compressed and fmt not in GZIP_SUFFIXES):
        shown = "".join(path.suffixes[-2:]) if compressed else fmt
        raise ValueError(
            f"unsupported trace format {shown or '(none)'!r} for {path}: "
            f"use one of {supported_formats()}"
        )
    if fmt == ".mf4" and not formats.mf4_available():
        raise ValueError(MF4_MISSING)
    if path.parent and not path.parent.exists():
        raise ValueError(f"cannot write trace {path}: directory {path.parent} does not exist")
    check_output(path, "trace")  # only a regular file is ever overwritten
    check_output(metadata_path(path), "sidecar")  # nor for the sidecar written with it


def open_writer(path: Path) -> can.io.generic.MessageWriter:
    """A python-can writer for ``path``, with a clear error for unsupported formats."""
    check_trace_path(path)
    try:
        return can.Logger(str(path))
    except OSError as exc:
        raise ValueError(f"cannot write trace {path}: {exc.strerror or exc}") from None
    except (ImportError, NotImplementedError):
        raise ValueError(MF4_MISSING) from None


#: Frames per batch handed to the writer process: about 70 lockstep cycles.
BATCH_FRAMES = 512

#: A partly filled batch is handed on at the latest after this long (wall time), so a
#: slowly running bus still reaches the file within a fraction of a second.
BATCH_MAX_AGE_S = 0.25

#: The capacity asked for the pipe to the writer process (bytes; Linux, where an
#: unprivileged process may ask up to ``/proc/sys/fs/pipe-max-size``): about 40 000
#: frames, some seconds of a lockstep run, so a writer that gets no CPU for a while (the
#: machine's other core busy) does not stall the loop at once.  Elsewhere, or when
#: refused, the system's default (64 KiB on Linux).
PIPE_BYTES = 1 << 20

#: How long ``stop`` waits for the writer process to finish the file.
WRITER_EXIT_TIMEOUT_S = 120.0

#: One frame on the pipe: timestamp, identifier, extended, remote, error frame, received,
#: DLC, channel number, payload (up to 8 bytes, with its length: a Pascal string).
_RECORD = struct.Struct("<dI????BB9p")
#: A record of a run with CAN FD frames (``WriterProcess(fd=True)``): the same fields
#: with a payload of up to 64 bytes, then the frame's FD and bit-rate-switch flags.
_FD_RECORD = struct.Struct("<dI????BB65p??")
#: The fields of a record, read from a frame in one call (tools, tests).
_FIELDS = operator.attrgetter("timestamp", "arbitration_id", "is_extended_id", "is_remote_frame",
                              "is_error_frame", "is_rx", "dlc", "channel", "data")  # fmt: skip


def _records(frames: Iterable[can.Message | FrameGroup]) -> list[bytes]:
    """The pipe records of ``frames`` (a comprehension: the cheapest way to pack a batch);
    a :class:`FrameGroup` gives the records of its frames, joined."""
    pack = _RECORD.pack
    return [pack(msg.timestamp, msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
                 msg.is_error_frame, msg.is_rx, msg.dlc, msg.channel, msg.data)
            if msg.__class__ is not FrameGroup else _group_records(msg)
            for msg in frames]  # fmt: skip


#: Three records in one pack (the truth channel's groups): the same bytes as three
#: packs of :data:`_RECORD`, which has no padding.
_RECORDS3 = struct.Struct("<" + _RECORD.format[1:] * 3)


def _group_records(group: FrameGroup) -> bytes:
    """The pipe records of a group's frames (received data frames), joined."""
    ts, channel, ids, extended, payloads = group
    if len(ids) == 3:
        (a, b, c), (da, db, dc) = ids, payloads
        return _RECORDS3.pack(
            ts, a, extended, False, False, True, len(da), channel, da,
            ts, b, extended, False, False, True, len(db), channel, db,
            ts, c, extended, False, False, True, len(dc), channel, dc,
        )  # fmt: skip
    pack = _RECORD.pack
    return b"".join([pack(ts, i, extended, False, False, True, len(d), channel, d)
                     for i, d in zip(ids, payloads, strict=True)])  # fmt: skip


def _fd_records(frames: Iterable[can.Message | FrameGroup]) -> list[bytes]:
    """:func:`_records` in the FD format (:data:`_FD_RECORD`)."""
    pack = _FD_RECORD.pack
    out = []
    for msg in frames:
        if msg.__class__ is FrameGroup:
            ts, channel, ids, extended, payloads = msg  # type: ignore[misc]
            out.append(b"".join([pack(ts, i, extended, False, False, True, len(d), channel, d,
                                      False, False)
                                 for i, d in zip(ids, payloads, strict=True)]))  # fmt: skip
        else:
            out.append(_fd_pack(msg))  # type: ignore[arg-type]
    return out


def _fd_pack(msg: can.Message) -> bytes:
    return _FD_RECORD.pack(*_FIELDS(msg), msg.is_fd, msg.bitrate_switch)


_Record = tuple[float, int, bool, bool, bool, bool, int, int, bytes]


class FrameRecord(NamedTuple):
    """One frame as a child listener gets it: the fields of a pipe record under
    :class:`can.Message`'s names (a tuple: made in one call per frame, where a message
    costs several)."""

    timestamp: float
    arbitration_id: int
    is_extended_id: bool
    is_remote_frame: bool
    is_error_frame: bool
    is_rx: bool
    dlc: int
    channel: int
    data: bytes


#: A factory, called once in the writer's child process, of a listener fed every frame
#: written (``on_frames`` with a list of :class:`FrameRecord`, or ``on_message_received``
#: per frame) whose ``result()`` goes back to the parent when the input ends.  Under the
#: ``spawn`` start method it must be picklable.
ChildListenerFactory = Callable[[], Any]


def _failure(what: str, exc: BaseException) -> str:
    """One line for an exception in the child, with the place it was raised."""
    where = traceback.extract_tb(exc.__traceback__)[-1:] if exc.__traceback__ else []
    at = f" (at {Path(where[0].filename).name}:{where[0].lineno})" if where else ""
    return f"{what}: {type(exc).__name__}: {exc}{at}"


class _ChildListening:
    """The child's side of a child listener: built from its factory, fed each batch,
    asked for its result.  An exception in it is kept for the parent (the trace is
    written on regardless) and the listener is fed no more."""

    def __init__(self, factory: ChildListenerFactory, fd: bool = False) -> None:
        self.fd = fd
        self.error: str | None = None
        self.listener: Any = None
        self._feed: Callable[[list[FrameRecord]], None] | None = None
        try:
            self.listener = factory()
            self._feed = getattr(self.listener, "on_frames", None) or self._each
        except Exception as exc:
            self.error = _failure("the trace writer's child listener could not start", exc)

    def _each(self, frames: list[FrameRecord]) -> None:
        on_message = self.listener.on_message_received
        for frame in frames:
            on_message(frame)

    def feed(self, batch: bytes) -> None:
        if self._feed is None:
            return
        try:
            if self.fd:
                self._feed([FrameRecord._make(r[:9]) for r in _FD_RECORD.iter_unpack(batch)])
            else:
                self._feed(list(map(FrameRecord._make, _RECORD.iter_unpack(batch))))
        except Exception as exc:
            self.error = _failure("the trace writer's child listener failed", exc)
            self._feed = None

    def result(self) -> tuple[str, Any]:
        """``("ok", the listener's result)`` or ``("error", text)``, picklable."""
        if self.error is not None or self.listener is None:
            return "error", self.error
        try:
            value = self.listener.result()
            self.listener.stop()
            pickle.dumps(value)  # what the pipe will do: fail here, with a clear error
        except Exception as exc:
            return "error", _failure("the trace writer's child listener failed at the end", exc)
        return "ok", value


def _message_checked(f: _Record, offset: float) -> can.Message:
    ts, can_id, extended, remote, error, rx, dlc, channel, data = f
    return can.Message(timestamp=ts + offset, arbitration_id=can_id, is_extended_id=extended,
                       is_remote_frame=remote, is_error_frame=error, is_rx=rx, dlc=dlc,
                       data=data, channel=channel, check=False)  # fmt: skip


_new_message = object.__new__


def _message_fast(f: _Record, offset: float) -> can.Message:
    """:func:`_message_checked` field by field (the constructor's keyword handling costs
    more than the writer's own work; the writers read the same values either way)."""
    ts, can_id, extended, remote, error, rx, dlc, channel, data = f
    msg = _new_message(can.Message)
    msg.timestamp = ts + offset
    msg.arbitration_id = can_id
    msg.is_extended_id = extended
    msg.is_remote_frame = remote
    msg.is_error_frame = error
    msg.is_rx = rx
    msg.channel = channel
    msg.dlc = dlc
    msg.data = bytearray() if remote else bytearray(data)
    msg.is_fd = False
    msg.bitrate_switch = False
    msg.error_state_indicator = False
    return msg


#: One record back into a :class:`can.Message` for the writer: field by field while
#: python-can's Message has exactly the fields filled here, else by its constructor.
_message = _message_fast if received_copy is _snapshot_fast else _message_checked


def _fd_batch_writer(writer: can.Listener, offset: float) -> Callable[[bytes], int]:
    """:func:`_batch_writer` for records in the FD format: a message per record."""
    on_message = writer.on_message_received

    def each_message(batch: bytes) -> int:
        n = 0
        for record in _FD_RECORD.iter_unpack(batch):
            msg = _message_checked(record[:9], offset)  # type: ignore[arg-type]
            msg.is_fd, msg.bitrate_switch = record[9], record[10]
            on_message(msg)
            n += 1
        return n

    return each_message


def _batch_writer(writer: can.Listener, offset: float) -> Callable[[bytes], int]:
    """A function writing one batch of records with ``writer``; it returns how many.

    Every record becomes a :class:`can.Message` for ``writer.on_message_received``; for
    python-can's own BLF writer, the classical frames go to its buffer in bulk
    (:mod:`hdhil.can.traces.blfobjects`: the same bytes, without a message per frame).
    """
    on_message = writer.on_message_received

    def one(record: _Record) -> None:
        on_message(_message(record, offset))

    def each_message(batch: bytes) -> int:
        n = 0
        for record in _RECORD.iter_unpack(batch):
            one(record)
            n += 1
        return n

    bulk = bulk_blf_writer(writer, offset, one)
    if bulk is None:
        return each_message
    return lambda batch: bulk(_RECORD.iter_unpack(batch))


def _pin_header_dates(unix_s: float) -> None:
    """Make the header dates python-can's ASC and MF4 writers take from the wall clock at
    creation (ASC's ``date`` line, MF4's start time, to which MF4 frame times are
    relative) the trace's own start, ``unix_s``.  Only ever called in the writer's child
    process, which exits after the one file it writes."""
    import datetime as _dt
    import importlib

    class _TraceStart(_dt.datetime):
        @classmethod
        def now(cls, tz: _dt.tzinfo | None = None) -> _dt.datetime:  # type: ignore[override]
            return _dt.datetime.fromtimestamp(unix_s, tz)

    for name in ("can.io.asc", "can.io.mf4"):
        module = importlib.import_module(name)
        if getattr(module, "datetime", None) is _dt.datetime:
            module.datetime = _TraceStart  # type: ignore[attr-defined]


def _writer_main(
    tmp_dir: str,
    target: str,
    shown: str,
    frames: Any,
    status: Any,
    frames_w: Any,
    offset: float,
    metadata: dict[str, Any] | None,
    child_listener: ChildListenerFactory | None = None,
    companions: tuple[tuple[str, str, str], ...] = (),
    fd: bool = False,
) -> None:
    """The child: open the writer, write every batch until the pipe closes, close the file
    and rename it into place.

    The file is written as ``tmp_dir/<the trace's name>`` (python-can picks the format
    from the name), the sidecar ``metadata`` to a temporary beside the sidecar; once
    both are complete they are renamed over ``target`` and its sidecar together with the
    ``companions`` (``(temporary, target, label)``: files the run wrote, its fault log),
    all of them or none (:func:`commit_together`), so an existing trace and its sidecar
    are never half overwritten nor split.  End of input, whether the run stopped, was
    interrupted or died (even by SIGKILL), finalises and keeps the trace of what
    happened.  On an error every temporary (the companions' too) is removed and the
    targets left as they were.

    Reports ``("ready", None)`` or ``("error", text)`` at start, and ``("done", frames
    written)`` or ``("error", text)`` at the end, on ``status``.  Signals meant for the run
    (Ctrl-C and a hang-up reach the whole process group) are ignored: the run decides when
    to stop, and end of input is what ends the child.  ``offset`` is added to every
    timestamp.

    With ``child_listener`` (a factory, called here once the writer is ready) the child
    feeds the listener every batch it has written, as :class:`FrameRecord` (timestamps
    without ``offset``), and after its final report sends ``("result", ("ok", value))``
    with the listener's ``result()`` or ``("result", ("error", text))`` if the listener
    failed (it is then fed no more; the trace is written on, as without it).
    """
    frames_w.close()  # the parent's end: with it open here, the input would never end
    leave_stopping_signals_to_parent()  # the run answers them; blocked across the fork
    if offset:
        _pin_header_dates(offset)
    work = Path(tmp_dir)
    label = f"trace {shown}"
    try:
        writer = can.Logger(str(work / Path(target).name))
    except (OSError, ValueError, ImportError, NotImplementedError) as exc:
        text = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        discard_temporary(work)
        status.send(("error", f"cannot write trace {shown}: {text}"))
        return
    status.send(("ready", None))
    write_batch = (_fd_batch_writer if fd else _batch_writer)(writer, offset)
    listening = _ChildListening(child_listener, fd) if child_listener is not None else None
    written = 0
    error: str | None = None
    try:
        while True:
            try:
                batch = frames.recv_bytes()
            except EOFError:
                break
            written += write_batch(batch)
            if listening is not None:
                listening.feed(batch)
    except OSError as exc:
        error = f"cannot write trace {shown}: {exc.strerror or exc}"
    finally:
        try:
            writer.stop()
        except OSError as exc:
            error = error or f"cannot close trace {shown}: {exc.strerror or exc}"
    if error is None:
        error = _commit(work, Path(target), Path(shown), label, metadata, companions)
    discard_temporary(work)
    for tmp, _, _ in companions:
        discard_temporary(Path(tmp))  # renamed into place, or not to be kept
    with contextlib.suppress(OSError):
        status.send(("error", error) if error else ("done", written))
    if listening is not None:
        with contextlib.suppress(OSError):  # the parent no longer waits for it
            status.send(("result", listening.result()))


def _commit(
    work: Path,
    target: Path,
    shown: Path,
    label: str,
    metadata: dict[str, Any] | None,
    companions: tuple[tuple[str, str, str], ...],
) -> str | None:
    """Write the sidecar (to a temporary beside it) once the trace in ``work`` is
    closed, then rename the trace, the sidecar and the companions into place as one;
    the error's text, or ``None``."""
    items = [(work / target.name, target, label)]
    items += [(Path(tmp), Path(dest), what) for tmp, dest, what in companions]
    try:
        if metadata is not None:
            side = metadata_path(shown)
            dest = check_output(side, "sidecar")
            assert dest is not None
            side_tmp = temporary_for(dest)  # beside the sidecar: renamed, never copied
            items.insert(1, (side_tmp, dest, f"sidecar {side}"))
            try:
                with open(side_tmp, "w", encoding="utf-8") as fh:
                    fh.write(metadata_text(metadata))
            except OSError as exc:
                raise UserError(f"cannot write sidecar {side}: {exc.strerror or exc}") from None
        commit_together(items)
    except (UserError, ValueError, OSError) as exc:
        for tmp, _, _ in items[1:]:
            discard_temporary(tmp)
        text = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        return str(text)
    return None


_pack = _RECORD.pack


def _widen_pipe(fd: int) -> None:
    """Ask for a pipe of :data:`PIPE_BYTES` (at most the system's limit) where the system
    lets a process size its pipes; keep the default otherwise."""
    set_size = getattr(fcntl, "F_SETPIPE_SZ", None) if fcntl is not None else None
    if set_size is None:
        return
    try:
        fcntl.fcntl(fd, set_size, PIPE_BYTES)
    except OSError:
        try:
            limit = int(Path("/proc/sys/fs/pipe-max-size").read_text())
            fcntl.fcntl(fd, set_size, min(PIPE_BYTES, limit))
        except (OSError, ValueError):
            pass


class WriterError(ValueError):
    """The trace writer process failed (disk full, killed): the trace is incomplete."""


class ChildListenerError(ValueError):
    """The listener run in the trace writer's process failed or gave no result (the
    trace itself is not concerned: :class:`WriterError` says when it is)."""


def _picklable(obj: Any) -> bool:
    try:
        pickle.dumps(obj)
    except Exception:
        return False
    return True


class WriterProcess(can.Listener):
    """python-can's writer for ``path`` (by extension), run in a child process.

    ``time_offset`` (s) is added to every frame's timestamp as it is written: simulated
    time starts at 0, the file gets the wall-clock time of the run's start plus it.

    The trace is written to a temporary beside ``path`` and its sidecar ``metadata`` to
    one beside the sidecar; both are renamed into place together when complete
    (:func:`_writer_main`), with the ``companions`` (``(temporary, target, label)``:
    another file of the run, its fault log, complete when ``stop`` is called; the child
    renames or removes them): only regular files are ever replaced, never half, and all
    of them or none.  A run that is interrupted or dies still gets a valid trace of every
    frame handed over; a writer that fails (or is stopped by :meth:`abort`) leaves
    ``path``, its sidecar and the companions' targets as they were.

    A :class:`can.Listener`: ``on_message_received`` copies the frame's fields into the
    current batch; full batches go through a pipe.  ``stop`` sends the rest, waits for the
    child to close the file and checks that it wrote every frame it was given.

    ``child_listener``: a factory of a listener run in the child on every frame written
    (:func:`_writer_main`); its result comes back by :meth:`child_result` after ``stop``
    (or is dropped by :meth:`discard_child_result`).  Under the ``spawn`` start method a
    factory that cannot be pickled is not taken: :attr:`child_listening` says whether it
    was, and the caller listens in its own process otherwise.
    """

    def __init__(self, path: Path, time_offset: float = 0.0,
                 metadata: dict[str, Any] | None = None,
                 child_listener: ChildListenerFactory | None = None,
                 companions: tuple[tuple[Path, Path, str], ...] = (),
                 fd: bool = False) -> None:  # fmt: skip
        check_trace_path(path)  # the sidecar's name too: it is written after the trace
        target = check_output(path, "trace")
        assert target is not None
        self.path = path
        self._companions = tuple(Path(tmp) for tmp, _, _ in companions)
        self._failure: str | None = None  # why handing on frames failed
        self.time_offset = time_offset
        self.sent = 0
        #: CAN FD frames (up to 64 bytes) are handed on whole: a wider record per frame.
        self.fd = fd
        self._records = _fd_records if fd else _records
        self._record_size = (_FD_RECORD if fd else _RECORD).size
        self._batch = bytearray()
        self._batched = 0
        self._batch_started = 0.0
        methods = multiprocessing.get_all_start_methods()
        ctx = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
        if child_listener is not None and ctx.get_start_method() != "fork":
            child_listener = child_listener if _picklable(child_listener) else None
        #: The child runs the ``child_listener`` given (its result: :meth:`child_result`).
        self.child_listening = child_listener is not None
        self._awaiting_result = False
        try:
            self._tmp = temporary_dir_for(target)
        except OSError as exc:
            raise ValueError(f"cannot write trace {path}: {exc.strerror or exc}") from None
        frames_r, frames_w = ctx.Pipe(duplex=False)
        _widen_pipe(frames_w.fileno())
        status_r, status_w = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=_writer_main,
            args=(str(self._tmp), str(target), str(path), frames_r, status_w, frames_w,
                  time_offset, metadata, child_listener,
                  tuple((str(t), str(d), w) for t, d, w in companions), fd),
            daemon=False, name=f"hdhil trace writer {path.name}",
        )  # fmt: skip
        # Signals stay blocked across the fork: a Ctrl-C reaching the whole process group
        # must not hit the child before it has set them to be ignored (it unblocks then).
        with stopping_signals_blocked():
            self._proc.start()
        frames_r.close()  # only the child reads frames, only the child reports
        status_w.close()
        self._frames = frames_w
        self._status = status_r
        # At interpreter exit multiprocessing joins its children; close the pipe first so
        # the child sees the end of input even if ``stop`` was never called.
        multiprocessing.util.Finalize(self, frames_w.close, exitpriority=10)
        kind, detail = self._report()
        if kind != "ready":
            self._proc.join()
            discard_temporary(self._tmp)
            raise ValueError(detail)
        # The child renames or removes the temporaries from now on, even after this
        # process is gone: removing them at this process's exit would lose the trace.
        release_temporary(self._tmp)
        for tmp in self._companions:
            release_temporary(tmp)

    def _report(self) -> tuple[str, Any]:
        try:
            if self._status.poll(WRITER_EXIT_TIMEOUT_S):
                return self._status.recv()  # type: ignore[no-any-return]
        except (EOFError, OSError):
            # The child closed its end: it has ended or is ending; reap it for its code.
            self._proc.join(WRITER_EXIT_TIMEOUT_S)
        code = self._proc.exitcode
        return "error", f"the trace writer for {self.path} stopped (exit code {code})"

    def on_message_received(self, msg: can.Message) -> None:
        """Append the frame to the batch; ``msg.channel`` must be a channel number (0-255),
        as the run's tap stamps it."""
        if not self._batch:
            self._batch_started = time.monotonic()
        self._batch += _pack(*_FIELDS(msg)) if not self.fd else _fd_pack(msg)
        self._batched += 1
        if self._batched >= BATCH_FRAMES or (
            self._batched & 31 == 0 and time.monotonic() - self._batch_started > BATCH_MAX_AGE_S
        ):
            self._send()

    #: :meth:`on_frames` takes :class:`FrameGroup` items (:class:`BusTap`).
    takes_frame_groups = True

    def on_frames(self, frames: list[can.Message | FrameGroup]) -> None:
        """:meth:`on_message_received` for each frame (or each frame of a group), in one
        call."""
        if not self._batch:
            self._batch_started = time.monotonic()
        pending = iter(frames)
        try:
            packed = b"".join(self._records(pending))
        except BaseException:
            # A signal handler raised (Ctrl-C) while a frame was read, or a frame does not
            # fit a record: the frames before that one are kept, as they were handed over.
            kept = frames[: max(len(frames) - operator.length_hint(pending) - 1, 0)]
            self._batch += b"".join(self._records(kept))
            self._batched = len(self._batch) // self._record_size
            raise
        self._batch += packed
        self._batched += len(packed) // self._record_size  # frames (a group holds several)
        if (
            self._batched >= BATCH_FRAMES
            or time.monotonic() - self._batch_started > BATCH_MAX_AGE_S
        ):
            self._send()

    def _send(self) -> None:
        if not self._batch:
            return
        # The batch goes whole or not at all, and is counted with it: a Ctrl-C between
        # the two would make stop() send it again, or leave half of it in the pipe.
        with signals_deferred():
            if self._failure is not None:
                raise WriterError(self._failure)
            try:
                self._frames.send_bytes(self._batch)
            except OSError as exc:
                # The child said why it stopped (disk full), else it is gone.
                self._failure = self._failure_reported() or (
                    f"the trace writer for {self.path} is gone ({exc.strerror or exc}); "
                    f"the trace holds at most {self.sent} frames"
                )
                raise WriterError(self._failure) from None
            # Counted from the bytes (fixed-size records, each appended whole): a Ctrl-C
            # between appending a frame and counting it cannot make the two disagree.
            self.sent += len(self._batch) // self._record_size
            self._batch = bytearray()
            self._batched = 0

    def _failure_reported(self) -> str | None:
        """The error the child reported before it ended (it could not write the trace),
        if any."""
        try:
            if self._status.poll(1.0):
                kind, detail = self._status.recv()
                if kind == "error":
                    return str(detail)
        except (EOFError, OSError, ValueError):
            pass
        return None

    def stop(self) -> None:
        """Hand on the last frames, let the child close the file, check the count."""
        if self._frames.closed:
            return
        try:
            self._send()
        finally:
            self._frames.close()
            kind, detail = ("error", self._failure) if self._failure else self._report()
            if self.child_listening and kind in ("done", "error"):
                self._awaiting_result = True  # the child's listener result follows
                if kind != "done":
                    self.discard_child_result()
            else:
                self._proc.join(WRITER_EXIT_TIMEOUT_S)
                self._status.close()
            if kind != "done":  # the child failed or died: nothing of it may stay behind
                self._discard_temporaries()
        if kind == "error":
            raise WriterError(detail)
        if detail != self.sent:
            raise WriterError(
                f"the trace writer wrote {detail} of {self.sent} frames to {self.path}"
            )

    def abort(self) -> None:
        """End the writer without renaming anything into place (another output of the
        run could not be written): the child is stopped at once (it ignores the stopping
        signals: killed) before it sees the end of its input, and the temporaries (the
        trace's, the sidecar's, the companions') are removed; the targets stay as they
        were.  A no-op once :meth:`stop` has run."""
        if self._frames.closed:
            return
        self._awaiting_result = False
        self._proc.kill()
        self._proc.join(WRITER_EXIT_TIMEOUT_S)
        self._frames.close()
        self._status.close()
        self._discard_temporaries()

    def _discard_temporaries(self) -> None:
        discard_temporary(self._tmp)
        for tmp in self._companions:
            discard_temporary(tmp)
        # a sidecar temporary the child had made when it stopped (named after its pid)
        side = metadata_path(self.path)
        pid = self._proc.pid
        if pid is not None:
            for stale in side.parent.glob(f".{side.name}.hdhil-{pid}-*"):
                discard_temporary(stale)

    def child_result(self) -> Any:
        """The result of the child listener, once :meth:`stop` has finished the trace:
        waits for the child to send it (the child has no more frames to write by then).
        Raises :class:`ChildListenerError` if the listener failed or the child died."""
        if not self._awaiting_result:
            raise ChildListenerError(
                f"no child listener result from the trace writer for {self.path} "
                "(none was run, the writer was not stopped, or it was already taken)"
            )
        self._awaiting_result = False
        try:
            kind, detail = self._report()
        finally:
            self._proc.join(WRITER_EXIT_TIMEOUT_S)
            self._status.close()
        if kind != "result":
            raise ChildListenerError(f"no result from the trace writer's child listener: {detail}")
        outcome, value = detail
        if outcome != "ok":
            raise ChildListenerError(value)
        return value

    def discard_child_result(self) -> None:
        """End the child without its listener's result (the run was interrupted or
        failed).  The trace is finished by then (:meth:`stop` has returned or raised), so
        the child is stopped at once (it ignores the stopping signals: killed); a no-op
        when no result is awaited."""
        if not self._awaiting_result:
            return
        self._awaiting_result = False
        self._proc.kill()
        self._proc.join(WRITER_EXIT_TIMEOUT_S)
        self._status.close()


def file_in_progress(path: Path) -> Path:
    """The file this process is writing for trace ``path`` right now (the temporary a
    :class:`WriterProcess` writes, renamed over ``path`` when complete), or ``path``
    itself when none is being written: for watching a trace grow during a run."""
    path = Path(path)
    pattern = f".{path.name}.hdhil-{os.getpid()}-*.tmp"
    for tmp in sorted(path.parent.glob(pattern)):
        inside = tmp / path.name
        if inside.exists():
            return inside
    return path

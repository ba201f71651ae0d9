"""What Ctrl-C (SIGINT), SIGTERM and a hang-up (SIGHUP) do, at every moment of a command.

One rule for the user: the first of them ends the command at a clean point (exit 130,
``hdhil: interrupted``, every file complete or untouched), never a traceback.  Getting
there takes different handling in different places, all of it here so that the places
stay consistent: the console's start-up and exit (:func:`install_start_up_handler`,
:func:`raise_interrupts_in_command`, :func:`ignore_stopping_signals`); SIGTERM and SIGHUP
raising ``KeyboardInterrupt`` like Ctrl-C while a command runs
(:func:`terminate_as_interrupt`); long loops that end at a cycle boundary instead
(:func:`stop_on_signals`); critical sections that must not be cut (:func:`signals_deferred`);
child processes that leave the signals to their parent (:func:`stopping_signals_blocked`
around the fork, :func:`leave_stopping_signals_to_parent`, :func:`leave_interrupt_to_parent`,
:func:`die_with_parent`, :func:`watch_parent`).

Python runs signal handlers in the main thread only, between bytecodes; elsewhere these
helpers do nothing.  Imported by the console before anything else of hdhil: standard
library only.
"""

from __future__ import annotations

import _signal
import contextlib
import os
import signal
import threading
import time
from collections.abc import Iterable, Iterator
from types import FrameType
from typing import Any

__all__ = [
    "STOPPING_SIGNALS",
    "TERMINATING_SIGNALS",
    "die_with_parent",
    "ignore_stopping_signals",
    "install_start_up_handler",
    "leave_interrupt_to_parent",
    "leave_stopping_signals_to_parent",
    "raise_interrupts_in_command",
    "restore_handlers",
    "signals_deferred",
    "stop_on_signals",
    "stopping_signals_blocked",
    "terminate_as_interrupt",
    "watch_parent",
]

#: Ctrl-C, SIGTERM and a hang-up: the signals that stop a command.
STOPPING_SIGNALS: tuple[int, ...] = tuple(
    s for s in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)) if s is not None
)
#: The stopping signals other than Ctrl-C.
TERMINATING_SIGNALS: tuple[int, ...] = tuple(s for s in STOPPING_SIGNALS if s != signal.SIGINT)


def _on_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


# ------------------------------------------------------------------ the console
def _interrupted_during_start_up(signum: int, frame: object) -> None:
    """Before the command runs: nothing done, nothing to clean up; say so and end
    (``os._exit``: no half-imported module's clean-up runs)."""
    ignore_stopping_signals()
    try:
        os.write(2, b"hdhil: interrupted\n")
    finally:
        os._exit(130)


def _in_finalizer(frame: FrameType | None) -> bool:
    """Whether ``frame`` runs inside an object's finalizer (``__del__``, a weakref or
    multiprocessing finalizer), where Python swallows an exception ("Exception ignored
    in ...") and the command would go on as if Ctrl-C had never come."""
    while frame is not None:
        code = frame.f_code
        if code.co_name == "__del__" or "Finalize" in getattr(code, "co_qualname", ""):
            return True
        frame = frame.f_back
    return False


def _keyboard_interrupt(signum: int, frame: FrameType | None) -> None:
    """Ctrl-C while a command runs: ``KeyboardInterrupt`` where the command is, or, if
    that is inside a finalizer (which would swallow it), the same signal again a moment
    later, once the finalizer is done."""
    if _in_finalizer(frame):
        threading.Timer(0.01, os.kill, (os.getpid(), signum)).start()
        return
    raise KeyboardInterrupt


def install_start_up_handler() -> None:
    """From now until the command starts, a stopping signal ends the process at once with
    exit code 130 and one line.  Signals that are ignored (nohup, background) stay so."""
    for sig in STOPPING_SIGNALS:
        with contextlib.suppress(OSError, ValueError):  # not the main thread
            if signal.getsignal(sig) is not signal.SIG_IGN:
                signal.signal(sig, _interrupted_during_start_up)


def raise_interrupts_in_command() -> None:
    """The command starts: Ctrl-C raises ``KeyboardInterrupt`` again (so ``finally``
    blocks run), also when it lands in a finalizer, 10 ms later.  Only if the start-up
    handler is in place (an ignored Ctrl-C stays ignored)."""
    if signal.getsignal(signal.SIGINT) is _interrupted_during_start_up:
        signal.signal(signal.SIGINT, _keyboard_interrupt)


def ignore_stopping_signals() -> None:
    """Ignore the stopping signals from now on (the process is ending)."""
    for sig in STOPPING_SIGNALS:
        with contextlib.suppress(OSError, ValueError):  # not the main thread
            signal.signal(sig, signal.SIG_IGN)


# ------------------------------------------------------------- while a command runs
def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def terminate_as_interrupt(signals: Iterable[int] = TERMINATING_SIGNALS) -> dict[int, Any]:
    """SIGTERM and SIGHUP (or ``signals``) raise ``KeyboardInterrupt`` like Ctrl-C, so
    ``finally`` blocks (temporary files, buses, the trace writer) run and the command
    exits 130.  Commands that stop cleanly at a cycle boundary install their own handlers
    over these.  Returns the previous handlers (for :func:`restore_handlers`)."""
    previous: dict[int, Any] = {}
    for sig in signals:
        with contextlib.suppress(ValueError, OSError):  # not the main thread
            previous[sig] = signal.signal(sig, _interrupt)
    return previous


def restore_handlers(previous: dict[int, Any]) -> None:
    """Put back handlers that :func:`terminate_as_interrupt` replaced."""
    for sig, handler in previous.items():
        with contextlib.suppress(ValueError, OSError, TypeError):
            signal.signal(sig, handler)


@contextlib.contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """Turn the first SIGINT/SIGTERM into a stop request (the run ends cleanly at the next
    cycle boundary, trace closed); a second SIGINT interrupts at once."""
    stop = threading.Event()
    if not _on_main_thread():
        yield stop
        return

    def request_stop(signum: int, frame: object) -> None:
        # The second Ctrl-C: whatever raised KeyboardInterrupt before (the console's own).
        # Put in place before the event is set: Event.set takes a lock that is not
        # reentrant, and a second Ctrl-C whose handler ran inside this one's set() and
        # set the event again waited for that lock for ever (a run that never ended).
        outer = previous.get(signal.SIGINT)
        signal.signal(signal.SIGINT, outer if callable(outer) else signal.default_int_handler)
        if not requested:  # a stopping signal whose handler runs inside this one's set()
            requested.append(signum)
            stop.set()

    requested: list[int] = []
    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold back the stopping signals' Python handlers for the block, then run them.

    For a step that must happen whole or not at all (the trace writer's pipe write and
    its count of frames sent): a signal that arrives in the block is noted, and its
    handler, whichever is in place when the block ends, runs then (a default action is
    raised again).  Ignored signals stay ignored.
    """
    if not _on_main_thread():
        yield
        return
    caught: list[int] = []

    def note(signum: int, frame: object) -> None:
        if signum not in caught:
            caught.append(signum)

    previous: dict[int, Any] = {}
    # The C module's functions: ``signal.signal`` and ``getsignal`` convert every handler to
    # and from the Handlers enum, which costs more than the rest of the block (the trace
    # writer's hand-off runs this every few dozen cycles).
    try:
        for sig in STOPPING_SIGNALS:
            if _signal.getsignal(sig) != _signal.SIG_IGN:
                previous[sig] = _signal.signal(sig, note)
        yield
    finally:
        for sig, handler in previous.items():
            _signal.signal(sig, handler)
        for sig in caught:
            handler = _signal.getsignal(sig)
            if callable(handler):
                handler(sig, None)
            elif handler == _signal.SIG_DFL:
                signal.raise_signal(sig)


# ------------------------------------------------------------ child processes
@contextlib.contextmanager
def stopping_signals_blocked() -> Iterator[None]:
    """Block the stopping signals for the block (a fork): a Ctrl-C reaching the whole
    process group must not hit a child before it has set them to be ignored; the child
    unblocks them then (:func:`leave_stopping_signals_to_parent`)."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, STOPPING_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def leave_stopping_signals_to_parent() -> None:
    """In a child process that ends when its input ends (the trace writer): ignore the
    stopping signals, which the parent answers, and unblock them (blocked across the
    fork by :func:`stopping_signals_blocked`)."""
    for sig in STOPPING_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOPPING_SIGNALS)


def leave_interrupt_to_parent() -> None:
    """In a pool worker: ignore Ctrl-C, which reaches the whole process group; the parent
    answers it (cancels the work and keeps the results)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


#: ``PR_SET_PDEATHSIG`` of <linux/prctl.h>.
_PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int) -> bool:
    """In a worker process: end when the parent dies, even by SIGKILL, which no handler
    of the parent can answer. Linux: the kernel sends this process SIGKILL
    (``PR_SET_PDEATHSIG``); a parent already gone by the time the request took effect
    ends this process at once. Elsewhere (POSIX): :func:`watch_parent`. Returns whether
    the kernel's request is in place."""
    import ctypes
    import sys

    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0:
                if os.getppid() != parent_pid:  # died before the request took effect
                    os._exit(1)
                return True
        except (OSError, AttributeError):
            pass
    if os.name == "posix":
        watch_parent(parent_pid)
    return False


#: How often :func:`watch_parent` looks for its parent, and how long it lets the process
#: end on its own after SIGTERM before it ends it (seconds).
PARENT_WATCH_INTERVAL_S = 0.2
PARENT_WATCH_GRACE_S = 1.0


def watch_parent(
    parent_pid: int,
    interval_s: float = PARENT_WATCH_INTERVAL_S,
    grace_s: float = PARENT_WATCH_GRACE_S,
) -> threading.Thread:
    """A daemon thread that ends this process once its parent is gone (POSIX: an orphan
    is adopted, so its parent id changes): SIGTERM to itself, so that its handlers clean
    up, then ``os._exit`` if it is still running ``grace_s`` later."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(interval_s)
        with contextlib.suppress(OSError):
            os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(grace_s)
        os._exit(1)

    thread = threading.Thread(target=watch, name="hdhil-parent-watch", daemon=True)
    thread.start()
    return thread

"""The ``hdhil`` console script (and ``python -m hdhil``): :func:`hdhil.cli.main` with
Ctrl-C handled at every moment of the process, not only while a command runs.

Three stretches, one rule: the first Ctrl-C (SIGINT; SIGTERM and SIGHUP alike) ends the
process with exit code 130 and the one line ``hdhil: interrupted``, never a traceback.

1. **Start-up**, from the import of this module until the command starts: importing the
   command line and the command's libraries (numpy, scipy, python-can) takes a noticeable
   time on a loaded machine.  Nothing has been written yet, so the handler installed at
   the import of this module (before anything else of hdhil is imported) writes the line
   and ends the process at once (``os._exit``: no half-imported module's clean-up runs).
2. **The command** (:func:`hdhil.cli.main`): Ctrl-C raises ``KeyboardInterrupt`` as
   usual, so ``finally`` blocks remove temporary files and close traces; long loops poll
   a stop request and end at a clean point (:func:`hdhil.rig.runner.stop_on_signals`).
   A Ctrl-C that lands in an object's finalizer (a bus closed by the garbage collector),
   where Python would swallow the exception and the command run on, is raised again
   10 ms later instead.
3. **Exit**, after the command returned its code: the output is complete; what is left is
   the interpreter's own shut-down (joining the trace writer process, which renames the
   finished trace into place, and thread and module clean-up, where a ``KeyboardInterrupt``
   could only print a traceback or kill the process by the signal).  The signals are
   ignored from here on, so the process ends with the command's exit code.

Python's own start-up, before the first line of this module runs (interpreter, ``site``
and the console script's two standard imports), is out of hdhil's reach: a Ctrl-C there
ends the process the way it ends any Python program.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from types import FrameType
from typing import NoReturn

_SIGNALS = tuple(
    s for s in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)) if s is not None
)


def _interrupted_during_start_up(signum: int, frame: object) -> None:
    """Stretch 1: nothing done, nothing to clean up; say so and end."""
    with_ignored()
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


def with_ignored() -> None:
    """Ignore the stopping signals from now on (the process is ending)."""
    for sig in _SIGNALS:
        with contextlib.suppress(OSError, ValueError):  # not the main thread
            signal.signal(sig, signal.SIG_IGN)


def _install_start_up_handler() -> None:
    for sig in _SIGNALS:
        with contextlib.suppress(OSError, ValueError):  # not the main thread
            if signal.getsignal(sig) is not signal.SIG_IGN:  # nohup/background: stay ignored
                signal.signal(sig, _interrupted_during_start_up)


_install_start_up_handler()


def run() -> NoReturn:
    """Run the command named in ``sys.argv`` and exit with its code."""
    from hdhil.cli import main  # the command line, imported under the start-up handler

    # Stretch 2: Ctrl-C is KeyboardInterrupt again; main turns SIGTERM/SIGHUP into it
    # while it runs and puts the start-up handler back when it returns.
    if signal.getsignal(signal.SIGINT) is _interrupted_during_start_up:
        signal.signal(signal.SIGINT, _keyboard_interrupt)
    try:
        code = main()
    except KeyboardInterrupt:  # a second Ctrl-C while main was already ending
        with_ignored()
        print("hdhil: interrupted", file=sys.stderr)
        code = 130
    with_ignored()  # stretch 3
    with contextlib.suppress(OSError, ValueError):
        sys.stdout.flush()
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover - python -m hdhil.console
    run()

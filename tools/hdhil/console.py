"""The ``hdhil`` console script (and ``python -m hdhil``): :func:`hdhil.cli.main` with
Ctrl-C handled at every moment of the process, not only while a command runs.

Three stretches, one rule: the first Ctrl-C (SIGINT; SIGTERM and SIGHUP alike) ends the
process with exit code 130 and the one line ``hdhil: interrupted``, never a traceback
(the handlers are :mod:`hdhil.core.signals`'):

1. **Start-up**, from the import of this module until the command starts (importing the
   command's libraries takes a noticeable time on a loaded machine): nothing has been
   written yet, so the process ends at once.
2. **The command**: Ctrl-C raises ``KeyboardInterrupt``, so ``finally`` blocks remove
   temporary files and close traces; long loops poll a stop request and end at a clean
   point (:func:`hdhil.core.signals.stop_on_signals`).
3. **Exit**, after the command returned its code: what is left is the interpreter's own
   shut-down (joining the trace writer, which renames the finished trace into place), so
   the signals are ignored and the process ends with the command's exit code.

Python's own start-up, before the first line of this module runs (the interpreter and
its ``site`` module, a few tens of milliseconds), is out of hdhil's reach: a Ctrl-C there
ends the process the way it ends any Python program.  From this module's first line on,
a handler written with built-in modules only is in place until the full start-up handler
replaces it, so that importing the handlers is covered too.
"""

from __future__ import annotations

import _signal  # built in: nothing to load before the first handler is in place
import os


def _interrupted_early(signum: int, frame: object) -> None:
    """Stretch 1 until :func:`hdhil.core.signals.install_start_up_handler` replaces it:
    the same one line and exit code 130."""
    for sig in _EARLY_SIGNALS:
        _signal.signal(sig, _signal.SIG_IGN)
    try:
        os.write(2, b"hdhil: interrupted\n")
    finally:
        os._exit(130)


_EARLY_SIGNALS = tuple(
    getattr(_signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(_signal, name)
)
for _sig in _EARLY_SIGNALS:
    if _signal.getsignal(_sig) != _signal.SIG_IGN:  # nohup, background: stays ignored
        _signal.signal(_sig, _interrupted_early)

# The rest after the first handler, on purpose.
import contextlib  # noqa: E402
import sys  # noqa: E402
from typing import NoReturn  # noqa: E402

from hdhil.core.signals import (  # noqa: E402
    ignore_stopping_signals,
    install_start_up_handler,
    raise_interrupts_in_command,
)

install_start_up_handler()  # stretch 1, before anything else of hdhil is imported


def run() -> NoReturn:
    """Run the command named in ``sys.argv`` and exit with its code."""
    from hdhil.cli import main  # the command line, imported under the start-up handler

    # Stretch 2: Ctrl-C is KeyboardInterrupt again; main turns SIGTERM/SIGHUP into it
    # while it runs and puts the start-up handler back when it returns.
    raise_interrupts_in_command()
    try:
        code = main()
    except KeyboardInterrupt:  # a second Ctrl-C while main was already ending
        ignore_stopping_signals()
        print("hdhil: interrupted", file=sys.stderr)
        code = 130
    ignore_stopping_signals()  # stretch 3
    sys.exit(_flush_stdout(code))


def _flush_stdout(code: int) -> int:
    """The exit code once standard output is flushed: what the command printed that
    could not be written (a full disk behind ``> FILE``) is an error, exit code 2 with
    one line (130 stays 130); a reader that stopped reading (``| head``) is not.  Either
    way standard output then goes to the null device, so the interpreter's own flush
    at exit finds nothing left to fail on."""
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        _stdout_to_null()
    except OSError as exc:
        _stdout_to_null()
        if code in (2, 130):  # its one line is out already
            return code
        with contextlib.suppress(OSError, ValueError):
            print(f"hdhil: error: cannot write standard output ({exc.strerror or exc})",
                  file=sys.stderr)  # fmt: skip
        return 2
    except ValueError:  # closed by the command
        pass
    return code


def _stdout_to_null() -> None:
    with contextlib.suppress(Exception):
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)
        sys.stdout.flush()


if __name__ == "__main__":  # pragma: no cover - python -m hdhil.console
    run()

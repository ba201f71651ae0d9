"""The ``hdhil`` command: one console script, one subcommand per module of
:mod:`hdhil.commands`.

Each command module exposes ``register(subparsers)``, which adds its parser(s) and sets
``func`` to a function ``(args) -> int`` (the exit code). Only the module of the command
being run is imported; the others appear in ``hdhil --help`` through the one-line help
of :data:`COMMANDS`, so asking for help or running one command never loads scipy or
matplotlib for the others. A test keeps that table equal to what the modules register.

Exit codes: 0 completed, 1 stopped early by a fault reaction or a failed verdict,
2 usage or input error (one line on stderr, never a traceback), 130 interrupted.
"""

from __future__ import annotations

import argparse
import codecs
import contextlib
import gc
import importlib
import os
import sys
from collections.abc import Iterator, Sequence
from typing import NoReturn

from hdhil.core.errors import ConfigError, UserError
from hdhil.core.files import display_name
from hdhil.core.signals import restore_handlers, terminate_as_interrupt

#: Every subcommand, in the order ``hdhil --help`` lists them: its module in
#: :mod:`hdhil.commands` and its one-line help.
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("run", "run a scenario end to end on the in-process bus"),
    "dump": ("dump", "show a CAN trace decoded with the DBCs (table, CSV or timing statistics)"),
    "filter": ("filter", "run the firmware's torque filter offline over a signal CSV or a trace"),
    "evaluate": ("evaluate", "score the filters against ground truth in a trace"),
    "tune": ("tune", "tune the recommended ripple filter's Q/R on a trace (maximum likelihood)"),
    "plot": ("plot", "draw the seed's torque figures (Figs. 8-11) from a trace"),
    "calibrate": (
        "calibrate",
        "calibrate the emulated torque sensor (arm and weights, [Taghirad97] §3)",
    ),
    "design": ("design", "controller design (LQG joint-torque regulator of [Vertechy])"),
    "identify": (
        "identify",
        "natural frequency and damping of the joint from a chirp trace ([Vertechy] Fig. 5)",
    ),
    "emulate": ("netcmd", "run the drive emulator alone on a CAN interface"),
    "firmware": ("netcmd", "run the controller firmware alone on a CAN interface"),
    "log": ("netcmd", "record a CAN interface (and the truth bus) to a trace"),
    "sdo": ("netcmd", "read or write a node's object dictionary (SDO client)"),
    "nmt": ("netcmd", "send an NMT command"),
    "conformance": ("conformance", "CiA 301 + CiA 402 conformance and timing suite against a node"),
    "plan": ("plan", "worst-case load of each bus of a scenario's rig, and the CPU a cycle needs"),
    "dbc": ("dbc", "CAN databases: export the control bus and ground truth as one DBC"),
    "bench": ("bench", "measure throughput, per-stage compute time and memory (medians)"),
    "soak": (
        "soak",
        "long lockstep run with logging, checked per block (filter health, errors, memory)",
    ),
    "campaign": (
        "campaign",
        "run a campaign (scenario x fault x seed x parameter grid) in parallel",
    ),
}

__all__ = ["COMMANDS", "ConfigError", "UserError", "build_parser", "main", "version"]


#: Commands that end a run stopped by a signal (exit code 130) with their own line
#: starting ``hdhil: interrupted``; for the others :func:`main` prints that line.
_SAYS_INTERRUPTED = frozenset({"campaign"})


def version() -> str:
    """The installed distribution's version (``importlib.metadata``), or ``"unknown"``
    when hdhil runs without being installed."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as distribution_version

    try:
        return distribution_version("hdhil")
    except PackageNotFoundError:
        return "unknown"


class _VersionAction(argparse.Action):
    """``--version``: print ``hdhil <version>`` and exit 0.  The version is looked up
    only when asked for, so other commands do not pay for importlib.metadata."""

    def __init__(self, option_strings: Sequence[str], dest: str, **_: object) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="print the version and exit")  # fmt: skip

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: object,
        option_string: str | None = None,
    ) -> NoReturn:
        print(f"hdhil {version()}")
        parser.exit(0)


def _requested(argv: Sequence[str]) -> str | None:
    """The subcommand named on the command line, if any (the first non-option word)."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


class _Parser(argparse.ArgumentParser):
    """Usage mistakes as one line, ``hdhil: error: ...`` and exit code 2, like every
    other input error (argparse would print the usage first); ``--help`` still prints
    the full usage."""

    def error(self, message: str) -> NoReturn:
        command = self.prog.removeprefix("hdhil").strip()
        raise UserError(f"{command + ': ' if command else ''}{message} (see {self.prog} --help)")


def build_parser(
    argv: Sequence[str] | None = None, load_all: bool = False
) -> argparse.ArgumentParser:
    """The parser for ``argv``: the requested command's module is imported and registers
    its full parser; the other commands are listed by name and help only.
    ``load_all`` imports every command module (for tests and documentation)."""
    wanted = _requested(sys.argv[1:] if argv is None else argv)
    parser = _Parser(
        prog="hdhil",
        description="Hardware-in-the-loop emulator for joint-torque sensing and control of "
        "harmonic-drive joints over CAN.",
        epilog="exit codes: 0 completed, 1 stopped early by a fault reaction or failed "
        "verdict, 2 usage or input error, 130 interrupted",
    )
    parser.add_argument("--version", action=_VersionAction)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    loaded: set[str] = set()
    for name, (module_name, help_text) in COMMANDS.items():
        if module_name in loaded:
            continue
        if load_all or COMMANDS.get(wanted or "", ("",))[0] == module_name:
            importlib.import_module(f"hdhil.commands.{module_name}").register(sub)
            loaded.add(module_name)
        else:
            sub.add_parser(name, help=help_text, add_help=False)
    return parser


def _caused_by_interrupt(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is in ``exc``'s chain of causes and contexts."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False


_frozen = False


@contextlib.contextmanager
def _start_up_collection() -> Iterator[None]:
    """The cyclic garbage collector off while the command's modules are imported, and
    what they built moved out of its reach afterwards (``gc.freeze``, once per process).

    Imports allocate many objects and free few: each collection found nearly nothing
    and the full ones traversed the whole growing heap, a sizeable part of ``hdhil
    run``'s start-up; the modules' objects live as long as the process, so later full
    collections (in the middle of a run) need not traverse them either.
    """
    global _frozen
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if not _frozen:
            _frozen = True
            gc.freeze()
        if enabled:
            gc.enable()


def _escape_unencodable(exc: UnicodeError) -> tuple[str, int]:
    """Codec error handler ``hdhil-escape``: a byte that was not UTF-8 in a file name
    (held as a lone surrogate U+DC80..U+DCFF) as ``\\xff``, as
    :func:`~hdhil.core.files.display_name` shows it; anything else as
    ``backslashreplace`` does."""
    if not isinstance(exc, UnicodeEncodeError):
        raise exc
    text = exc.object[exc.start : exc.end]
    return "".join(
        f"\\x{ord(c) - 0xDC00:02x}" if 0xDC80 <= ord(c) <= 0xDCFF
        else c.encode("ascii", "backslashreplace").decode("ascii")
        for c in text
    ), exc.end  # fmt: skip


codecs.register_error("hdhil-escape", _escape_unencodable)


@contextlib.contextmanager
def _escaping_output() -> Iterator[None]:
    """Standard output escapes what its encoding cannot write (``\\xff``, ``\\u2014``)
    instead of raising ``UnicodeEncodeError``: a file name may hold bytes that are not
    UTF-8 (Python keeps them as lone surrogates), and a command prints the names it
    wrote.  Standard error never raises there (Python's default is backslashreplace)."""
    stream = sys.stdout
    errors = getattr(stream, "errors", None)
    change = errors == "strict" and hasattr(stream, "reconfigure")
    if change:
        with contextlib.suppress(ValueError, OSError):
            stream.reconfigure(errors="hdhil-escape")
    try:
        yield
    finally:
        if change:
            with contextlib.suppress(ValueError, OSError):
                stream.reconfigure(errors=errors)


def _error(message: object) -> None:
    """The one line of an input error: ``hdhil: error: ...``, names in it escaped
    (:func:`~hdhil.core.files.display_name`: no raw control character or undecodable
    byte, so it stays one line on any terminal)."""
    print(f"hdhil: error: {display_name(str(message))}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; the exit code (see the module docstring)."""
    previous = terminate_as_interrupt()  # SIGTERM/SIGHUP: like Ctrl-C; temporaries removed
    try:
        with _escaping_output():
            with _start_up_collection():
                parser = build_parser(argv)
                args = parser.parse_args(argv)
            code = int(args.func(args) or 0)
        if code == 130 and getattr(args, "command", None) not in _SAYS_INTERRUPTED:
            print("hdhil: interrupted", file=sys.stderr)  # stopped at a signal (run, soak, ...)
        return code
    except (UserError, ConfigError) as exc:
        _error(exc)
        return 2
    except KeyboardInterrupt:
        print("hdhil: interrupted", file=sys.stderr)
        return 130
    except SystemExit as exc:  # --help (0); in-process callers get the code back
        return exc.code if isinstance(exc.code, int) else 0
    except BrokenPipeError:
        # Output piped into a command that stopped reading (e.g. `| head`): not an error.
        sys.stderr.close()
        return 0
    except OSError as exc:
        # Disk full, a file vanished mid-run, ...: one line naming what failed.
        name = getattr(exc, "filename", None)
        what = f"{os.fsdecode(name) if isinstance(name, bytes) else name}: " if name else ""
        _error(f"{what}{exc.strerror or exc}")
        return 2
    except Exception as exc:
        # A Ctrl-C inside code that turns it into an error of its own (a compiled
        # extension's import, scipy's loaded by a command on first use, raises ImportError)
        # is still an interrupt; any other exception is a bug and keeps its traceback.
        if not _caused_by_interrupt(exc):
            raise
        print("hdhil: interrupted", file=sys.stderr)
        return 130
    finally:
        restore_handlers(previous)


if __name__ == "__main__":
    sys.exit(main())

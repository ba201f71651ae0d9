"""The ``hdhil`` command: one console script, one subcommand per tool.

Each subcommand lives in its own module exposing ``register(subparsers)``, which adds
its parser and sets ``func`` to a function ``(args) -> int`` (the exit code).  User
mistakes (bad files, bad parameters) raise :class:`UserError` or ``ConfigError`` and
become a one-line ``hdhil: error: ...`` on stderr with exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from hdhil.dataconf import ConfigError


class UserError(Exception):
    """A mistake the user can fix: reported as one line, exit code 2."""


#: Subcommand modules, in the order ``hdhil --help`` lists them.
COMMANDS = (
    "run",
    "dump",
    "filter_cmd",
    "evaluate",
    "tune",
    "plot",
    "calibrate",
    "design",
    "identify",
    "netcmd",
    "bench",
    "soak",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hdhil",
        description="Hardware-in-the-loop emulator for joint-torque sensing and control of "
        "harmonic-drive joints over CAN.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"hdhil.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"hdhil.{name}":
                raise
            continue
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (UserError, ConfigError) as exc:
        print(f"hdhil: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hdhil: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # Output piped into a command that stopped reading (e.g. `| head`): not an error.
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())

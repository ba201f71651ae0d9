"""Progress with an ETA for long commands (``run``, ``soak``, ``bench``, ``tune``,
``calibrate``, ``identify``): a tqdm bar on standard error, shown only when standard error
is a terminal and neither ``--json`` nor ``--quiet`` was given, so pipes, files and
machine-readable output never carry it.
"""

from __future__ import annotations

import argparse
import sys
from types import TracebackType
from typing import Any


def add_quiet_argument(p: argparse.ArgumentParser) -> None:
    """``--quiet``: no progress bar."""
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar on standard error")


def wanted(args: argparse.Namespace) -> bool:
    """Whether to show progress: standard error is a terminal, no ``--json``/``--quiet``."""
    if getattr(args, "json", False) or getattr(args, "quiet", False):
        return False
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


class Progress:
    """A bar from 0 to ``total`` in ``unit`` (``s`` simulated seconds, ``eval``, ...),
    with rate and ETA; does nothing when disabled.  A context manager."""

    def __init__(self, total: float, desc: str, unit: str, enabled: bool) -> None:
        self._bar: Any = None
        self._done = 0.0
        if enabled:
            import shutil

            from tqdm import tqdm

            # A terminal that reports no size (0 x 0, e.g. a bare pseudo-terminal) would
            # make tqdm hide the bar: fall back to 80 x 24 then.
            size = shutil.get_terminal_size((80, 24))
            self._bar = tqdm(
                total=total,
                desc=desc,
                unit=unit,
                file=sys.stderr,
                ncols=size.columns or 80,
                nrows=size.lines or 24,
                leave=False,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.4g}/{total:.4g} {unit} "
                "[{elapsed}<{remaining}, {rate_fmt}]",
            )

    @property
    def enabled(self) -> bool:
        return self._bar is not None

    def update_to(self, done: float) -> None:
        """Set the progress to ``done`` (of ``total``)."""
        if self._bar is not None and done > self._done:
            self._bar.update(done - self._done)
            self._done = done

    def advance(self, step: float = 1.0) -> None:
        self.update_to(self._done + step)

    def describe(self, text: str) -> None:
        if self._bar is not None:
            self._bar.set_description_str(text)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def progress(args: argparse.Namespace, total: float, desc: str, unit: str = "s") -> Progress:
    """A :class:`Progress` shown only if :func:`wanted`."""
    return Progress(total, desc, unit, wanted(args))

"""Trace formats: which files hdhil writes and reads, chosen by extension.

python-can's :func:`can.Logger` and :class:`can.LogReader` pick the format from the file
name: ``.blf`` (default), ``.asc``, ``.log`` (candump), ``.csv``, ``.trc``, ``.mf4``
(ASAM MDF 4, needs asammdf: the ``mf4`` extra); the text formats also gzip-compressed
(``.asc.gz``, ``.log.gz``, ...).  This module names that set once, for the writer, the
reader and the commands' messages.  It imports nothing heavy (not even python-can), so a
command can check a path or a suffix before loading anything.
"""

from __future__ import annotations

from pathlib import Path

#: Formats python-can's Logger writes and its LogReader reads, by extension.  python-can's
#: SQLite writer (``.db``) is left out: its writer thread dropped frames at the end of a
#: run (python-can 4.6), and a trace must hold every frame.
SUPPORTED_SUFFIXES = (".blf", ".asc", ".log", ".csv", ".trc", ".mf4")

#: Formats python-can writes gzip-compressed when ``.gz`` follows (``run.asc.gz``).
GZIP_SUFFIXES = (".asc", ".log", ".csv", ".trc")

#: The message when ``.mf4`` is asked for without asammdf installed.
MF4_MISSING = "writing and reading .mf4 traces needs asammdf: pip install 'hdhil[mf4]'"


def trace_format(path: Path) -> tuple[str, bool]:
    """``(format extension, gzip-compressed)`` of ``path``, e.g. ``(".asc", True)``."""
    suffixes = [s.lower() for s in path.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        return (suffixes[-2] if len(suffixes) >= 2 else ""), True
    return (suffixes[-1] if suffixes else ""), False


def supported_formats() -> str:
    """The writable formats, for messages and help texts."""
    return f"{', '.join(SUPPORTED_SUFFIXES)} (and {', '.join(GZIP_SUFFIXES)} with .gz)"


def mf4_available() -> bool:
    """Whether asammdf, which python-can's MF4 writer and reader need, is installed."""
    import importlib.util

    return importlib.util.find_spec("asammdf") is not None


def supported_extensions() -> str:
    """The readable formats, for messages."""
    return ", ".join(SUPPORTED_SUFFIXES) + " (optionally .gz)"

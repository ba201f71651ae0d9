"""The times ``hdhil dump`` prints: relative to the trace's first frame, or wall-clock.

Trace formats disagree on what a timestamp is: BLF, candump ``.log``, CSV, TRC and MF4
store (or python-can's readers give) Unix times, ASC stores seconds since its first frame
and the wall-clock start in its header (``Begin Triggerblock`` date, else the ``date``
line).  :class:`TraceClock` hides that: by default every time is relative to the trace's
first frame, so the same run reads the same in every format; ``absolute`` gives ISO 8601
UTC times with microseconds, the trace's own time plus, where the format stores relative
times, its start (the ASC header, else the sidecar's ``time_offset_s``).
"""

from __future__ import annotations

import datetime as _dt
import gzip
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: Width of a relative time (seconds, 6 decimals) and of an ISO 8601 UTC time.
RELATIVE_WIDTH = 12
ABSOLUTE_WIDTH = len("2000-01-01T00:00:00.000000Z")

#: Formats whose timestamps (as python-can reads them) are relative to the trace's start.
RELATIVE_FORMATS = frozenset({".asc"})

_ASC_DATE = re.compile(r"\s*(begin\s+triggerblock|date)\s+\w+\s+(.+)", re.I)
_ASC_FRAME_LINE = re.compile(r"\s*\d+\.\d+\s")
_HEADER_LINES = 50


@dataclass(frozen=True)
class TraceClock:
    """``origin``: trace time of the first frame; ``start``: Unix time of trace time 0
    (0 for formats storing Unix times, None if unknown); ``absolute``: print wall-clock."""

    origin: float
    start: float | None = 0.0
    absolute: bool = False

    @property
    def width(self) -> int:
        return ABSOLUTE_WIDTH if self.absolute else RELATIVE_WIDTH

    @property
    def label(self) -> str:
        return "time (UTC)" if self.absolute else "time/s"

    def seconds(self, t: float) -> float:
        """``t`` relative to the first frame."""
        return t - self.origin

    def text(self, t: float) -> str:
        """``t`` as the table prints it (fixed width)."""
        if not self.absolute:
            return f"{t - self.origin:{RELATIVE_WIDTH}.6f}"
        assert self.start is not None
        return iso_utc(t + self.start)


def iso_utc(unix_s: float) -> str:
    """``unix_s`` as ISO 8601 UTC with microseconds (``2024-05-01T12:00:00.123456Z``)."""
    whole = int(unix_s // 1)
    micro = round((unix_s - whole) * 1e6)
    if micro >= 1_000_000:
        whole, micro = whole + 1, micro - 1_000_000
    moment = _dt.datetime.fromtimestamp(whole, _dt.timezone.utc).replace(microsecond=micro)
    return moment.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def asc_start(path: Path, compressed: bool) -> float | None:
    """Unix time of an ASC trace's time 0 from its header (``Begin Triggerblock`` date,
    else the ``date`` line; local time, as python-can writes and reads it), or None."""
    from can.io.asc import ASCReader

    found: dict[str, str] = {}
    opener: Any = gzip.open if compressed else open
    try:
        with opener(path, "rt", encoding="ascii", errors="replace") as stream:
            for number, line in enumerate(stream):
                if number > _HEADER_LINES or _ASC_FRAME_LINE.match(line):
                    break
                match = _ASC_DATE.match(line)
                if match:
                    found.setdefault(match.group(1).split()[0].lower(), match.group(2).strip())
    except (OSError, EOFError):
        return None
    for key in ("begin", "date"):
        if key in found:
            try:
                return float(ASCReader._datetime_to_timestamp(found[key]))
            except ValueError:
                continue
    return None


def trace_clock(
    path: Path,
    fmt: str,
    compressed: bool,
    first_time: float,
    sidecar: dict[str, Any] | None,
    absolute: bool,
) -> TraceClock:
    """The clock of a trace of format ``fmt`` whose first frame is at ``first_time``;
    ``absolute`` without a known start is a ValueError."""
    start: float | None = 0.0
    if fmt in RELATIVE_FORMATS:
        start = asc_start(path, compressed) if fmt == ".asc" else None
        if start is None and sidecar is not None:
            offset = sidecar.get("time_offset_s")
            if isinstance(offset, int | float) and not isinstance(offset, bool) and offset > 0:
                start = float(offset)
    if absolute and start is None:
        raise ValueError(
            f"{path}: no start date (the {fmt[1:].upper()} header has none and no sidecar "
            "gives time_offset_s)"
        )
    return TraceClock(first_time, start, absolute)

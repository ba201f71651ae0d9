"""A trace as tidy data: one row per control cycle, one column per signal, units in the
column names.

A CAN trace holds about seven frames per 1 ms cycle, so a per-frame table is mostly empty
cells.  Here a row is one **sample**, opened by the drive's sensor frame ``DRIVE_TPDO1``
(sampled at the SYNC instant): it carries that cycle's SYNC counter, the truth frames of
the same instant and the controller's answers that follow before the next sample
(``DRIVE_RPDO1`` with its ``cycle`` counter, ``CTRL_TPDO1``, ``CTRL_TPDO2``).  Which
frames are cyclic comes from the DBCs (``GenMsgCycleTime``); the event-driven statusword
is carried forward as the drive's state.  The columns are ``time_s`` (since the trace's
first frame), ``sample``, then ``SIGNAL_UNIT`` for every signal in the trace
(``T_meas_Nm``, ``velocity_radps``, ``sync_counter_cycle``, ...) in DBC order; a cell is
empty where that cycle's frame is missing.

:func:`read_cycles` gives the same table as numpy arrays (NaN where empty).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hdhil.can.traces.decode import DecodedFrame, FrameDecoder, FrameKind, default_decoder
from hdhil.can.traces.reader import read_trace

#: The message whose arrival opens a row: the drive's sensor frame of sample k.
SAMPLE_MESSAGE = "DRIVE_TPDO1"
#: Event-driven messages whose last value is carried into every row.
STATE_MESSAGES = ("DRIVE_TPDO2",)
#: The leading columns of every row.
INDEX_COLUMNS = ("time_s", "sample")


def unit_slug(unit: str) -> str:
    """A unit as a column-name suffix: ``rad/s`` -> ``radps``, ``Nm/s`` -> ``Nmps``,
    ``rad/s^2`` -> ``radps2``, ``%`` -> ``pct``; empty for no unit."""
    text = unit.strip().replace("µ", "u").replace("²", "2").replace("%", "pct")
    text = text.replace("/", "p").replace("^", "")
    return re.sub(r"[^0-9A-Za-z]", "", text)


def column_name(signal: str, unit: str) -> str:
    """``signal`` with its unit appended (``T_meas`` + ``Nm`` -> ``T_meas_Nm``)."""
    slug = unit_slug(unit)
    if not slug or signal == slug or signal.endswith(f"_{slug}"):
        return signal  # "cycle" in cycles stays "cycle"
    return f"{signal}_{slug}"


@dataclass(frozen=True)
class CycleColumn:
    """One signal column: its name with unit, and where its values come from."""

    name: str
    message: str
    signal: str
    unit: str


def cycle_columns(decoder: FrameDecoder | None = None) -> list[CycleColumn]:
    """Every column a per-cycle table can have, in DBC order (control bus, then truth)."""
    decoder = decoder or default_decoder()
    columns: list[CycleColumn] = []
    seen: set[str] = set()
    for _bus, db in decoder.databases.items():
        for message in db.messages:
            if not (message.cycle_time or message.name in STATE_MESSAGES):
                continue
            for fmt in decoder.formats[message.name]:
                name = column_name(fmt.name, fmt.unit)
                if name in seen:  # the same signal name in two messages: qualify it
                    name = f"{message.name}.{name}"
                seen.add(name)
                columns.append(CycleColumn(name, message.name, fmt.name, fmt.unit))
    return columns


class CycleBuilder:
    """Turns decoded frames, in trace order, into per-cycle rows.

    ``emit(time_s, sample, values)`` is called once per sample with the sample's values
    (``None`` where absent), in the order of :attr:`columns`; :attr:`present` tells
    which columns ever had a value.  Call :meth:`finish` after the last frame.
    """

    def __init__(
        self,
        emit: Callable[[float, int, list[float | int | None]], None],
        decoder: FrameDecoder | None = None,
    ) -> None:
        self.columns = cycle_columns(decoder)
        self.present = [False] * len(self.columns)
        self._emit = emit
        self._slots: dict[str, list[tuple[str, int]]] = {}
        for i, col in enumerate(self.columns):
            self._slots.setdefault(col.message, []).append((col.signal, i))
        self._state = frozenset(STATE_MESSAGES)
        self._row: list[float | int | None] | None = None
        self._pending: list[float | int | None] = [None] * len(self.columns)
        self._carried: dict[int, float | int] = {}
        self._t0: float | None = None
        self._time = 0.0
        self.samples = 0

    def add(self, frame: DecodedFrame) -> None:
        if self._t0 is None:
            self._t0 = frame.time
        if frame.kind is not FrameKind.DECODED or frame.message is None:
            return
        slots = self._slots.get(frame.message)
        if slots is None:
            return
        message = frame.message
        if message == SAMPLE_MESSAGE:
            self._flush()
            row = self._pending
            self._pending = [None] * len(self.columns)
            for i, value in self._carried.items():
                row[i] = value
            self._row = row
            self._time = frame.time - self._t0
            target: list[float | int | None] | None = row
        elif message == "SYNC" or frame.bus == "truth":
            target = self._pending  # sent for the coming sample, before its sensor frame
        else:
            target = self._row  # the controller's answers, after the sensor frame
        signals = frame.signals
        state = message in self._state
        for signal, i in slots:
            if signal in signals:
                value = signals[signal]
                if state:
                    self._carried[i] = value
                if target is not None:
                    target[i] = value

    def _flush(self) -> None:
        row = self._row
        if row is None:
            return
        for i, value in enumerate(row):
            if value is not None:
                self.present[i] = True
        self._emit(self._time, self.samples, row)
        self.samples += 1
        self._row = None

    def finish(self) -> None:
        self._flush()


def read_cycles(
    path: str | os.PathLike[str], decoder: FrameDecoder | None = None
) -> dict[str, np.ndarray]:
    """A trace as per-cycle arrays: ``time_s``, ``sample`` and one float array per signal
    that occurred (names with units, as ``hdhil dump --csv`` writes them; NaN where a
    cycle's frame is missing).  Damage in the trace is a :class:`ValueError` naming it.
    ``decoder``: the trace's frame decoder (default: the project DBCs)."""
    decoder = decoder or default_decoder()
    times: list[float] = []
    rows: list[list[float]] = []

    def emit(t: float, _sample: int, values: Iterable[float | int | None]) -> None:
        times.append(t)
        rows.append([math.nan if v is None else float(v) for v in values])

    builder = CycleBuilder(emit, decoder)
    trace = read_trace(Path(path))
    with trace:
        for msg in trace:
            builder.add(decoder.classify(msg))
    builder.finish()
    if trace.damage:
        raise ValueError(trace.damage[0].describe(trace.path))
    table = np.array(rows, dtype=np.float64).reshape(len(rows), len(builder.columns))
    out: dict[str, np.ndarray] = {
        "time_s": np.array(times, dtype=np.float64),
        "sample": np.arange(len(rows), dtype=np.int64),
    }
    for i, col in enumerate(builder.columns):
        if builder.present[i]:
            out[col.name] = table[:, i]
    return out

"""Trace logging: every frame of the control bus and the truth channel into one file.

The writer is python-can's, chosen by the file extension (``.blf`` default, ``.asc``,
``.log`` candump, ``.csv``, ``.trc``).  Frames are stamped with the python-can channel
number of their bus (:data:`hdhil.dbc.CHANNEL_NUMBER`: control 0, truth 1) so a dump can
tell the buses apart; formats without channels (CSV) still decode because truth frames use
29-bit identifiers.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import can

SUPPORTED_SUFFIXES = (".blf", ".asc", ".log", ".csv", ".trc")


def open_writer(path: Path) -> can.io.generic.MessageWriter:
    """A python-can writer for ``path``, with a clear error for unsupported formats."""
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise ValueError(
            f"unsupported trace format {suffix or '(none)'!r} for {path}: "
            f"use one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    if path.parent and not path.parent.exists():
        raise ValueError(f"cannot write trace {path}: directory {path.parent} does not exist")
    try:
        return can.Logger(str(path))
    except OSError as exc:
        raise ValueError(f"cannot write trace {path}: {exc.strerror or exc}") from None


class FrameCounter(can.Listener):
    """Counts frames per (channel, identifier)."""

    def __init__(self) -> None:
        self.counts: dict[tuple[int, int], int] = {}

    def on_message_received(self, msg: can.Message) -> None:
        key = (msg.channel, msg.arbitration_id)
        self.counts[key] = self.counts.get(key, 0) + 1

    @property
    def total(self) -> int:
        return sum(self.counts.values())


def _timestamp(item: tuple[float, int, can.Message]) -> float:
    return item[0]


class BusTap:
    """Drains listen-only buses and hands each frame, channel-stamped, to listeners.

    ``buses`` maps a channel number to the bus that listens on it.  The frame handed on is
    the received frame itself when it already carries that channel number (``simbus`` with
    ``trace_channel``), else a fresh :class:`can.Message` carrying it (received frames are
    shared between receivers and are never modified).
    """

    def __init__(self, buses: dict[int, can.BusABC], listeners: Iterable[can.Listener]) -> None:
        self.buses = buses
        self.listeners = list(listeners)
        self._callbacks = [listener.on_message_received for listener in self.listeners]

    def poll(self) -> int:
        """Hand on every waiting frame, all channels merged in timestamp order.

        Frames of one bus arrive in order; across buses the timestamp decides (the truth
        frame of cycle k, stamped at the sample instant t(k), precedes the telemetry of
        cycle k).  Ties keep channel order.
        """
        batch: list[tuple[float, int, can.Message]] = []
        for channel, bus in self.buses.items():
            recv = bus.recv
            while (msg := recv(0)) is not None:
                batch.append((msg.timestamp, channel, msg))
        if not batch:
            return 0
        batch.sort(key=_timestamp)
        callbacks = self._callbacks
        for _, channel, msg in batch:
            if msg.channel == channel:
                for callback in callbacks:
                    callback(msg)
                continue
            stamped = can.Message(
                timestamp=msg.timestamp,
                arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id,
                is_remote_frame=msg.is_remote_frame,
                is_error_frame=msg.is_error_frame,
                dlc=msg.dlc,
                data=msg.data,
                channel=channel,
                is_rx=True,
                check=False,
            )
            for callback in callbacks:
                callback(stamped)
        return len(batch)

    def stop(self) -> None:
        """Flush and close every listener (writers close their files)."""
        for listener in self.listeners:
            listener.stop()

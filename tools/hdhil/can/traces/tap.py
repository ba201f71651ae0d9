"""The host tap: a run's listen-only buses drained into its listeners.

:class:`BusTap` hands every frame of the control bus and the truth channel, merged in
timestamp order and stamped with the python-can channel number of its bus
(:data:`hdhil.dbc.CHANNEL_NUMBER`: control 0, truth 1), to the run's listeners: the trace
writer, :class:`FrameCounter`, the scorers.  The channel number lets a dump tell the buses
apart; formats without channels (CSV) still decode because truth frames use 29-bit
identifiers.  Listeners get each poll's frames in one call where they can take them.
"""

from __future__ import annotations

import operator
from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any

import can

from hdhil.can.groups import FrameGroup, GroupChannel, expand_groups
from hdhil.can.simbus import SimBus, received_copy


class FrameCounter(can.Listener):
    """Counts frames per (channel, identifier)."""

    def __init__(self) -> None:
        #: Per (channel, identifier) of a message, or (channel, identifiers) of a frame
        #: group (:attr:`FrameGroup.arbitration_id`): a batch is counted in one pass.
        self._counts: Counter[tuple[int, int | tuple[int, ...]]] = Counter()

    @property
    def counts(self) -> dict[tuple[int, int], int]:
        """Frames per (channel, identifier)."""
        counts: dict[tuple[int, int], int] = {}
        for (channel, ident), n in self._counts.items():
            for arbitration_id in ident if ident.__class__ is tuple else (ident,):
                key = (channel, arbitration_id)
                counts[key] = counts.get(key, 0) + n
        return counts

    def on_message_received(self, msg: can.Message) -> None:
        self._counts[(msg.channel, msg.arbitration_id)] += 1

    #: :meth:`on_frames` takes :class:`FrameGroup` items (:class:`BusTap`).
    takes_frame_groups = True

    def on_frames(self, frames: list[can.Message | FrameGroup]) -> None:
        self._counts.update(map(_frame_key, frames))

    @property
    def total(self) -> int:
        return sum(self.counts.values())


#: A frame's key in :attr:`FrameCounter._counts` (a frame group's identifiers: a tuple).
_frame_key = operator.attrgetter("channel", "arbitration_id")
_timestamp = operator.attrgetter("timestamp")


def _frames_callback(listener: can.Listener) -> Callable[[list[can.Message]], object]:
    """``listener.on_frames``, or a loop over ``on_message_received``."""
    on_frames = getattr(listener, "on_frames", None)
    if on_frames is not None:
        return on_frames
    callback = listener.on_message_received

    def one_by_one(frames: list[can.Message]) -> None:
        for msg in frames:
            callback(msg)

    return one_by_one


def _drain(channel: int, bus: can.BusABC | GroupChannel) -> Callable[[list[Any]], int]:
    """A function appending every frame waiting on ``bus`` to its argument, stamped with
    ``channel``; it returns how many (a frame group counts once)."""
    if isinstance(bus, GroupChannel):
        if bus.channel != channel:
            raise ValueError(f"frame groups of channel {bus.channel} tapped as channel {channel}")
        return bus.drain_into
    if isinstance(bus, SimBus) and bus.trace_channel == channel:
        return bus.drain_into  # frames already carry the channel number
    recv = bus.recv

    def drain(batch: list[can.Message]) -> int:
        append = batch.append
        n = 0
        while (msg := recv(0)) is not None:
            append(msg if msg.channel == channel else _stamped(msg, channel))
            n += 1
        return n

    return drain


def _stamped(msg: can.Message, channel: int) -> can.Message:
    """A copy of a received frame carrying the trace's channel number."""
    copy = received_copy(msg, channel)
    copy.timestamp = msg.timestamp
    return copy


class BusTap:
    """Drains listen-only buses and hands each frame, channel-stamped, to listeners.

    ``buses`` maps a channel number to the bus that listens on it.  The frame handed on is
    the received frame itself when it already carries that channel number (``simbus`` with
    ``trace_channel``), else a fresh :class:`can.Message` carrying it (received frames are
    shared between receivers and are never modified).

    A listener with an ``on_frames(frames)`` method gets each poll's frames in one call
    (:class:`WriterProcess`, :class:`FrameCounter`, the scorers); any other
    :class:`can.Listener` gets them one by one through ``on_message_received``.

    A bus may be a :class:`GroupChannel` (the in-process truth channel): a listener that
    says it ``takes_frame_groups`` gets its :class:`FrameGroup` items as they are; every
    other listener gets their frames as messages, in the same place of the batch.
    """

    def __init__(self, buses: dict[int, can.BusABC | GroupChannel],
                 listeners: Iterable[can.Listener]) -> None:  # fmt: skip
        self.listeners = list(listeners)
        self._deliver = [_frames_callback(listener) for listener in self.listeners]
        #: Per listener: whether it takes frame groups as they are.
        self._takes_groups = [
            bool(getattr(listener, "takes_frame_groups", False)) for listener in self.listeners
        ]
        self._drains = [_drain(channel, bus) for channel, bus in buses.items()]
        self._groups = any(isinstance(bus, GroupChannel) for bus in buses.values())

    def poll(self) -> int:
        """Hand on every waiting frame, all channels merged in timestamp order; returns
        how many (a frame group counts once).

        Frames of one bus arrive in order; across buses the timestamp decides (the truth
        frame of cycle k, stamped at the sample instant t(k), precedes the telemetry of
        cycle k).  Ties keep channel order (the sort is stable).
        """
        batch: list[can.Message] = []
        channels = 0
        for drain in self._drains:
            channels += drain(batch) > 0
        if not batch:
            return 0
        if channels > 1:
            batch.sort(key=_timestamp)
        if not self._groups:
            for deliver in self._deliver:
                deliver(batch)
            return len(batch)
        expanded = None
        for deliver, takes_groups in zip(self._deliver, self._takes_groups, strict=True):
            if takes_groups:
                deliver(batch)
            else:
                if expanded is None:
                    expanded = expand_groups(batch)
                deliver(expanded)
        return len(batch)

    def stop(self) -> None:
        """Flush and close every listener (writers close their files)."""
        for listener in self.listeners:
            listener.stop()

"""Frame groups: frames one sender puts on a channel together, handed on as one record.

The drive sends its three truth frames (``truth.dbc``) at one instant every cycle. On
the in-process truth channel of a lockstep run nothing shares a wire with them (bit rate
0, no faults): the channel delivers at once, in the order sent, to the run's tap alone.
A :class:`GroupChannel` stands in for that channel: the sender hands the payloads of a
cycle in one call (``send_group``) and the tap gets one :class:`FrameGroup` for them,
instead of three python-can messages copied, queued and drained one by one.

A group means exactly the frames it holds: the same identifiers, payloads, channel
number and timestamp (the sim clock's time when sent, never earlier than the previous
delivery, as :class:`hdhil.can.simbus.SimBus` stamps a channel without a wire). Listeners
that take groups (``takes_frame_groups``: the trace writer, the frame counter, the
scorer) read them as they are; any other listener gets the frames as messages
(:func:`group_messages`), so what every listener sees is unchanged. A channel with
injected faults is a :class:`SimBus`: faults act on single frames.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import can

from hdhil.can.simbus import SimClock, _snapshot_fast, received_copy

__all__ = ["FrameGroup", "GroupChannel", "expand_groups", "group_messages"]


class FrameGroup(NamedTuple):
    """Data frames sent together: ``ids[i]`` carries ``payloads[i]``, all at ``timestamp``
    on channel number ``channel``; ``extended`` says whether the identifiers are 29-bit."""

    timestamp: float
    channel: int
    ids: tuple[int, ...]
    extended: bool
    payloads: tuple[bytes, ...]

    @property
    def arbitration_id(self) -> tuple[int, ...]:
        """The identifiers, under a message's name for its identifier: a batch's
        ``(channel, arbitration_id)`` are read alike from messages and groups (the
        frame counter's keys)."""
        return self.ids


_new_message = object.__new__
_new_tuple = tuple.__new__


def _group_messages_fast(group: FrameGroup) -> list[can.Message]:
    out = []
    for arbitration_id, data in zip(group.ids, group.payloads, strict=True):
        msg = _new_message(can.Message)  # field by field, as simbus copies a frame
        msg.timestamp = group.timestamp
        msg.arbitration_id = arbitration_id
        msg.is_extended_id = group.extended
        msg.is_remote_frame = False
        msg.is_error_frame = False
        msg.channel = group.channel
        msg.dlc = len(data)
        msg.data = data
        msg.is_fd = False
        msg.is_rx = True
        msg.bitrate_switch = False
        msg.error_state_indicator = False
        out.append(msg)
    return out


def _group_messages_checked(group: FrameGroup) -> list[can.Message]:
    return [
        can.Message(
            timestamp=group.timestamp,
            arbitration_id=i,
            data=d,
            dlc=len(d),
            is_extended_id=group.extended,
            channel=group.channel,
            is_rx=True,
            check=False,
        )
        for i, d in zip(group.ids, group.payloads, strict=True)
    ]


#: The frames of a group as received python-can messages, in order: built field by
#: field while python-can's Message has the fields simbus fills, else by its constructor.
group_messages = (
    _group_messages_fast if received_copy is _snapshot_fast else _group_messages_checked
)


def expand_groups(batch: Sequence[Any]) -> list[Any]:
    """``batch`` with every :class:`FrameGroup` replaced by its messages, in place."""
    out: list[Any] = []
    for item in batch:
        if item.__class__ is FrameGroup:
            out += group_messages(item)
        else:
            out.append(item)
    return out


class GroupChannel:
    """A channel without a wire whose senders send frame groups, drained by one tap.

    ``channel`` is the channel number the groups carry (the trace's); the clock stamps
    them. ``frames_sent`` counts frames, as a :class:`SimBus` counts its channel's.
    """

    def __init__(self, clock: SimClock, channel: int, name: str = "") -> None:
        self.clock = clock
        self.channel = channel
        self.channel_info = f"frame groups {name}".strip()
        self.frames_sent = 0
        self._last = 0.0
        self._queue: list[FrameGroup] = []

    def send_group(self, ids: tuple[int, ...], extended: bool,
                   payloads: tuple[bytes, ...]) -> None:  # fmt: skip
        """Send ``payloads`` on ``ids`` together, now (delivered at once, in order)."""
        now = self.clock.now
        if now > self._last:
            self._last = now
        # Built by tuple.__new__, all fields in order: the NamedTuple's generated
        # __new__ (keyword handling) is a call of its own.
        self._queue.append(_new_tuple(FrameGroup, (self._last, self.channel, ids, extended,
                                                   payloads)))  # fmt: skip
        self.frames_sent += len(ids)

    @property
    def frames_requested(self) -> int:
        return self.frames_sent

    def drain_into(self, batch: list[Any]) -> int:
        """Move every group waiting to the end of ``batch``; returns how many."""
        queue = self._queue
        n = len(queue)
        if n:
            batch += queue
            queue.clear()
        return n

    def shutdown(self) -> None:
        self._queue.clear()

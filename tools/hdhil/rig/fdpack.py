"""CAN FD packing on a rig's FD bus: the joints' cyclic PDOs share one FD frame per direction.

On an FD bus the rig's database (:func:`hdhil.canopen.rigdb.rig_packing`) has each
cyclic drive PDO of the bus's joints packed into FD frames: ``FD_DRIVE_TPDO1`` (every
joint's sensor frame, one after another) at the first joint's TPDO1 identifier and
``FD_DRIVE_RPDO1`` (every joint's command) at its RPDO1 identifier; the controllers'
telemetry goes as FD frames of its own. One transmitter sends each packed frame, as a
multi-axis drive or controller does (docs/schedule.md, "FD packing in a rig run").

The nodes stay one per drive and per controller, each with its own object dictionary,
NMT state, heartbeat and SDO server, and encode and decode their own frames. Between
them and the wire sits :class:`FdGateway`, one per FD bus: each node sends through a
:class:`PackingBus`, which hands the node's member frames of a packed PDO to the gateway
(nothing on the wire), sends its cyclic telemetry as an FD frame with bit-rate switching
and everything else as it is; on receipt it hands the node each member frame of a packed
frame as the node's own frame. The gateway is a node of the loop, polled after the
others: in each round of a cycle it sends every packed frame whose members came in that
round (the drives' sensor frames right after SYNC, the controllers' commands after
their interrupts), at the identifier and layout of the database. A member that sent
nothing in the round (a drive not yet in operation, a joint that went safe) is zero in
the frame and not handed to its receivers: the one thing the emulation knows beside the
frame, as a multi-axis device knows its axes' states.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import can

from hdhil.canopen.rigdb import PackedPdo

__all__ = ["FdGateway", "PackingBus"]


class _Group:
    """One packed frame being filled: its layout, its buffer and which members came."""

    __slots__ = ("buffer", "fresh", "layout", "message", "sent_fresh")

    def __init__(self, layout: PackedPdo, brs: bool) -> None:
        self.layout = layout
        self.buffer = bytearray(layout.length)
        self.fresh = [False] * len(layout.members)
        #: Which members the latest packed frame carried (for its receivers).
        self.sent_fresh: tuple[bool, ...] = tuple(self.fresh)
        self.message = can.Message(arbitration_id=layout.frame_id, is_extended_id=False,
                                   is_fd=True, bitrate_switch=brs, dlc=layout.length,
                                   data=bytes(layout.length), check=False)  # fmt: skip


class FdGateway:
    """The transmitter of one FD bus's packed frames (module docstring): a node of the
    loop with its own handle on the bus (``bus``), polled after the nodes."""

    def __init__(
        self, bus: Any, packed: Sequence[PackedPdo], telemetry_ids: Sequence[int], brs: bool
    ) -> None:
        self.bus = bus
        self.brs = brs
        self.groups = [_Group(layout, brs) for layout in packed]
        #: Member identifier -> (its group, its index there).
        self.member_of: dict[int, tuple[_Group, int]] = {
            m.frame_id: (g, k) for g in self.groups for k, m in enumerate(g.layout.members)
        }
        #: Packed frame identifier -> its group.
        self.packed_at = {g.layout.frame_id: g for g in self.groups}
        self.telemetry_ids = frozenset(telemetry_ids)
        self._dirty: list[_Group] = []
        self._scratch: list[can.Message] = []
        #: Packed frames sent.
        self.frames_sent = 0

    def deposit(self, msg: can.Message) -> bool:
        """Take ``msg`` if it is a member of a packed frame (True), else leave it (False)."""
        if msg.is_extended_id:
            return False
        entry = self.member_of.get(msg.arbitration_id)
        if entry is None:
            return False
        group, k = entry
        member = group.layout.members[k]
        data = bytes(msg.data)
        if len(data) != member.length or msg.is_remote_frame:
            return False
        group.buffer[member.offset : member.offset + member.length] = data
        if not any(group.fresh):
            self._dirty.append(group)
        group.fresh[k] = True
        return True

    # -- a node of the loop
    def boot(self, now: float) -> None:
        """Nothing to boot: the gateway has no CANopen state of its own."""

    def tick(self, now: float) -> None:
        """No timers."""

    def on_message(self, msg: can.Message) -> None:
        """The gateway reads nothing from the bus."""

    def poll(self) -> int:
        """Send every packed frame whose members came since the last poll; return how
        many went out."""
        scratch = self._scratch
        self.bus.drain_into(scratch)  # its own handle hears the bus: nothing to read
        scratch.clear()
        dirty = self._dirty
        if not dirty:
            return 0
        for group in dirty:
            message = group.message
            message.data = bytes(group.buffer)
            group.sent_fresh = tuple(group.fresh)
            group.buffer[:] = bytes(len(group.buffer))
            group.fresh = [False] * len(group.fresh)
            self.bus.send(message)
        n = len(dirty)
        self.frames_sent += n
        dirty.clear()
        return n

    def unpacked(self, msg: can.Message) -> list[can.Message] | None:
        """The member frames of the packed frame ``msg`` that it carries fresh (None: not
        a packed frame of this bus)."""
        if not msg.is_fd or msg.is_extended_id:
            return None
        group = self.packed_at.get(msg.arbitration_id)
        if group is None or len(msg.data) != group.layout.length:
            return None
        data = msg.data
        out = []
        for member, fresh in zip(group.layout.members, group.sent_fresh, strict=True):
            if fresh:
                out.append(can.Message(
                    timestamp=msg.timestamp, arbitration_id=member.frame_id,
                    is_extended_id=False, dlc=member.length,
                    data=bytes(data[member.offset : member.offset + member.length]),
                    channel=msg.channel, is_rx=True, check=False,
                ))  # fmt: skip
        return out


class PackingBus:
    """A node's handle on an FD bus with packing (module docstring): ``send`` and
    ``dispatch``/``recv`` as the node's own bus, everything else the wrapped handle's."""

    def __init__(self, bus: Any, gateway: FdGateway) -> None:
        self._bus = bus
        self._gateway = gateway
        self._handlers: dict[Callable[[can.Message], object], Callable[[can.Message], object]]
        self._handlers = {}
        self._pending: list[can.Message] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._bus, name)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        gateway = self._gateway
        if gateway.deposit(msg):
            return
        if not msg.is_fd and not msg.is_extended_id and msg.arbitration_id in gateway.telemetry_ids:
            msg = can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False,
                              is_fd=True, bitrate_switch=gateway.brs, dlc=len(msg.data),
                              data=bytes(msg.data), check=False)  # fmt: skip
        self._bus.send(msg, timeout)

    def dispatch(self, handler: Callable[[can.Message], object]) -> int:
        """The wrapped handle's ``dispatch``, a packed frame handed on as its members."""
        wrapped = self._handlers.get(handler)
        if wrapped is None:
            unpacked = self._gateway.unpacked

            def wrapped(msg: can.Message) -> None:
                members = unpacked(msg)
                if members is None:
                    handler(msg)
                else:
                    for member in members:
                        handler(member)

            self._handlers[handler] = wrapped
        return int(self._bus.dispatch(wrapped))

    def recv(self, timeout: float | None = None) -> can.Message | None:
        pending = self._pending
        while not pending:
            msg = self._bus.recv(timeout)
            if msg is None:
                return None
            members = self._gateway.unpacked(msg)
            if members is None:
                return msg  # type: ignore[no-any-return]
            pending.extend(members)
        return pending.pop(0)

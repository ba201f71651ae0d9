"""What every CAN node here shares: frame dispatch and non-blocking polling.

A node registers a handler per ``(frame_id, is_extended_id)``.  Frames of the bus's DBC
that are not addressed to it are ignored; anything else (an identifier the DBC does not
know) is counted in ``unknown_frames``.  Error frames are never data: they are counted in
``error_frames`` and go to no handler, whatever identifier they carry.  Nodes only ever
use the python-can ``BusABC`` API, so they run on ``simbus``, ``virtual``, SocketCAN or
a real adapter alike.
"""

from __future__ import annotations

from collections.abc import Callable

import can

from hdhil.dbc import BusName, FrameCodec, known_frames

Handler = Callable[[can.Message], None]


class CanNode:
    """Dispatches received frames of one bus to handlers."""

    def __init__(self, bus: can.BusABC, bus_name: BusName = "control") -> None:
        self.bus = bus
        self.unknown_frames: dict[int, int] = {}
        self.error_frames = 0
        self._known = known_frames(bus_name)
        self._handlers: dict[tuple[int, bool], Handler] = {}
        #: The handlers of 11-bit identifiers by identifier alone (the 1 kHz frames).
        self._base_handlers: dict[int, Handler] = {}
        # A bus that can hand queued frames straight to a handler (simbus) is drained
        # without a recv() call per frame; any other python-can bus through recv(0).
        self._dispatch: Callable[[Handler], int] | None = getattr(bus, "dispatch", None)

    def handle(self, frame_id: int, handler: Handler, extended: bool = False) -> None:
        """Route frames with this identifier to ``handler``."""
        self._handlers[(frame_id, extended)] = handler
        if not extended:
            self._base_handlers[frame_id] = handler

    def unhandle(self, frame_id: int, extended: bool = False) -> None:
        """Stop routing frames with this identifier (they count as any other frame)."""
        self._handlers.pop((frame_id, extended), None)
        if not extended:
            self._base_handlers.pop(frame_id, None)

    def on_message(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.error_frames += 1
            return
        if not msg.is_extended_id:
            handler = self._base_handlers.get(msg.arbitration_id)
            if handler is not None:
                handler(msg)
                return
        key = (msg.arbitration_id, msg.is_extended_id)
        handler = self._handlers.get(key)
        if handler is not None:
            handler(msg)
        elif key not in self._known:
            self.unknown_frames[msg.arbitration_id] = (
                self.unknown_frames.get(msg.arbitration_id, 0) + 1
            )

    def poll(self) -> int:
        """Handle every frame waiting on the bus without blocking; returns how many."""
        if self._dispatch is not None:
            return self._dispatch(self.on_message)
        n = 0
        recv = self.bus.recv
        while (msg := recv(0)) is not None:
            self.on_message(msg)
            n += 1
        return n


def pdo_cob_id(od: object, comm_index: int, frame: FrameCodec) -> int:
    """The COB-ID of a PDO, read from the node's object dictionary.

    ``comm_index`` is the PDO's communication parameter (0x1400.. RPDO, 0x1800.. TPDO),
    sub-index 1 (CiA 301; bit 31 = PDO not valid, bit 30 = no RTR, 11-bit identifier).
    The node encodes the payload with ``frame``, the DBC's layout of the same PDO; if the
    two disagree the node refuses to start instead of talking past its peer.
    """
    cob_id = int(od[comm_index][1].default) & 0x7FF  # type: ignore[index]
    if cob_id != frame.frame_id:
        raise ValueError(
            f"PDO 0x{comm_index:04X}: the object dictionary's COB-ID 0x{cob_id:03X} does not "
            f"match {frame.name} (0x{frame.frame_id:03X}) in control.dbc"
        )
    return cob_id

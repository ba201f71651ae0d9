"""What every CAN node here shares: frame dispatch and non-blocking polling.

A node registers a handler per ``(frame_id, is_extended_id)``.  Frames of the bus's DBC
that are not addressed to it are ignored; anything else (an identifier the DBC does not
know) is counted in ``unknown_frames``.  Error frames are never data: they are counted in
``error_frames`` and go to no handler, whatever identifier they carry.  Nodes only ever
use the python-can ``BusABC`` API, so they run on ``simbus``, ``virtual``, SocketCAN or
a real adapter alike.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import can

from hdhil.dbc import BusName, FrameCodec, known_frames

Handler = Callable[[can.Message], None]


class CanNode:
    """Dispatches received frames of one bus to handlers."""

    def __init__(
        self,
        bus: can.BusABC,
        bus_name: BusName = "control",
        *,
        drive_node_id: int | Sequence[int] | None = None,
        controller_node_id: int | None = None,
    ) -> None:
        self.bus = bus
        self.unknown_frames: dict[int, int] = {}
        self.error_frames = 0
        # the DBC's frames, the drive's (or each drive's) and the controller's at their
        # node-IDs
        drives = drive_node_id if isinstance(drive_node_id, Sequence) else (drive_node_id,)
        drives = drives or (None,)
        self._known = known_frames(bus_name, drives[0], controller_node_id).union(
            *(known_frames(bus_name, drive, controller_node_id) for drive in drives[1:])
        )
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


#: The dummy-mapping data types 0x0001..0x0007 and their sizes (CiA 301 §7.4.7.1): a
#: mapping entry of one leaves a gap in the frame.
_DUMMY_BITS = {0x1: 1, 0x2: 8, 0x3: 16, 0x4: 32, 0x5: 8, 0x6: 16, 0x7: 32}


def _int_entry(od: object, index: int, sub: int, read: Callable[[int, int], int] | None) -> int:
    if read is not None:
        return int(read(index, sub))
    return int(od[index][sub].default or 0)  # type: ignore[index]


def pdo_cob_id(
    od: object,
    comm_index: int,
    frame: FrameCodec,
    read: Callable[[int, int], int] | None = None,
) -> int:
    """The COB-ID of a PDO, read from the node's object dictionary.

    ``comm_index`` is the PDO's communication parameter (0x1400.. RPDO, 0x1800.. TPDO),
    sub-index 1 (CiA 301; bit 31 = PDO not valid, bit 30 = no RTR, 11-bit identifier):
    the object dictionary gives the identifier (the EDS's ``$NODEID+0x180`` etc. at the
    node's node-ID, CiA 301's pre-defined connection set, or what a DCF or the node's
    configuration set).  ``frame`` is the DBC's layout of the same PDO, whatever
    identifier the DBC gives it: the node encodes the payload with it, so when the
    object dictionary's mapping (``comm_index + 0x200``) lays out other signals (their
    number, sizes or positions) the node refuses to start instead of talking past its
    peer.  ``read(index, sub)`` reads the present values (default: the EDS defaults).
    """
    cob_id = _int_entry(od, comm_index, 1, read) & 0x7FF
    mapping = comm_index + 0x200
    count = _int_entry(od, mapping, 0, read)
    fields = []
    start = 0
    for sub in range(1, count + 1):
        entry = _int_entry(od, mapping, sub, read)
        bits = entry & 0xFF
        if (entry >> 16) not in _DUMMY_BITS:
            fields.append((start, bits))
        start += bits
    signals = sorted((s.start, s.length) for s in frame.message.signals)
    if fields != signals or start != 8 * frame.length:
        raise ValueError(
            f"PDO 0x{comm_index:04X} (COB-ID 0x{cob_id:03X}): the object dictionary maps "
            f"{len(fields)} object(s) in {start // 8} bytes (bits {fields}), but "
            f"{frame.name} in control.dbc lays out {len(signals)} signal(s) in "
            f"{frame.length} bytes (bits {signals})"
        )
    return cob_id

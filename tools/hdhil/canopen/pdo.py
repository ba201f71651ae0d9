"""PDOs configured at run time from the object dictionary (CiA 301 §7.2.2, §7.4.7.1,
§7.5.2.35-38): the checks of the mapping procedure, the live layout of each PDO, and
the transmission of a TPDO by its transmission type, inhibit time and event timer.

The mapping objects (RPDO 0x1600-0x17FF, TPDO 0x1A00-0x1BFF) are checked when written,
over SDO or by the application: an entry must name an object that exists (0x06020000),
is PDO-mappable (0x06040041) and whose length it states (0x06040043); a dummy entry
(data types 0x0001-0x0007) must state the type's size; sub-index 0 may not enable more
entries than exist or more than 64 bits (0x06040042).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import can
from canopen.objectdictionary import ObjectDictionary

from hdhil.canopen.clock import TIME_EPSILON
from hdhil.canopen.od import variable
from hdhil.canopen.sdo import (
    ABORT_INCOMPATIBLE,
    ABORT_INVALID_VALUE,
    ABORT_NO_OBJECT,
    ABORT_NOT_MAPPABLE,
    ABORT_PDO_LENGTH,
    ABORT_UNSUPPORTED_ACCESS,
)

__all__ = [
    "DUMMY_BITS",
    "MAX_PDO_BITS",
    "PDO_NOT_VALID",
    "PdoLayout",
    "Tpdo",
    "check_comm_write",
    "check_mapping_count",
    "check_mapping_entry",
    "check_mapping_write",
    "decode_to_od",
    "encode_from_od",
    "read_layout",
]

#: Bit size of the dummy-mapping data types 0x0001..0x0007 (CiA 301 §7.4.7.1).
DUMMY_BITS = {0x1: 1, 0x2: 8, 0x3: 16, 0x4: 32, 0x5: 8, 0x6: 16, 0x7: 32}

#: A classical CAN PDO carries at most 8 bytes.
MAX_PDO_BITS = 64


def check_mapping_entry(od: ObjectDictionary, value: int) -> int | None:
    """Abort code for a mapping entry ``index << 16 | sub << 8 | bits``, None if valid."""
    if value == 0:
        return None
    index, sub, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
    if index in DUMMY_BITS:
        return None if sub == 0 and bits == DUMMY_BITS[index] else ABORT_INCOMPATIBLE
    var = variable(od, index, sub)
    if var is None:
        return ABORT_NO_OBJECT
    if not var.pdo_mappable:
        return ABORT_NOT_MAPPABLE
    if bits != len(var):
        return ABORT_INCOMPATIBLE
    return None


def check_mapping_count(
    od: ObjectDictionary, read: Callable[[int, int], int], index: int, count: int
) -> int | None:
    """Abort code for writing ``count`` to sub-index 0 of mapping object ``index``.

    ``read(index, sub)`` returns the entries as stored now.
    """
    obj = od.get(index)
    entries = [s for s in getattr(obj, "subindices", {}) if s > 0]
    if count > len(entries):
        return ABORT_PDO_LENGTH
    total = 0
    for sub in range(1, count + 1):
        total += read(index, sub) & 0xFF
    return ABORT_PDO_LENGTH if total > MAX_PDO_BITS else None


# ------------------------------------------------------------------ run-time PDOs

#: COB-ID bit 31: the PDO is not valid (CiA 301 §7.5.2.35); bit 30: no RTR allowed.
PDO_NOT_VALID = 1 << 31
RTR_NOT_ALLOWED = 1 << 30
#: Transmission types (CiA 301 table "description of TPDO transmission type").
ACYCLIC_SYNCHRONOUS = 0
MAX_SYNCHRONOUS = 240
EVENT_MANUFACTURER = 254
EVENT_PROFILE = 255

#: Highest PDO number per direction (CiA 301: 512; this project's nodes have 4).
MAX_PDOS = 4


def comm_index_of(kind: str, number: int) -> int:
    """Communication parameter index of RPDO/TPDO ``number`` (1-based)."""
    return (0x1400 if kind == "rpdo" else 0x1800) + number - 1


@dataclass(frozen=True)
class PdoLayout:
    """One PDO as its communication and mapping parameters say now.

    ``entries`` are ``(index, sub, bits)`` of the mapped objects (dummy entries keep
    their data type as index); ``inhibit_s`` (sub 3, 100 µs units) and ``event_s``
    (sub 5, ms) are 0 when absent.
    """

    kind: str
    number: int
    cob_id: int
    valid: bool
    trans_type: int
    inhibit_s: float
    event_s: float
    entries: tuple[tuple[int, int, int], ...]

    @property
    def length(self) -> int:
        return sum(bits for _, _, bits in self.entries) // 8

    @property
    def synchronous(self) -> bool:
        return self.trans_type <= MAX_SYNCHRONOUS

    @property
    def comm_index(self) -> int:
        return comm_index_of(self.kind, self.number)


def read_layout(
    od: ObjectDictionary, read: Callable[[int, int], int], kind: str, number: int
) -> PdoLayout | None:
    """The layout of RPDO/TPDO ``number`` from the OD's present values (None if the
    node has no such PDO)."""
    comm = comm_index_of(kind, number)
    if variable(od, comm, 1) is None:
        return None
    mapping = comm + 0x200
    cob = read(comm, 1)
    count = read(mapping, 0) if variable(od, mapping, 0) is not None else 0
    entries = []
    for sub in range(1, count + 1):
        value = read(mapping, sub)
        entries.append((value >> 16, (value >> 8) & 0xFF, value & 0xFF))
    return PdoLayout(
        kind=kind,
        number=number,
        cob_id=cob & 0x7FF,
        valid=not cob & PDO_NOT_VALID,
        trans_type=read(comm, 2),
        inhibit_s=read(comm, 3) * 100e-6 if variable(od, comm, 3) is not None else 0.0,
        event_s=read(comm, 5) * 1e-3 if variable(od, comm, 5) is not None else 0.0,
        entries=tuple(entries),
    )


def check_comm_write(
    od: ObjectDictionary, read: Callable[[int, int], int], index: int, sub: int, value: int
) -> int | None:
    """CiA 301 refusals for a write to a PDO communication parameter (§7.5.2.35/37), with
    CANopenNode's abort codes.

    COB-ID (sub 1): bits 11-29 must be 0 (11-bit identifiers), the identifier may change
    only while the PDO is not valid, and a PDO without mapped objects cannot be made
    valid (0x06090030).  Transmission type (sub 2): 241-253 are reserved or RTR-only,
    which these nodes do not support (0x06090030).
    """
    if sub == 1:
        if value & 0x3FFFF800:
            return ABORT_INVALID_VALUE
        old = read(index, 1)
        valid_now, valid_new = not old & PDO_NOT_VALID, not value & PDO_NOT_VALID
        if valid_now and valid_new and (value & 0x7FF) != (old & 0x7FF):
            return ABORT_INVALID_VALUE
        mapping = index + 0x200
        if valid_new and variable(od, mapping, 0) is not None and read(mapping, 0) == 0:
            return ABORT_INVALID_VALUE
        return None
    if sub == 2 and MAX_SYNCHRONOUS < value < EVENT_MANUFACTURER:
        return ABORT_INVALID_VALUE
    return None


def check_mapping_write(
    od: ObjectDictionary, read: Callable[[int, int], int], index: int, sub: int, value: int
) -> int | None:
    """CiA 301 mapping procedure (§7.5.2.36/38): entries may change only while the PDO
    is not valid and sub-index 0 is 0; sub-index 0 may change only while the PDO is not
    valid, and the entries it enables must be mappable and fit in 64 bits."""
    comm = index - 0x200
    if variable(od, comm, 1) is not None and not read(comm, 1) & PDO_NOT_VALID:
        return ABORT_UNSUPPORTED_ACCESS
    if sub == 0:
        return check_mapping_count(od, read, index, value) or _check_entries(od, read, index, value)
    if read(index, 0) != 0:
        return ABORT_UNSUPPORTED_ACCESS
    return check_mapping_entry(od, value)


def _check_entries(
    od: ObjectDictionary, read: Callable[[int, int], int], index: int, count: int
) -> int | None:
    for sub in range(1, count + 1):
        code = check_mapping_entry(od, read(index, sub))
        if code:
            return code
    return None


class Tpdo:
    """Transmission of one TPDO by its live layout (CiA 301 §7.2.2).

    ``payload()`` returns the PDO's data now.  Synchronous types send at every
    ``trans_type``-th SYNC (type 0: at a SYNC, when the data changed since the last
    frame); event-driven types (254/255) send when the data changes, no sooner than the
    inhibit time after the previous frame (held back, then sent at the first
    ``flush``), and at least every event-timer period.  A PDO that is not valid sends
    nothing.
    """

    def __init__(
        self,
        bus: can.BusABC,
        layout: PdoLayout,
        payload: Callable[[], bytes],
        on_sent: Callable[[PdoLayout], None] | None = None,
    ) -> None:
        self.bus = bus
        self.layout = layout
        self.payload = payload
        self.on_sent = on_sent
        self.sent = 0
        self._sync_count = 0
        self._last: bytes | None = None
        self._last_at = -math.inf
        self._pending = False
        self._msg = can.Message(
            arbitration_id=layout.cob_id, is_extended_id=False, dlc=layout.length, check=False
        )
        # What ``flush`` tests on every call, from the (frozen) layout once.
        self._event_driven = layout.valid and not layout.synchronous
        self._event_s = layout.event_s
        self._event_due_s = layout.event_s - TIME_EPSILON
        self._inhibit_due_s = layout.inhibit_s - TIME_EPSILON

    def restart(self) -> None:
        """Entering OPERATIONAL: the next event sends at once; SYNC counting restarts."""
        self._sync_count = 0
        self._last = None
        self._last_at = -math.inf
        self._pending = False

    def on_sync(self, now: float) -> bool:
        layout = self.layout
        if not layout.valid:
            return False
        tt = layout.trans_type
        if tt == ACYCLIC_SYNCHRONOUS:
            data = self.payload()
            return data != self._last and self._send(data, now)
        if tt <= MAX_SYNCHRONOUS:
            self._sync_count += 1
            if self._sync_count >= tt:
                self._sync_count = 0
                return self._send(self.payload(), now)
            return False
        return self.flush(now)

    def flush(self, now: float, force: bool = False) -> bool:
        """Event-driven types: send if the data changed (or ``force``) and the inhibit
        time allows, or if the event timer expired."""
        if not self._event_driven:
            return False
        data = self.payload()
        if not (force or self._pending or data != self._last) and not (
            self._event_s > 0 and now - self._last_at >= self._event_due_s
        ):
            return False
        if now - self._last_at < self._inhibit_due_s:
            self._pending = True
            return False
        return self._send(data, now)

    def _send(self, data: bytes, now: float) -> bool:
        self._msg.data = data
        self.bus.send(self._msg)
        self.sent += 1
        self._last = data
        self._last_at = now
        self._pending = False
        if self.on_sent is not None:
            self.on_sent(self.layout)
        return True


def entry_slices(layout: PdoLayout) -> tuple[tuple[int, int, int, int], ...]:
    """``(index, sub, start byte, end byte)`` of each byte-aligned mapped object."""
    out = []
    pos = 0
    for index, sub, bits in layout.entries:
        out.append((index, sub, pos, pos + bits // 8))
        pos += bits // 8
    return tuple(out)


def encode_from_od(layout: PdoLayout, get: Callable[[int, int], bytes]) -> bytes:
    """The PDO's data from the objects' present values (``get`` returns each object's
    bytes as the OD stores them; dummy entries are zeros)."""
    parts = []
    for index, sub, bits in layout.entries:
        parts.append(bytes(bits // 8) if index in DUMMY_BITS else bytes(get(index, sub)))
    return b"".join(parts)


def decode_to_od(layout: PdoLayout, data: bytes) -> list[tuple[int, int, bytes]]:
    """``(index, sub, bytes)`` per mapped object of a received PDO (dummies skipped)."""
    return [
        (index, sub, bytes(data[a:b]))
        for index, sub, a, b in entry_slices(layout)
        if index not in DUMMY_BITS
    ]

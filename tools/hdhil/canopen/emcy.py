"""EMCY (CiA 301 §7.2.7): codes, error register, producer with error history, consumer
records.

The frame layout is canopen's ``canopen.emcy.EMCY_STRUCT`` (error code UINT16 LE, error
register, 5 bytes manufacturer-specific data).  The producer keeps the active errors,
0x1001 and the 0x1003 history in the object dictionary; it sends an error once, on its
rising edge, and EMCY 0x0000 when errors clear.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum, IntFlag

import can
from canopen.emcy import EMCY_STRUCT
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord

from hdhil.canopen.od import variable

__all__ = [
    "EMCY_BASE",
    "EMCY_STRUCT",
    "EMCY_TEXT",
    "EmcyCode",
    "EmcyEvent",
    "EmcyProducer",
    "ErrorRegister",
    "decode_emcy",
    "default_error_register",
    "emcy_text",
]

#: EMCY COB-ID base (0x080 + node-ID, object 0x1014; CiA 301 pre-defined connection set).
EMCY_BASE = 0x080


class ErrorRegister(IntFlag):
    """Object 0x1001 error register bits (CiA 301 §7.5.2.2)."""

    GENERIC = 0x01
    CURRENT = 0x02
    VOLTAGE = 0x04
    TEMPERATURE = 0x08
    COMMUNICATION = 0x10
    DEVICE_PROFILE = 0x20
    MANUFACTURER = 0x80


class EmcyCode(IntEnum):
    """Emergency error codes used by the hdhil nodes.

    CiA 301 table "emergency error codes" unless noted; the CiA 402 codes come from
    CiA 402-2 / IEC 61800-7-201 (drive profile error codes).
    """

    #: 0x0000 "error reset or no error": sent when an error goes away.
    NO_ERROR = 0x0000
    #: 0x1000 "generic error".
    GENERIC = 0x1000
    #: 0x2310 "continuous over current" (CiA 402, device output side): amplifier current
    #: limit exceeded for longer than allowed.
    CONTINUOUS_OVER_CURRENT = 0x2310
    #: 0x5000 "device hardware": hardware fault with no more specific code.
    DEVICE_HARDWARE = 0x5000
    #: 0x6100 "internal software": e.g. the torque filter's covariance lost definiteness
    #: or produced a non-finite value.
    INTERNAL_SOFTWARE = 0x6100
    #: 0x6320 "parameter error" (CiA 402): a parameter set the application cannot apply.
    PARAMETER_ERROR = 0x6320
    #: 0x7300 "sensor error" (CiA 402): a sensor reading outside its range, e.g. the
    #: torque bridge ADC at full scale.
    SENSOR = 0x7300
    #: 0x7301 "tacho fault" (CiA 402).
    TACHO_FAULT = 0x7301
    #: 0x7305 "incremental sensor 1 fault" (CiA 402): the encoder.
    INCREMENTAL_SENSOR_1 = 0x7305
    #: 0x8100 "communication - generic".
    COMMUNICATION = 0x8100
    #: 0x8110 "CAN overrun (objects lost)".
    CAN_OVERRUN = 0x8110
    #: 0x8120 "CAN in error passive mode".
    CAN_ERROR_PASSIVE = 0x8120
    #: 0x8130 "life guard error or heartbeat error": a monitored heartbeat timed out.
    HEARTBEAT = 0x8130
    #: 0x8140 "recovered from bus off".
    RECOVERED_FROM_BUS_OFF = 0x8140
    #: 0x8210 "PDO not processed due to length error": a PDO shorter than its mapping.
    PDO_LENGTH = 0x8210
    #: 0x8220 "PDO length exceeded".
    PDO_LENGTH_EXCEEDED = 0x8220
    #: 0x8240 "unexpected SYNC data length": SYNC DLC disagrees with the counter setting.
    SYNC_LENGTH = 0x8240
    #: 0x8250 "RPDO timeout": the cyclic command (or the SYNC that paces it) stopped
    #: arriving; used for "lost SYNC / command PDO late".
    RPDO_TIMEOUT = 0x8250
    #: 0x8311 "excess torque" (CiA 402).
    EXCESS_TORQUE = 0x8311
    #: 0xFF00 "device specific": manufacturer-specific; the 5 manufacturer bytes say more.
    DEVICE_SPECIFIC = 0xFF00


#: Text per EMCY code (CiA 301 / CiA 402 wording).
EMCY_TEXT: dict[int, str] = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2310: "continuous over current",
    0x5000: "device hardware",
    0x6100: "internal software",
    0x6320: "parameter error",
    0x7300: "sensor error",
    0x7301: "tacho fault",
    0x7305: "incremental sensor 1 fault",
    0x8100: "communication - generic",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard error or heartbeat error",
    0x8140: "recovered from bus off",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8240: "unexpected SYNC data length",
    0x8250: "RPDO timeout",
    0x8311: "excess torque",
    0xFF00: "device specific",
}

_EMCY_CLASS_TEXT = (
    (0xF000, 0x2000, "current"),
    (0xF000, 0x3000, "voltage"),
    (0xF000, 0x4000, "temperature"),
    (0xFF00, 0x5000, "device hardware"),
    (0xF000, 0x6000, "device software"),
    (0xF000, 0x7000, "additional modules"),
    (0xF000, 0x8000, "monitoring"),
    (0xFF00, 0x9000, "external error"),
    (0xFF00, 0xF000, "additional functions"),
    (0xFF00, 0xFF00, "device specific"),
)


def emcy_text(code: int) -> str:
    """Meaning of an EMCY code: its own text, else its class (CiA 301 table)."""
    text = EMCY_TEXT.get(code)
    if text is not None:
        return text
    for mask, value, name in _EMCY_CLASS_TEXT:
        if code & mask == value:
            return name
    return "unknown"


def default_error_register(code: int) -> ErrorRegister:
    """Error register bits an EMCY code sets (bit 0 "generic" is added for any error)."""
    group = code & 0xF000
    if group == 0x2000:
        return ErrorRegister.CURRENT
    if group == 0x3000:
        return ErrorRegister.VOLTAGE
    if group == 0x4000:
        return ErrorRegister.TEMPERATURE
    if 0x8100 <= code <= 0x82FF:
        return ErrorRegister.COMMUNICATION
    if group == 0x7000 or 0x8300 <= code <= 0x8FFF:
        return ErrorRegister.DEVICE_PROFILE
    if code & 0xFF00 == 0xFF00:
        return ErrorRegister.MANUFACTURER
    return ErrorRegister.GENERIC


@dataclass(frozen=True)
class EmcyEvent:
    """An EMCY message received from another node."""

    node_id: int
    code: int
    register: int
    data: bytes
    time: float

    @property
    def text(self) -> str:
        return emcy_text(self.code)


def decode_emcy(data: bytes | bytearray) -> tuple[int, int, bytes]:
    """(error code, error register, manufacturer data) of an 8-byte EMCY payload."""
    code, register, payload = EMCY_STRUCT.unpack(bytes(data))
    return code, register, payload


class EmcyProducer:
    """Active errors, error register 0x1001 and history 0x1003 of one node, and its
    EMCY frames (CiA 301 §7.2.7.3.1).

    ``cob_id`` None disables the producer (0x1014 bit 31); ``allowed()`` says whether the
    NMT state lets EMCY out (PRE-OPERATIONAL and OPERATIONAL).  ``sent`` counts the EMCY
    frames that went out (never reset, not even by NMT resets).
    """

    def __init__(
        self,
        bus: can.BusABC,
        od: ObjectDictionary,
        store: dict[int, dict[int, bytes]],
        allowed: Callable[[], bool],
    ) -> None:
        self.bus = bus
        self.od = od
        self.store = store
        self.allowed = allowed
        self.cob_id: int | None = None
        self.sent = 0
        self.active: dict[tuple[int, bytes], int] = {}  # (code, manuf.) -> bits

    @property
    def error_register(self) -> int:
        """Object 0x1001: OR of the active errors' bits, plus bit 0 if any is active."""
        bits = 0
        for value in self.active.values():
            bits |= value  # each entry includes the generic bit
        return bits

    @property
    def active_errors(self) -> tuple[int, ...]:
        """Codes of the errors raised with ``raise_error`` and not yet cleared."""
        return tuple(sorted({code for code, _ in self.active}))

    def error_active(self, code: int) -> bool:
        """True while an error with this code is raised and not cleared (a per-frame check:
        no allocation when none is active)."""
        active = self.active
        return bool(active) and any(c == code for c, _ in active)

    def raise_error(
        self, code: int, register_bits: int | None = None, manufacturer: bytes = b""
    ) -> bool:
        """Signal an error: EMCY frame (CiA 301 §7.2.7.3.1), 0x1001 and 0x1003 updated.

        Layout: canopen's ``EMCY_STRUCT``.  ``register_bits`` defaults to the code's
        class (:func:`default_error_register`).  An error is signalled once, on its rising
        edge: repeating an active (code, manufacturer) returns False without a frame;
        ``clear`` ends it.  True if a frame was sent (not outside PRE-OPERATIONAL and
        OPERATIONAL, not with the producer disabled).
        """
        if not 0x0001 <= code <= 0xFFFF:
            raise ValueError(f"EMCY error code must be 0x0001..0xFFFF, got 0x{code:X}")
        payload = manufacturer_data(manufacturer)
        key = (code, payload)
        if key in self.active:
            return False
        bits = default_error_register(code) if register_bits is None else register_bits
        self.active[key] = (bits | ErrorRegister.GENERIC) & 0xBF  # bit 6 reserved
        self.store_error_register()
        self.push_history(code, payload)
        return self.send(code, payload)

    def clear(self, code: int, manufacturer: bytes | None = None) -> bool:
        """An error went away: EMCY 0x0000 with the remaining error register.

        ``manufacturer`` None clears every instance of ``code``.  True if a frame was sent.
        """
        if manufacturer is None:
            keys = [k for k in self.active if k[0] == code]
        else:
            keys = [(code, manufacturer_data(manufacturer))]
        removed = [k for k in keys if self.active.pop(k, None) is not None]
        if not removed:
            return False
        self.store_error_register()
        return self.send(EmcyCode.NO_ERROR, bytes(5))

    def reset(self) -> bool:
        """Clear every error: EMCY 0x0000 "error reset or no error", 0x1001 = 0."""
        self.active.clear()
        self.store_error_register()
        return self.send(EmcyCode.NO_ERROR, bytes(5))

    def send(self, code: int, payload: bytes) -> bool:
        if self.cob_id is None or not self.allowed():
            return False
        data = EMCY_STRUCT.pack(code, self.error_register, payload)
        self.bus.send(
            can.Message(arbitration_id=self.cob_id, is_extended_id=False, data=data, check=False)
        )
        self.sent += 1
        return True

    def store_error_register(self) -> None:
        if variable(self.od, 0x1001, 0) is not None:
            self.store.setdefault(0x1001, {})[0] = bytes((self.error_register,))

    def history_capacity(self) -> int:
        obj = self.od.get(0x1003)
        if not isinstance(obj, (ODArray, ODRecord)):
            return 0
        return max((s for s in obj.subindices if s > 0), default=0)

    def push_history(self, code: int, payload: bytes) -> None:
        capacity = self.history_capacity()
        if not capacity:
            return
        store = self.store.setdefault(0x1003, {})
        count = store.get(0, b"\x00")[0]
        entry = (code | int.from_bytes(payload[:2], "little") << 16).to_bytes(4, "little")
        for sub in range(min(count + 1, capacity), 1, -1):
            store[sub] = store.get(sub - 1, bytes(4))
        store[1] = entry
        store[0] = bytes((min(count + 1, capacity),))

    @property
    def history(self) -> tuple[int, ...]:
        """0x1003 entries, newest first (error code | manufacturer info << 16)."""
        store = self.store.get(0x1003, {})
        count = store.get(0, b"\x00")[0]
        return tuple(int.from_bytes(store.get(s, bytes(4)), "little") for s in range(1, count + 1))


def manufacturer_data(data: bytes) -> bytes:
    """Manufacturer-specific EMCY bytes, zero-padded to 5."""
    if len(data) > 5:
        raise ValueError(f"EMCY manufacturer data is at most 5 bytes, got {len(data)}")
    return bytes(data).ljust(5, b"\x00")

"""CANopen services (CiA 301) for the hdhil nodes, built on python-canopen's ``LocalNode``.

Everything here is driven explicitly, so lockstep runs stay deterministic: no threads, no
timers, no ``send_periodic``.  Time comes in as ``now`` (seconds: simulated time in
lockstep, ``time.monotonic()`` in real time), received frames come in through
``CanopenServices.handle(msg)`` and frames go out through ``bus.send``.  python-canopen's
``Network`` is used without its ``Notifier``: ``handle`` feeds SDO requests to
``network.notify`` and the ``LocalNode``'s SDO server answers synchronously through
``network.send_message``.

Per node, the application does, once per cycle::

    services.tick(now)                   # heartbeat producer, heartbeat consumer timeouts
    while (msg := bus.recv(0)) is not None:
        if not services.handle(msg):     # NMT, SDO, heartbeat, EMCY: consumed here
            node.on_message(msg)         # SYNC and PDOs: the node's own business

``handle`` costs one dict lookup for frames that are not CANopen service frames.

What python-canopen's ``LocalNode`` already does, and what is added here
--------------------------------------------------------------------------

``LocalNode`` (canopen 2.4) provides the SDO server protocol (expedited and segmented
transfers; block upload falls back to segmented), the OD data store, the access checks
"attempt to read a write-only object" (0x06010001) and "attempt to write a read-only
object" (0x06010002), "object does not exist" (0x06020000), "sub-index does not exist"
(0x06090011, records only), a generic length check for numbers (0x06070010), and
read/write callback hooks.  Its ``NmtSlave`` and ``EmcyProducer`` are thin: NMT reset
leaves the node in INITIALISING without a boot-up message, its heartbeat runs on a
``send_periodic`` thread, and there is no heartbeat consumer or TPDO-on-SYNC (canopen
issues #286, #558).

Added here: the NMT slave state machine with boot-up and resets (CiA 301 §7.3.2), an NMT
master helper, a deterministic heartbeat producer and consumer (§7.2.8.3.2), EMCY producer
with error register and error history and an EMCY consumer (§7.2.7), CiA 301 SDO abort
codes for the length (0x06070012/13), the value range from the EDS (LowLimit/HighLimit ->
0x06090031/32, NaN -> 0x06090030, including REAL32/REAL64 limits, which canopen's EDS
reader drops), sub-indices of arrays that are not defined (0x06090011; canopen invents
them), PDO mapping checks (0x06040041/42/43), object-specific checks of the communication
profile, and per-object validators and change callbacks for the application.  A parameter
is never changed by an aborted write.  The SYNC producer (counter per 0x1019) and a SYNC
consumer monitor live here too.  canopen's threaded heartbeat (``NmtSlave.on_write`` for
0x1017) and its NMT command handler are detached from the ``LocalNode``.

Object dictionary entries the services use
------------------------------------------

Missing optional objects switch the feature to its constructor argument or off.

====== === ========== ====== ================================ =========================
index  sub type       access default                          used by
====== === ========== ====== ================================ =========================
0x1001 0   UNSIGNED8  ro     0                                EMCY producer (error reg.)
0x1003 0   UNSIGNED8  rw     0 (write 0 = clear; else abort)  EMCY error history
0x1003 1-8 UNSIGNED32 ro     0 (code | manuf. info << 16)     (ARRAY, newest at sub 1)
0x1005 0   UNSIGNED32 rw     0x40000080 producer / 0x80 cons. SYNC COB-ID (bit 30 = gen.)
0x1006 0   UNSIGNED32 rw     1000 (us)                        SYNC period (0x1019 gate)
0x1014 0   UNSIGNED32 rw     $NODEID+0x80 (bit 31 = invalid)  EMCY COB-ID (optional)
0x1016 0   UNSIGNED8  const  n entries                        heartbeat consumer (ARRAY)
0x1016 1-n UNSIGNED32 rw     node << 16 | time_ms, 0 = unused controller 0x00020000|250,
                                                              drive 0x00010000|250
0x1017 0   UNSIGNED16 rw     100 (ms, 0 = off)                heartbeat producer
0x1019 0   UNSIGNED8  rw     240 (0 or 2..240; Low 0 High 240) SYNC producer counter
0x1029 0   UNSIGNED8  const  1                                error behaviour (optional)
0x1029 1   UNSIGNED8  rw     1 (0 pre-op, 1 no change, 2 stop) reaction to heartbeat loss
====== === ========== ====== ================================ =========================

CiA 402 objects of the drive (``hdhil.canopen.cia402``): 0x603F error code UNSIGNED16 ro 0;
0x6040 controlword UNSIGNED16 rww 0 (PDO); 0x6041 statusword UNSIGNED16 ro 0 (PDO); 0x605A
quick stop option code INTEGER16 rw 2 (Low 0 High 8); 0x605E fault reaction option code
INTEGER16 rw 0; 0x6060 modes of operation INTEGER8 rw 10 (validator: 0 or 10); 0x6061
modes of operation display INTEGER8 ro 10; 0x6502 supported drive modes UNSIGNED32 ro
0x00000200.  Application parameters that SDO may change (e.g. the firmware's filter Q and
R as REAL32 with LowLimit/HighLimit) get a validator and an ``on_write`` callback.

EMCY codes (CiA 301 table "emergency error codes"; 0x2310, 0x73xx, 0x8311 from CiA 402-2 /
IEC 61800-7-201): see :class:`EmcyCode`.
"""

from __future__ import annotations

import configparser
import math
import re
import struct
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag
from pathlib import Path
from typing import Any, Literal

import can
import canopen
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable
from canopen.objectdictionary import datatypes as dt
from canopen.sdo import SdoAbortedError, SdoCommunicationError

# ---------------------------------------------------------------------------- constants

NMT_COB_ID = 0x000
SYNC_COB_ID = 0x080
EMCY_BASE = 0x080
SDO_TX_BASE = 0x580  # server -> client
SDO_RX_BASE = 0x600  # client -> server
HEARTBEAT_BASE = 0x700

#: Time tolerance for due/deadline comparisons, so float rounding of the caller's clock
#: never moves a heartbeat or a timeout by a whole tick.
TIME_EPSILON = 1e-9


class NmtState(IntEnum):
    """NMT states as the heartbeat byte codes them (CiA 301 §7.2.8.3.2.1)."""

    INITIALISING = 0x00  # only ever seen as the boot-up message
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


class NmtCommand(IntEnum):
    """NMT node control command specifiers (CiA 301 §7.2.8.3.1)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


# The NMT states the per-frame checks test for, as module globals: an attribute of an Enum
# class (``NmtState.OPERATIONAL``) is looked up through ``EnumType.__getattr__``'s slow
# path in Python 3.11, several times slower than a global.
_OPERATIONAL = NmtState.OPERATIONAL
_PRE_OPERATIONAL = NmtState.PRE_OPERATIONAL


ResetKind = Literal["node", "communication"]


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


#: SDO abort codes and their CiA 301 text (§7.2.4.3.17, table "SDO abort codes").
ABORT_TEXT: dict[int, str] = {
    0x05030000: "toggle bit not alternated",
    0x05040000: "SDO protocol timed out",
    0x05040001: "client/server command specifier not valid or unknown",
    0x05040002: "invalid block size",
    0x05040003: "invalid sequence number",
    0x05040004: "CRC error",
    0x05040005: "out of memory",
    0x06010000: "unsupported access to an object",
    0x06010001: "attempt to read a write only object",
    0x06010002: "attempt to write a read only object",
    0x06020000: "object does not exist in the object dictionary",
    0x06040041: "object cannot be mapped to the PDO",
    0x06040042: "the number and length of the objects to be mapped would exceed PDO length",
    0x06040043: "general parameter incompatibility reason",
    0x06040047: "general internal incompatibility in the device",
    0x06060000: "access failed due to a hardware error",
    0x06070010: "data type does not match, length of service parameter does not match",
    0x06070012: "data type does not match, length of service parameter too high",
    0x06070013: "data type does not match, length of service parameter too low",
    0x06090011: "sub-index does not exist",
    0x06090030: "invalid value for parameter (download only)",
    0x06090031: "value of parameter written too high (download only)",
    0x06090032: "value of parameter written too low (download only)",
    0x06090036: "maximum value is less than minimum value",
    0x060A0023: "resource not available: SDO connection",
    0x08000000: "general error",
    0x08000020: "data cannot be transferred or stored to the application",
    0x08000021: (
        "data cannot be transferred or stored to the application because of local control"
    ),
    0x08000022: (
        "data cannot be transferred or stored to the application because of the present "
        "device state"
    ),
    0x08000023: "object dictionary dynamic generation fails or no object dictionary is present",
    0x08000024: "no data available",
}

# Named abort codes used in this module.
ABORT_TIMEOUT = 0x05040000
ABORT_UNKNOWN_COMMAND = 0x05040001
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_INCOMPATIBLE = 0x06040043
ABORT_NO_OBJECT = 0x06020000
ABORT_LENGTH = 0x06070010
ABORT_LENGTH_HIGH = 0x06070012
ABORT_LENGTH_LOW = 0x06070013
ABORT_NO_SUBINDEX = 0x06090011
ABORT_INVALID_VALUE = 0x06090030
ABORT_VALUE_HIGH = 0x06090031
ABORT_VALUE_LOW = 0x06090032
ABORT_DEVICE_STATE = 0x08000022


def abort_text(code: int) -> str:
    """CiA 301 text of an SDO abort code."""
    return ABORT_TEXT.get(code, "unknown abort code")


class BootTimeoutError(RuntimeError):
    """Expected nodes sent no boot-up message in time (NMT master)."""

    def __init__(self, node_ids: tuple[int, ...], waited_s: float) -> None:
        self.node_ids = node_ids
        names = ", ".join(
            f"node {n} (COB-ID 0x{HEARTBEAT_BASE + n:03X}, data 00)" for n in node_ids
        )
        super().__init__(
            f"no boot-up message from {names} within {waited_s:.3f} s: check that the node "
            "is powered, on the same bus at the same bit rate, and uses that node-ID"
        )


# --------------------------------------------------------------------- data records


@dataclass
class MonitoredNode:
    """Heartbeat consumer state for one monitored node (an entry of 0x1016)."""

    node_id: int
    timeout_s: float
    #: "waiting" until the first heartbeat (CiA 301: monitoring starts there), "active"
    #: while heartbeats arrive in time, "lost" after a timeout until the next heartbeat.
    status: Literal["waiting", "active", "lost"] = "waiting"
    last_heartbeat: float | None = None
    nmt_state: int | None = None
    deadline: float = math.inf
    losses: int = 0
    #: Time the latest loss was detected (the ``now`` of that ``tick``).
    lost_at: float | None = None
    resumed_at: float | None = None


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


@dataclass
class ServiceCounters:
    """What the services did (never reset, not even by NMT resets)."""

    nmt_commands: int = 0
    sdo_requests: int = 0
    heartbeats_sent: int = 0
    heartbeats_received: int = 0
    emcy_sent: int = 0
    emcy_received: int = 0
    #: Frames of the right COB-ID but wrong length (NMT 2, SDO 8, heartbeat 1, EMCY 8).
    malformed_frames: int = 0
    #: SDO/EMCY frames ignored because of this node's NMT state (INITIALISING, STOPPED).
    ignored_in_state: int = 0
    #: SDO segments outside a transfer, answered with abort 0x05040001.
    sdo_protocol_errors: int = 0


Validator = Callable[[Any], "int | None"]
WriteCallback = Callable[[Any], None]


# ------------------------------------------------------------------- OD loading


_SECTION = re.compile(r"^([0-9A-Fa-f]{4})(?:sub([0-9A-Fa-f]+))?$")


def load_od(source: str | Path | ObjectDictionary, node_id: int) -> ObjectDictionary:
    """Import an EDS/DCF (or pass an ``ObjectDictionary`` through).

    canopen's EDS reader parses LowLimit/HighLimit as integers only and silently drops
    them for REAL32/REAL64 objects; they are read again here so range checks cover them.
    """
    if isinstance(source, ObjectDictionary):
        return source
    od = canopen.import_od(str(source), node_id)
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",), strict=False)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read(str(source), encoding="utf-8")
    for section in parser.sections():
        match = _SECTION.match(section)
        if not match:
            continue
        index = int(match.group(1), 16)
        sub = int(match.group(2), 16) if match.group(2) else 0
        var = _variable(od, index, sub)
        if var is None or var.data_type not in dt.FLOAT_TYPES:
            continue
        for option, attr in (("LowLimit", "min"), ("HighLimit", "max")):
            if parser.has_option(section, option):
                setattr(var, attr, float(parser.get(section, option)))
    return od


def _variable(od: ObjectDictionary, index: int, sub: int) -> ODVariable | None:
    """The variable at index:sub, or None (array sub-indices must be defined)."""
    obj = od.get(index)
    if obj is None:
        return None
    if isinstance(obj, ODVariable):
        return obj if sub == 0 else None
    return obj.subindices.get(sub)


def _is_mapping_index(index: int) -> bool:
    return 0x1600 <= index <= 0x17FF or 0x1A00 <= index <= 0x1BFF


#: Bit size of the dummy-mapping data types 0x0001..0x0007 (CiA 301 §7.4.7.1).
_DUMMY_BITS = {0x1: 1, 0x2: 8, 0x3: 16, 0x4: 32, 0x5: 8, 0x6: 16, 0x7: 32}


class _ServiceNode(canopen.LocalNode):
    """``LocalNode`` with CiA 301 aborts and post-store callbacks; no threaded heartbeat."""

    def __init__(self, node_id: int, od: ObjectDictionary, specific_length_codes: bool) -> None:
        super().__init__(node_id, od)
        # canopen's NmtSlave starts a send_periodic thread on writes of 0x1017 and on its own
        # boot; CanopenServices produces the heartbeat deterministically instead.
        self._write_callbacks.remove(self.nmt.on_write)
        self.specific_length_codes = specific_length_codes
        #: Called after a write was stored: ``after_write(index, sub, var, data)``.
        self.after_write: Callable[[int, int, ODVariable, bytes], None] | None = None

    def associate_network(self, network: canopen.Network) -> None:
        super().associate_network(network)
        network.unsubscribe(NMT_COB_ID, self.nmt.on_command)  # NMT is CanopenServices' job

    def remove_network(self) -> None:
        if self.has_network():
            self.network.subscribe(NMT_COB_ID, self.nmt.on_command)
        super().remove_network()

    def _find_object(self, index: int, subindex: int) -> ODVariable:
        obj = super()._find_object(index, subindex)
        parent = obj.parent
        # ODArray invents members for any sub-index 1..255; only defined ones exist.
        if isinstance(parent, ODArray) and subindex not in parent.subindices:
            raise SdoAbortedError(ABORT_NO_SUBINDEX)
        return obj

    def set_data(
        self, index: int, subindex: int, data: bytes, check_writable: bool = False
    ) -> None:
        obj = self._find_object(index, subindex)
        if check_writable and not obj.writable:
            raise SdoAbortedError(0x06010002)
        if obj.fixed_size:
            size = len(obj) // 8
            if len(data) != size:
                if not self.specific_length_codes:
                    raise SdoAbortedError(ABORT_LENGTH)
                raise SdoAbortedError(ABORT_LENGTH_HIGH if len(data) > size else ABORT_LENGTH_LOW)
        store = self.data_store.get(index)
        old = None if store is None else store.get(subindex)
        super().set_data(index, subindex, data, check_writable)  # validators, then store
        if self.after_write is None:
            return
        try:
            self.after_write(index, subindex, obj, bytes(data))
        except BaseException:
            if old is None:
                self.data_store[index].pop(subindex, None)
            else:
                self.data_store[index][subindex] = old
            raise


# ----------------------------------------------------------------------- services


class CanopenServices:
    """NMT slave/master, heartbeat, EMCY, checked SDO server of one node (CiA 301).

    ``od`` is an EDS/DCF path or an ``ObjectDictionary``.  ``heartbeat_producer_ms`` and
    ``heartbeat_consumers`` ({node_id: timeout_ms}) are power-on values: written to 0x1017
    / 0x1016 when the OD has them (and again after every NMT reset), kept internally when
    it does not.  ``length_aborts="generic"`` answers every length mismatch with
    0x06070010 instead of 0x06070012/0x06070013.  With ``emcy_on_heartbeat_loss`` a lost
    heartbeat raises EMCY 0x8130 (manufacturer byte 0 = the lost node-ID) and its return
    clears it.

    NMT states gate the services (CiA 301 §7.3.2.2, table "NMT states and communication
    objects"): INITIALISING (before ``boot``) - nothing; PRE-OPERATIONAL - SDO, SYNC,
    EMCY, heartbeat, NMT, no PDOs; OPERATIONAL - all; STOPPED - only NMT and heartbeat.
    This class drops SDO requests and does not send EMCY outside PRE-OPERATIONAL and
    OPERATIONAL; the node itself must stop its PDOs (``pdo_allowed``) and SYNC production
    (``sync_allowed``) when this says so.
    """

    def __init__(
        self,
        bus: can.BusABC,
        node_id: int,
        od: str | Path | ObjectDictionary,
        *,
        heartbeat_producer_ms: int | None = None,
        heartbeat_consumers: Mapping[int, int] | None = None,
        length_aborts: Literal["specific", "generic"] = "specific",
        emcy_on_heartbeat_loss: bool = True,
        emcy_log_size: int = 64,
    ) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"CANopen node-ID must be 1..127, got {node_id}")
        if length_aborts not in ("specific", "generic"):
            raise ValueError(
                f"length_aborts must be 'specific' or 'generic', got {length_aborts!r}"
            )
        self.bus = bus
        self.node_id = node_id
        self.od = load_od(od, node_id)
        self.node = _ServiceNode(node_id, self.od, length_aborts == "specific")
        self.network = canopen.Network(bus)  # no Notifier: frames come in through handle()
        self.network.add_node(self.node)
        self.node.add_write_callback(self._validate_write)
        self.node.after_write = self._after_write
        self.emcy_on_heartbeat_loss = emcy_on_heartbeat_loss

        self.state = NmtState.INITIALISING
        #: The latest ``now`` given to ``boot``/``tick``; frames handled without an explicit
        #: ``now`` are timed with it.
        self.now = 0.0
        self.counters = ServiceCounters()
        self.emcy_log: deque[EmcyEvent] = deque(maxlen=emcy_log_size)
        self.remote_states: dict[int, NmtState | int] = {}
        self.boot_times: dict[int, float] = {}
        self.monitored: dict[int, MonitoredNode] = {}
        self.sync_producer: SyncProducer | None = None

        self._state_callbacks: list[Callable[[NmtState, NmtState], None]] = []
        self._reset_callbacks: list[Callable[[ResetKind], None]] = []
        self._lost_callbacks: list[Callable[[int], None]] = []
        self._resumed_callbacks: list[Callable[[int], None]] = []
        self._boot_callbacks: list[Callable[[int], None]] = []
        self._emcy_callbacks: list[Callable[[int, int, int, bytes], None]] = []
        self._validators: dict[tuple[int, int], list[Validator]] = {}
        self._write_callbacks: dict[tuple[int, int], list[WriteCallback]] = {}

        self._boot_deadlines: dict[int, tuple[float, float]] = {}  # node -> (deadline, wait)
        self._sdo_downloading = False
        self._active_errors: dict[tuple[int, bytes], int] = {}  # (code, manuf.) -> bits
        self._hb_period_s = 0.0
        self._hb_origin = 0.0
        self._hb_count = 0
        self._hb_next = math.inf
        self._hb_fallback_ms = 0
        self._consumer_fallback: dict[int, int] = {}
        self._emcy_cob_id: int | None = EMCY_BASE + node_id
        self._error_behaviour: int | None = None
        self._heartbeat_msg = can.Message(
            arbitration_id=HEARTBEAT_BASE + node_id,
            is_extended_id=False,
            data=bytes(1),
            check=False,
        )
        self._power_on: dict[tuple[int, int], bytes] = {}
        self._set_power_on_values(heartbeat_producer_ms, heartbeat_consumers)
        self._apply_power_on_values()
        self._load_comm_config()
        self._dispatch = self._build_dispatch()

    # ------------------------------------------------------------ registration

    def on_state_change(
        self, callback: Callable[[NmtState, NmtState], None]
    ) -> Callable[[NmtState, NmtState], None]:
        """``callback(old, new)`` after every NMT state change of this node."""
        self._state_callbacks.append(callback)
        return callback

    def on_reset(self, callback: Callable[[ResetKind], None]) -> Callable[[ResetKind], None]:
        """``callback("node" | "communication")`` during an NMT reset, after the OD areas
        were restored and before the boot-up message: re-initialise the application."""
        self._reset_callbacks.append(callback)
        return callback

    def on_heartbeat_lost(self, callback: Callable[[int], None]) -> Callable[[int], None]:
        """``callback(node_id)`` once when a monitored node's heartbeat times out."""
        self._lost_callbacks.append(callback)
        return callback

    def on_heartbeat_resumed(self, callback: Callable[[int], None]) -> Callable[[int], None]:
        """``callback(node_id)`` when a lost node's heartbeat comes back."""
        self._resumed_callbacks.append(callback)
        return callback

    def on_boot(self, callback: Callable[[int], None]) -> Callable[[int], None]:
        """``callback(node_id)`` on every boot-up message from another node."""
        self._boot_callbacks.append(callback)
        return callback

    def on_emcy(
        self, callback: Callable[[int, int, int, bytes], None]
    ) -> Callable[[int, int, int, bytes], None]:
        """``callback(node_id, code, register, manufacturer_data)`` for others' EMCY."""
        self._emcy_callbacks.append(callback)
        return callback

    def add_validator(self, index: int, subindex: int, validator: Validator) -> Validator:
        """``validator(value) -> abort code | None`` before a write of index:sub is stored.

        Runs after the type, access and range checks, for SDO and local writes alike.
        Returning an abort code (e.g. 0x06090030, 0x08000022) refuses the write and leaves
        the parameter unchanged; raising ``SdoAbortedError`` does the same.
        """
        self._require_variable(index, subindex)
        self._validators.setdefault((index, subindex), []).append(validator)
        return validator

    def on_write(self, index: int, subindex: int, callback: WriteCallback) -> WriteCallback:
        """``callback(value)`` after a write of index:sub was accepted and stored.

        Use it to apply a new parameter (the firmware's filter Q, an emulator knob).  If
        it raises, the old value is restored and an SDO write answers with an abort
        (``SdoAbortedError``'s code, or 0x08000000 for other exceptions); prefer refusing
        in a validator.
        """
        self._require_variable(index, subindex)
        self._write_callbacks.setdefault((index, subindex), []).append(callback)
        return callback

    # ------------------------------------------------------------ frames and time

    def handle(self, msg: can.Message, now: float | None = None) -> bool:
        """Feed a received frame; True if it was a CANopen service frame consumed here.

        Consumed: NMT (0x000), SDO requests to this node (0x600+id), heartbeats and
        boot-ups of other nodes (0x701-0x77F), EMCY of other nodes (0x081-0x0FF).  SYNC
        (0x080), PDOs and anything else return False at the cost of one dict lookup.
        """
        handler = self._dispatch.get(msg.arbitration_id)
        if handler is None or msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return False
        handler(msg, self.now if now is None else now)
        return True

    def boot(self, now: float) -> None:
        """Power-on: INITIALISING -> boot-up message -> PRE-OPERATIONAL (CiA 301 §7.3.2.2)."""
        if self.state is not NmtState.INITIALISING:
            raise RuntimeError(
                f"node {self.node_id} already booted (state {self.state.name}); "
                "use an NMT reset to boot again"
            )
        self.now = now
        self._boot_up(now)

    def tick(self, now: float) -> None:
        """Advance time: send a heartbeat when due, detect heartbeat timeouts."""
        self.now = now
        if now + TIME_EPSILON >= self._hb_next:
            self._send_heartbeat(now)
        for m in self.monitored.values():
            if m.status == "active" and now > m.deadline + TIME_EPSILON:
                self._heartbeat_lost(m, now)

    # --------------------------------------------------------------- NMT slave

    @property
    def pdo_allowed(self) -> bool:
        """PDOs may be sent and received only in OPERATIONAL."""
        return self.state is _OPERATIONAL

    @property
    def sdo_allowed(self) -> bool:
        state = self.state
        return state is _OPERATIONAL or state is _PRE_OPERATIONAL

    #: SYNC and EMCY follow the same rule as SDO (PRE-OPERATIONAL and OPERATIONAL).
    sync_allowed = sdo_allowed
    emcy_allowed = sdo_allowed

    def enter_state(self, state: NmtState) -> None:
        """Local state change by the application (e.g. the NMT master starting itself,
        or a node leaving OPERATIONAL on an error).  Not for INITIALISING: use a reset."""
        if state is NmtState.INITIALISING:
            raise ValueError("INITIALISING is entered through an NMT reset, not enter_state")
        if self.state is NmtState.INITIALISING:
            raise RuntimeError(f"node {self.node_id} has not booted yet")
        self._set_state(state)

    def reset(self, kind: ResetKind, now: float | None = None) -> None:
        """Local NMT reset ("node" or "communication"), as if commanded by the master."""
        self._reset(kind, self.now if now is None else now)

    def _on_nmt(self, msg: can.Message, now: float) -> None:
        data = msg.data
        if len(data) != 2:
            self.counters.malformed_frames += 1
            return
        cs, target = data[0], data[1]
        if target not in (0, self.node_id) or self.state is NmtState.INITIALISING:
            return
        self.counters.nmt_commands += 1
        if cs == NmtCommand.START:
            self._set_state(NmtState.OPERATIONAL)
        elif cs == NmtCommand.STOP:
            self._set_state(NmtState.STOPPED)
        elif cs == NmtCommand.ENTER_PRE_OPERATIONAL:
            self._set_state(NmtState.PRE_OPERATIONAL)
        elif cs == NmtCommand.RESET_NODE:
            self._reset("node", now)
        elif cs == NmtCommand.RESET_COMMUNICATION:
            self._reset("communication", now)

    def _set_state(self, new: NmtState) -> None:
        old = self.state
        if new == old:
            return
        self.state = new
        if old is NmtState.STOPPED and self.sync_producer is not None:
            self.sync_producer.reset()  # CiA 301: counter restarts when leaving STOPPED
        for callback in self._state_callbacks:
            callback(old, new)

    def _reset(self, kind: ResetKind, now: float) -> None:
        self._set_state(NmtState.INITIALISING)
        low, high = (0x1000, 0x9FFF) if kind == "node" else (0x1000, 0x1FFF)
        keep = () if kind == "node" else (0x1001, 0x1003)  # errors survive a comm reset
        store = self.node.data_store
        for index in [i for i in store if low <= i <= high and i not in keep]:
            del store[index]
        if kind == "node":
            self._active_errors.clear()
        self._apply_power_on_values(low, high)
        self._load_comm_config()
        self._store_error_register()
        for callback in self._reset_callbacks:
            callback(kind)
        self._boot_up(now)

    def _boot_up(self, now: float) -> None:
        self.bus.send(
            can.Message(
                arbitration_id=HEARTBEAT_BASE + self.node_id,
                is_extended_id=False,
                data=b"\x00",
                check=False,
            )
        )
        self._start_heartbeat(now)
        if self.sync_producer is not None:
            self.sync_producer.reset()
        self._set_state(NmtState.PRE_OPERATIONAL)

    # -------------------------------------------------------------- NMT master

    def nmt_command(self, cs: int, node_id: int = 0) -> None:
        """Send an NMT node-control command (node_id 0 = all nodes).

        The master's own state is not changed by its broadcast; use ``enter_state``.
        A reset command forgets earlier boot-ups of the addressed nodes, so
        ``boot_seen`` waits for the new one.
        """
        cs = NmtCommand(cs)
        if not 0 <= node_id <= 127:
            raise ValueError(f"NMT node-ID must be 0..127, got {node_id}")
        self.bus.send(
            can.Message(
                arbitration_id=NMT_COB_ID,
                is_extended_id=False,
                data=bytes((cs, node_id)),
                check=False,
            )
        )
        if cs in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            if node_id == 0:
                self.boot_times.clear()
            else:
                self.boot_times.pop(node_id, None)

    def expect_boot(self, node_id: int, now: float, timeout_s: float) -> None:
        """Start waiting (without blocking) for ``node_id``'s boot-up until now + timeout."""
        self._boot_deadlines[node_id] = (now + timeout_s, timeout_s)

    def boot_seen(self, node_id: int) -> bool:
        """True once a boot-up message from ``node_id`` has been received."""
        return node_id in self.boot_times

    def boot_timed_out(self, now: float) -> tuple[int, ...]:
        """Expected nodes whose boot-up deadline has passed without a boot-up."""
        return tuple(
            n
            for n, (deadline, _) in sorted(self._boot_deadlines.items())
            if n not in self.boot_times and now > deadline + TIME_EPSILON
        )

    def check_boot(self, now: float) -> bool:
        """True when every expected node has booted; raises ``BootTimeoutError`` past a
        deadline; False while still waiting."""
        late = self.boot_timed_out(now)
        if late:
            raise BootTimeoutError(late, max(self._boot_deadlines[n][1] for n in late))
        return all(n in self.boot_times for n in self._boot_deadlines)

    def remote_state(self, node_id: int) -> NmtState | int | None:
        """Last NMT state another node reported by heartbeat (PRE-OPERATIONAL after boot-up)."""
        return self.remote_states.get(node_id)

    # --------------------------------------------------------------- heartbeat

    @property
    def heartbeat_period_s(self) -> float:
        return self._hb_period_s

    def _start_heartbeat(self, now: float) -> None:
        # The boot-up message (or a new 0x1017 value) starts the schedule: heartbeats at
        # origin + k * period, k = 1, 2, ...
        self._hb_origin = now
        self._hb_count = 0
        self._hb_next = now + self._hb_period_s if self._hb_period_s > 0 else math.inf

    def _send_heartbeat(self, now: float) -> None:
        self._heartbeat_msg.data = bytes((self.state,))
        self.bus.send(self._heartbeat_msg)
        self.counters.heartbeats_sent += 1
        period, origin = self._hb_period_s, self._hb_origin
        # Slots on the fixed grid origin + k * period; a late tick sends one heartbeat
        # and skips the slots it missed instead of bursting.
        k = max(self._hb_count + 1, math.floor((now - origin) / period))
        while origin + (k + 1) * period <= now + TIME_EPSILON:
            k += 1
        self._hb_count = k
        self._hb_next = origin + (k + 1) * period

    def _on_heartbeat(self, msg: can.Message, now: float) -> None:
        if len(msg.data) != 1:
            self.counters.malformed_frames += 1
            return
        node_id = msg.arbitration_id - HEARTBEAT_BASE
        state = msg.data[0] & 0x7F  # bit 7 is the node-guarding toggle bit
        self.counters.heartbeats_received += 1
        monitor = self.monitored.get(node_id)
        if state == NmtState.INITIALISING:
            # Boot-up: the node restarted.  Monitoring (re)starts at its next heartbeat.
            self.boot_times[node_id] = now
            self.remote_states[node_id] = NmtState.PRE_OPERATIONAL
            if monitor is not None and monitor.status == "active":
                monitor.status = "waiting"
                monitor.deadline = math.inf
            for callback in self._boot_callbacks:
                callback(node_id)
            return
        try:
            self.remote_states[node_id] = NmtState(state)
        except ValueError:
            self.remote_states[node_id] = state
        if monitor is None or self.state is NmtState.INITIALISING:
            return
        monitor.last_heartbeat = now
        monitor.nmt_state = state
        monitor.deadline = now + monitor.timeout_s
        if monitor.status == "lost":
            monitor.status = "active"
            monitor.resumed_at = now
            if self.emcy_on_heartbeat_loss:
                self.emcy_clear(EmcyCode.HEARTBEAT, bytes((node_id,)))
            for callback in self._resumed_callbacks:
                callback(node_id)
        else:
            monitor.status = "active"

    def _heartbeat_lost(self, monitor: MonitoredNode, now: float) -> None:
        monitor.status = "lost"
        monitor.losses += 1
        monitor.lost_at = now
        monitor.deadline = math.inf
        if self.emcy_on_heartbeat_loss:
            self.emcy(EmcyCode.HEARTBEAT, manufacturer=bytes((monitor.node_id,)))
        # 0x1029 sub 1 "communication error" behaviour (CiA 301 §7.5.2.32).
        if self._error_behaviour == 0 and self.state is NmtState.OPERATIONAL:
            self._set_state(NmtState.PRE_OPERATIONAL)
        elif self._error_behaviour == 2 and self.state is not NmtState.INITIALISING:
            self._set_state(NmtState.STOPPED)
        for callback in self._lost_callbacks:
            callback(monitor.node_id)

    def _configure_consumers(self, entries: Mapping[int, int]) -> None:
        """Set the monitored nodes from {node_id: timeout_ms}; unchanged entries keep state."""
        wanted = {n: ms for n, ms in entries.items() if n and ms}
        for node_id in list(self.monitored):
            if node_id not in wanted or self.monitored[node_id].timeout_s != wanted[node_id] / 1e3:
                del self.monitored[node_id]
        for node_id, ms in wanted.items():
            if node_id not in self.monitored:
                self.monitored[node_id] = MonitoredNode(node_id, ms / 1e3)

    # -------------------------------------------------------------------- EMCY

    @property
    def error_register(self) -> int:
        """Object 0x1001: OR of the active errors' bits, plus bit 0 if any is active."""
        bits = 0
        for value in self._active_errors.values():
            bits |= value  # each entry includes the generic bit
        return bits

    @property
    def active_errors(self) -> tuple[int, ...]:
        """Codes of the errors raised with ``emcy`` and not yet cleared."""
        return tuple(sorted({code for code, _ in self._active_errors}))

    def error_active(self, code: int) -> bool:
        """True while an error with this code is raised and not cleared (a per-frame check:
        no allocation when none is active)."""
        return bool(self._active_errors) and any(c == code for c, _ in self._active_errors)

    def emcy(self, code: int, register_bits: int | None = None, manufacturer: bytes = b"") -> bool:
        """Signal an error: EMCY frame (CiA 301 §7.2.7.3.1), 0x1001 and 0x1003 updated.

        Layout: error code UINT16 LE, error register (0x1001 after the update), 5 bytes
        manufacturer-specific data (zero-padded).  ``register_bits`` defaults to the
        code's class (:func:`default_error_register`).  An error is signalled once, on
        its rising edge: repeating an active (code, manufacturer) returns False without
        a frame; ``emcy_clear`` ends it.  True if a frame was sent (not in STOPPED).
        """
        if not 0x0001 <= code <= 0xFFFF:
            raise ValueError(f"EMCY error code must be 0x0001..0xFFFF, got 0x{code:X}")
        payload = self._manufacturer(manufacturer)
        key = (code, payload)
        if key in self._active_errors:
            return False
        bits = default_error_register(code) if register_bits is None else register_bits
        self._active_errors[key] = (bits | ErrorRegister.GENERIC) & 0xBF  # bit 6 reserved
        self._store_error_register()
        self._push_history(code, payload)
        return self._send_emcy(code, payload)

    def emcy_clear(self, code: int, manufacturer: bytes | None = None) -> bool:
        """An error went away: EMCY 0x0000 with the remaining error register.

        ``manufacturer`` None clears every instance of ``code``.  True if a frame was sent.
        """
        if manufacturer is None:
            keys = [k for k in self._active_errors if k[0] == code]
        else:
            keys = [(code, self._manufacturer(manufacturer))]
        removed = [k for k in keys if self._active_errors.pop(k, None) is not None]
        if not removed:
            return False
        self._store_error_register()
        return self._send_emcy(EmcyCode.NO_ERROR, bytes(5))

    def emcy_reset(self) -> bool:
        """Clear every error: EMCY 0x0000 "error reset or no error", 0x1001 = 0."""
        self._active_errors.clear()
        self._store_error_register()
        return self._send_emcy(EmcyCode.NO_ERROR, bytes(5))

    @staticmethod
    def _manufacturer(data: bytes) -> bytes:
        if len(data) > 5:
            raise ValueError(f"EMCY manufacturer data is at most 5 bytes, got {len(data)}")
        return bytes(data).ljust(5, b"\x00")

    def _send_emcy(self, code: int, payload: bytes) -> bool:
        if self._emcy_cob_id is None or not self.emcy_allowed:
            return False
        data = struct.pack("<HB5s", code, self.error_register, payload)
        self.bus.send(
            can.Message(
                arbitration_id=self._emcy_cob_id, is_extended_id=False, data=data, check=False
            )
        )
        self.counters.emcy_sent += 1
        return True

    def _store_error_register(self) -> None:
        if _variable(self.od, 0x1001, 0) is not None:
            self.node.data_store.setdefault(0x1001, {})[0] = bytes((self.error_register,))

    def _history_capacity(self) -> int:
        obj = self.od.get(0x1003)
        if not isinstance(obj, (ODArray, ODRecord)):
            return 0
        return max((s for s in obj.subindices if s > 0), default=0)

    def _push_history(self, code: int, payload: bytes) -> None:
        capacity = self._history_capacity()
        if not capacity:
            return
        store = self.node.data_store.setdefault(0x1003, {})
        count = store.get(0, b"\x00")[0]
        entry = struct.pack("<HH", code, int.from_bytes(payload[:2], "little"))
        for sub in range(min(count + 1, capacity), 1, -1):
            store[sub] = store.get(sub - 1, bytes(4))
        store[1] = entry
        store[0] = bytes((min(count + 1, capacity),))

    @property
    def error_history(self) -> tuple[int, ...]:
        """0x1003 entries, newest first (error code | manufacturer info << 16)."""
        store = self.node.data_store.get(0x1003, {})
        count = store.get(0, b"\x00")[0]
        return tuple(struct.unpack("<I", store.get(s, bytes(4)))[0] for s in range(1, count + 1))

    def _on_emcy(self, msg: can.Message, now: float) -> None:
        if self.state in (NmtState.INITIALISING, NmtState.STOPPED):
            self.counters.ignored_in_state += 1
            return
        if len(msg.data) != 8:
            self.counters.malformed_frames += 1
            return
        code, register, payload = struct.unpack("<HB5s", bytes(msg.data))
        node_id = msg.arbitration_id - EMCY_BASE
        self.counters.emcy_received += 1
        self.emcy_log.append(EmcyEvent(node_id, code, register, payload, now))
        for callback in self._emcy_callbacks:
            callback(node_id, code, register, payload)

    # --------------------------------------------------------------------- SDO

    def _on_sdo_request(self, msg: can.Message, now: float) -> None:
        if not self.sdo_allowed:
            self.counters.ignored_in_state += 1
            return
        if len(msg.data) != 8:
            self.counters.malformed_frames += 1
            return
        self.counters.sdo_requests += 1
        data = msg.data
        ccs = data[0] & 0xE0
        if ccs == 0x00:  # download segment
            # canopen's server keeps the buffer of a finished transfer and would store a
            # stray segment into the old object: only pass segments of an open download.
            if not self._sdo_downloading:
                self._sdo_protocol_abort()
                return
            if data[0] & 0x01:
                self._sdo_downloading = False
        else:
            # A non-expedited initiate download opens a segmented download; any other
            # request (or an abort) closes it.
            self._sdo_downloading = ccs == 0x20 and not data[0] & 0x02
        try:
            self.network.notify(msg.arbitration_id, data, now)
        except Exception:
            # canopen's server raises out of on_request when it cannot even build its abort
            # (e.g. an upload segment with no transfer): answer for it.
            self._sdo_protocol_abort()

    def _sdo_protocol_abort(self) -> None:
        """Abort 0x05040001 for a request that belongs to no transfer."""
        self.counters.sdo_protocol_errors += 1
        self._sdo_downloading = False
        server = self.node.sdo
        index = getattr(server, "_index", None) or 0
        sub = getattr(server, "_subindex", None) or 0
        response = struct.pack("<BHBI", 0x80, index, sub, ABORT_UNKNOWN_COMMAND)
        self.network.send_message(SDO_TX_BASE + self.node_id, response)

    def read(self, index: int, subindex: int = 0) -> Any:
        """The application's read of an OD value (decoded; no access check)."""
        var = self._require_variable(index, subindex)
        return var.decode_raw(self.node.get_data(index, subindex))

    def write(self, index: int, subindex: int, value: Any) -> None:
        """The application's write of an OD value: every check except the access rights
        (so it may write read-only objects such as the statusword); raises
        ``SdoAbortedError`` when a check fails, leaving the value unchanged."""
        var = self._require_variable(index, subindex)
        self.node.set_data(index, subindex, var.encode_raw(value))

    def _require_variable(self, index: int, subindex: int) -> ODVariable:
        var = _variable(self.od, index, subindex)
        if var is None:
            raise KeyError(f"0x{index:04X}:{subindex:02X} is not in node {self.node_id}'s OD")
        return var

    def _validate_write(
        self, index: int, subindex: int, od: ODVariable, data: bytes, **_: Any
    ) -> None:
        """LocalNode write callback: runs before the store; raising aborts the write."""
        value = od.decode_raw(data)
        if od.data_type in dt.NUMBER_TYPES:
            limited = od.min is not None or od.max is not None
            if limited and isinstance(value, float) and math.isnan(value):
                raise SdoAbortedError(ABORT_INVALID_VALUE)
            if od.max is not None and value > od.max:
                raise SdoAbortedError(ABORT_VALUE_HIGH)
            if od.min is not None and value < od.min:
                raise SdoAbortedError(ABORT_VALUE_LOW)
        code = self._builtin_check(index, subindex, value)
        if code:
            raise SdoAbortedError(code)
        for validator in self._validators.get((index, subindex), ()):
            code = validator(value)
            if code:
                raise SdoAbortedError(code)

    def _after_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        if 0x1000 <= index <= 0x1FFF:
            self._builtin_apply(index, subindex)
        callbacks = self._write_callbacks.get((index, subindex))
        if callbacks:
            value = od.decode_raw(data)
            for callback in callbacks:
                callback(value)

    def _builtin_check(self, index: int, subindex: int, value: Any) -> int | None:
        """Object-specific rules of the communication profile (CiA 301 §7.5.2)."""
        if index == 0x1003 and subindex == 0 and value != 0:
            return ABORT_INVALID_VALUE  # only 0 (clear the history) may be written
        if index == 0x1016 and subindex >= 1:
            if value >> 24:
                return ABORT_INVALID_VALUE  # bits 24-31 reserved
            node, ms = (value >> 16) & 0xFF, value & 0xFFFF
            if node and ms:
                for sub, (other, other_ms) in self._consumer_entries().items():
                    if sub != subindex and other == node and other_ms:
                        return ABORT_INCOMPATIBLE  # one node monitored twice
        if index == 0x1019:
            if value == 1 or value > 240:
                return ABORT_INVALID_VALUE  # 1 and 241..255 are reserved
            if _variable(self.od, 0x1006, 0) is not None and self.read(0x1006) != 0:
                return ABORT_DEVICE_STATE  # only writable while the SYNC period is 0
        if _is_mapping_index(index):
            if subindex == 0:
                return self._check_mapping_count(index, value)
            return self._check_mapping_entry(value)
        return None

    def _check_mapping_entry(self, value: int) -> int | None:
        if value == 0:
            return None
        index, sub, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
        if index in _DUMMY_BITS:
            return None if sub == 0 and bits == _DUMMY_BITS[index] else ABORT_INCOMPATIBLE
        var = _variable(self.od, index, sub)
        if var is None:
            return ABORT_NO_OBJECT
        if not var.pdo_mappable:
            return ABORT_NOT_MAPPABLE
        if bits != len(var):
            return ABORT_INCOMPATIBLE
        return None

    def _check_mapping_count(self, index: int, count: int) -> int | None:
        obj = self.od.get(index)
        entries = [s for s in getattr(obj, "subindices", {}) if s > 0]
        if count > len(entries):
            return ABORT_PDO_LENGTH
        total = 0
        for sub in range(1, count + 1):
            total += self.read(index, sub) & 0xFF
        return ABORT_PDO_LENGTH if total > 64 else None

    def _builtin_apply(self, index: int, subindex: int) -> None:
        if index == 0x1017:
            self._hb_period_s = self.read(0x1017) / 1e3
            if self.state is not NmtState.INITIALISING:
                self._start_heartbeat(self.now)
        elif index == 0x1016:
            self._configure_consumers(self._consumers_from_od())
        elif index == 0x1003 and subindex == 0:
            self.node.data_store[0x1003] = {0: b"\x00"}
        elif index in (0x1005, 0x1019) and self.sync_producer is not None:
            self._configure_sync_producer(self.sync_producer)
        elif index in (0x1014, 0x1029):
            self._load_comm_config()

    # ------------------------------------------------------------ configuration

    def _set_power_on_values(
        self, heartbeat_ms: int | None, consumers: Mapping[int, int] | None
    ) -> None:
        if heartbeat_ms is not None:
            if not 0 <= heartbeat_ms <= 0xFFFF:
                raise ValueError(f"heartbeat producer time must be 0..65535 ms, got {heartbeat_ms}")
            self._hb_fallback_ms = heartbeat_ms
            if _variable(self.od, 0x1017, 0) is not None:
                self._power_on[(0x1017, 0)] = struct.pack("<H", heartbeat_ms)
        if consumers is not None:
            for node, ms in consumers.items():
                if not 1 <= node <= 127 or not 0 <= ms <= 0xFFFF or node == self.node_id:
                    raise ValueError(f"bad heartbeat consumer entry node {node}: {ms} ms")
            self._consumer_fallback = dict(consumers)
            subs = sorted(self._consumer_entries())
            if subs:
                if len(consumers) > len(subs):
                    raise ValueError(
                        f"{len(consumers)} heartbeat consumers but 0x1016 has {len(subs)} entries"
                    )
                items = sorted(consumers.items())
                for i, sub in enumerate(subs):
                    node, ms = items[i] if i < len(items) else (0, 0)
                    self._power_on[(0x1016, sub)] = struct.pack("<I", node << 16 | ms)

    def _apply_power_on_values(self, low: int = 0x0000, high: int = 0xFFFF) -> None:
        for (index, sub), data in self._power_on.items():
            if low <= index <= high:
                self.node.data_store.setdefault(index, {})[sub] = data

    def _consumer_entries(self) -> dict[int, tuple[int, int]]:
        obj = self.od.get(0x1016)
        if not isinstance(obj, (ODArray, ODRecord)):
            return {}
        entries = {}
        for sub in obj.subindices:
            if sub > 0:
                value = self.read(0x1016, sub)
                entries[sub] = ((value >> 16) & 0xFF, value & 0xFFFF)
        return entries

    def _consumers_from_od(self) -> dict[int, int]:
        return {node: ms for node, ms in self._consumer_entries().values() if node and ms}

    def _load_comm_config(self) -> None:
        if _variable(self.od, 0x1017, 0) is not None:
            self._hb_period_s = self.read(0x1017) / 1e3
        else:
            self._hb_period_s = self._hb_fallback_ms / 1e3
        if isinstance(self.od.get(0x1016), (ODArray, ODRecord)):
            self._configure_consumers(self._consumers_from_od())
        else:
            self._configure_consumers(self._consumer_fallback)
        if _variable(self.od, 0x1014, 0) is not None:
            cob = self.read(0x1014)
            self._emcy_cob_id = None if cob & 0x80000000 else cob & 0x7FF
        else:
            self._emcy_cob_id = EMCY_BASE + self.node_id
        self._error_behaviour = (
            self.read(0x1029, 1) if _variable(self.od, 0x1029, 1) is not None else None
        )
        if self.sync_producer is not None:
            self._configure_sync_producer(self.sync_producer)

    def _build_dispatch(self) -> dict[int, Callable[[can.Message, float], None]]:
        dispatch: dict[int, Callable[[can.Message, float], None]] = {
            NMT_COB_ID: self._on_nmt,
            SDO_RX_BASE + self.node_id: self._on_sdo_request,
        }
        for other in range(1, 128):
            if other != self.node_id:
                dispatch[HEARTBEAT_BASE + other] = self._on_heartbeat
                dispatch[EMCY_BASE + other] = self._on_emcy
        return dispatch

    # -------------------------------------------------------------------- SYNC

    @property
    def sync_period_s(self) -> float | None:
        """0x1006 communication cycle period in seconds (None if absent or 0)."""
        if _variable(self.od, 0x1006, 0) is None:
            return None
        us = self.read(0x1006)
        return us / 1e6 if us else None

    def make_sync_producer(self) -> SyncProducer:
        """A SYNC producer configured from 0x1005 (COB-ID) and 0x1019 (counter overflow),
        kept in step with SDO writes to them and reset by NMT as CiA 301 requires."""
        producer = SyncProducer(self.bus)
        self._configure_sync_producer(producer)
        self.sync_producer = producer
        return producer

    def send_sync(self) -> bool:
        """Send one SYNC through ``sync_producer`` if the NMT state allows it."""
        if self.sync_producer is None:
            raise RuntimeError("no SYNC producer: call make_sync_producer() first")
        if not self.sync_allowed:
            return False
        self.sync_producer.send()
        return True

    def _configure_sync_producer(self, producer: SyncProducer) -> None:
        has = _variable(self.od, 0x1005, 0) is not None
        cob = self.read(0x1005) & 0x7FF if has else SYNC_COB_ID
        overflow = self.read(0x1019) if _variable(self.od, 0x1019, 0) is not None else 0
        producer.configure(overflow=overflow, cob_id=cob)


# ------------------------------------------------------------------------- SYNC


class SyncProducer:
    """SYNC producer (CiA 301 §7.2.5): counter 1..overflow then 1 again; 0 = no counter.

    ``overflow`` is object 0x1019: 0 sends SYNC with DLC 0, 2..240 adds the counter byte.
    """

    def __init__(self, bus: can.BusABC, overflow: int = 0, cob_id: int = SYNC_COB_ID) -> None:
        self.bus = bus
        self.sent = 0
        self.counter = 0  # last counter sent (0 before the first SYNC / after a reset)
        self._payloads = [bytes((i,)) for i in range(256)]
        self.configure(overflow=overflow, cob_id=cob_id)

    def configure(self, *, overflow: int, cob_id: int = SYNC_COB_ID) -> None:
        """Set 0x1019 / COB-ID; the counter restarts at 1 (CiA 301 §7.5.2.22)."""
        if overflow == 1 or not 0 <= overflow <= 240:
            raise ValueError(f"SYNC counter overflow must be 0 or 2..240 (CiA 301), got {overflow}")
        self.overflow = overflow
        self.cob_id = cob_id
        self._msg = can.Message(
            arbitration_id=cob_id,
            is_extended_id=False,
            data=bytes(1 if overflow else 0),
            check=False,
        )
        self.reset()

    def reset(self) -> None:
        """The next SYNC carries counter 1."""
        self.counter = 0

    def send(self) -> int | None:
        """Send one SYNC; returns the counter it carried (None without a counter)."""
        msg = self._msg
        if self.overflow:
            self.counter = self.counter % self.overflow + 1
            msg.data = self._payloads[self.counter]
        self.bus.send(msg)
        self.sent += 1
        return self.counter if self.overflow else None


@dataclass
class SyncMonitor:
    """SYNC consumer checks: missed SYNCs, late or missing cyclic commands (counters only).

    ``period_s`` is the SYNC period (0x1006), ``overflow`` the producer's counter overflow
    (0x1019 of the producer; 0 = SYNC without counter).  Missed SYNCs come from the
    counter when there is one; with a period too, the number of whole periods elapsed
    settles how many counter wraps were missed.  A command (the synchronous RPDO) is late
    when it arrives more than ``command_deadline_s`` after the SYNC that started its cycle
    (default ``period_s``: it must arrive before the next SYNC is due).  A cycle without
    any command counts in ``missing_commands`` once commands have started to arrive.
    The node decides the reaction (e.g. EMCY 0x8250, quick stop).
    """

    period_s: float | None = None
    overflow: int = 0
    command_deadline_s: float | None = None
    syncs: int = 0
    missed_syncs: int = 0
    #: SYNCs whose DLC/counter did not match ``overflow`` (EMCY 0x8240 material).
    length_errors: int = 0
    late_commands: int = 0
    missing_commands: int = 0
    last_counter: int | None = None
    last_sync_time: float | None = None
    _commands_in_cycle: int = field(default=0, init=False, repr=False)
    _commands_started: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.overflow == 1 or not 0 <= self.overflow <= 240:
            raise ValueError(f"SYNC counter overflow must be 0 or 2..240, got {self.overflow}")
        if self.period_s is not None and self.period_s <= 0:
            raise ValueError(f"SYNC period must be > 0, got {self.period_s}")
        if self.command_deadline_s is None:
            self.command_deadline_s = self.period_s

    def on_sync_frame(self, msg: can.Message, now: float) -> int:
        """``on_sync`` for a received SYNC frame (DLC 0: no counter, DLC 1: counter)."""
        data = msg.data
        if len(data) > 1:
            self.length_errors += 1
            return self._register(None, now)
        return self.on_sync(data[0] if data else None, now)

    def on_sync(self, counter: int | None, now: float) -> int:
        """Register a SYNC; returns how many SYNCs were missed just before it."""
        if (counter is None) != (self.overflow == 0) or (
            counter is not None and not 1 <= counter <= self.overflow
        ):
            self.length_errors += 1
            counter = None
        return self._register(counter, now)

    def _register(self, counter: int | None, now: float) -> int:
        missed = 0
        if self.last_sync_time is not None:
            elapsed = None
            if self.period_s is not None:
                elapsed = max(0, round((now - self.last_sync_time) / self.period_s) - 1)
            if counter is not None and self.last_counter is not None:
                missed = (counter - (self.last_counter % self.overflow + 1)) % self.overflow
                if elapsed is not None and elapsed > missed:
                    missed += self.overflow * round((elapsed - missed) / self.overflow)
            elif elapsed is not None:
                missed = elapsed
            if self._commands_started and self._commands_in_cycle == 0:
                self.missing_commands += 1
        self.missed_syncs += missed
        self.syncs += 1
        self.last_counter = counter
        self.last_sync_time = now
        self._commands_in_cycle = 0
        return missed

    def on_command(self, now: float) -> bool:
        """Register a cyclic command; True if on time (before the deadline after its SYNC)."""
        self._commands_started = True
        self._commands_in_cycle += 1
        if self.last_sync_time is None or self.command_deadline_s is None:
            return True
        if now - self.last_sync_time > self.command_deadline_s + TIME_EPSILON:
            self.late_commands += 1
            return False
        return True

    @property
    def next_sync_due(self) -> float | None:
        if self.last_sync_time is None or self.period_s is None:
            return None
        return self.last_sync_time + self.period_s


# ------------------------------------------------------------------- SDO client


class SdoError(Exception):
    """An SDO transfer failed: ``code`` is the CiA 301 abort code (0x05040000 on timeout)."""

    def __init__(self, code: int, node_id: int, index: int, subindex: int, action: str) -> None:
        self.code = code
        self.node_id = node_id
        self.index = index
        self.subindex = subindex
        self.text = abort_text(code)
        super().__init__(
            f"SDO {action} of 0x{index:04X}:{subindex:02X} on node {node_id} failed: "
            f"abort 0x{code:08X} ({self.text})"
        )


def _remote_node(
    network: canopen.Network, node_id: int, od: ObjectDictionary | None, timeout: float
) -> canopen.RemoteNode:
    node = network.nodes.get(node_id)
    if node is None:
        node = network.add_node(node_id, od if od is not None else ObjectDictionary())
    elif not isinstance(node, canopen.RemoteNode):
        raise ValueError(f"node {node_id} is a local node on this network, not an SDO server")
    node.sdo.RESPONSE_TIMEOUT = timeout
    return node


def _client_error(exc: Exception, node_id: int, index: int, sub: int, action: str) -> SdoError:
    if isinstance(exc, SdoAbortedError):
        return SdoError(exc.code, node_id, index, sub, action)
    code = ABORT_TIMEOUT if "No SDO response" in str(exc) else ABORT_UNKNOWN_COMMAND
    return SdoError(code, node_id, index, sub, action)


def sdo_read(
    network: canopen.Network,
    node_id: int,
    index: int,
    subindex: int = 0,
    *,
    od: ObjectDictionary | None = None,
    timeout: float = 1.0,
    raw: bool = False,
) -> Any:
    """Read index:sub of ``node_id`` (host tool; blocks up to ``timeout`` per response).

    The network must be receiving (``network.connect(...)`` starts canopen's Notifier).
    Returns the value decoded with the node's OD (``od`` or the one already attached),
    raw bytes without one or with ``raw``.  Raises :class:`SdoError` with the abort code.
    """
    node = _remote_node(network, node_id, od, timeout)
    try:
        data = node.sdo.upload(index, subindex)
    except (SdoAbortedError, SdoCommunicationError) as exc:
        raise _client_error(exc, node_id, index, subindex, "read") from exc
    var = _variable(node.object_dictionary, index, subindex)
    if raw or var is None:
        return data
    return var.decode_raw(data)


def sdo_write(
    network: canopen.Network,
    node_id: int,
    index: int,
    subindex: int,
    value: Any,
    *,
    od: ObjectDictionary | None = None,
    timeout: float = 1.0,
    force_segment: bool = False,
) -> None:
    """Write index:sub of ``node_id``: ``value`` as bytes, or encoded with the node's OD.

    Up to 4 bytes go expedited, longer data (or ``force_segment``) segmented.  Raises
    :class:`SdoError` with the abort code; a value the OD cannot encode raises ValueError.
    """
    node = _remote_node(network, node_id, od, timeout)
    if isinstance(value, (bytes, bytearray)):
        data = bytes(value)
    else:
        var = _variable(node.object_dictionary, index, subindex)
        if var is None:
            raise TypeError(
                f"0x{index:04X}:{subindex:02X} is not in the OD given for node {node_id}: "
                "pass the value as bytes"
            )
        data = var.encode_raw(value)
    try:
        node.sdo.download(index, subindex, data, force_segment=force_segment)
    except (SdoAbortedError, SdoCommunicationError) as exc:
        raise _client_error(exc, node_id, index, subindex, "write") from exc

"""CANopen services (CiA 301) of one node: the protocol objects composed on canopen's
``LocalNode``, and the NMT slave state machine that gates them.

One protocol per module: :mod:`~hdhil.canopen.od` (EDS loading, lookups),
:mod:`~hdhil.canopen.nmt` (states, commands, master), :mod:`~hdhil.canopen.heartbeat`
(producer, consumer), :mod:`~hdhil.canopen.emcy` (codes, producer, history),
:mod:`~hdhil.canopen.sdo` (checked server, non-blocking client, host helpers),
:mod:`~hdhil.canopen.pdo` (mapping checks), :mod:`~hdhil.canopen.sync` (producer,
consumer checks).  :class:`CanopenServices` makes one object per protocol and exposes it
(``services.nmt``, ``.heartbeat``, ``.heartbeat_consumer``, ``.emcy``, ``.sdo``,
``.sync``), as canopen's nodes do, so a node calls the protocol it means; what depends on
the NMT state (which service may run, resets, SYNC) stays here.  The protocol modules'
names are re-exported for the nodes that use several.

Everything is driven explicitly, so lockstep runs stay deterministic: no threads, no
timers, no ``send_periodic``.  Time comes in as ``now`` (simulated time in lockstep,
``time.monotonic()`` in real time), frames come in through ``CanopenServices.handle`` and
go out through ``bus.send``; python-canopen's ``Network`` runs without its ``Notifier``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import can
import canopen
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable
from canopen.sdo import SdoAbortedError

from hdhil.canopen.clock import TIME_EPSILON
from hdhil.canopen.emcy import (
    EMCY_BASE,
    EMCY_TEXT,
    EmcyCode,
    EmcyEvent,
    EmcyProducer,
    ErrorRegister,
    decode_emcy,
    default_error_register,
    emcy_text,
)
from hdhil.canopen.heartbeat import HeartbeatConsumer, HeartbeatProducer, MonitoredNode
from hdhil.canopen.nmt import (
    HEARTBEAT_BASE,
    NMT_COB_ID,
    BootTimeoutError,
    NmtCommand,
    NmtMaster,
    NmtState,
    ResetKind,
    boot_up_frame,
)
from hdhil.canopen.od import is_comm_index, is_mapping_index, load_od, variable
from hdhil.canopen.pdo import check_comm_write, check_mapping_write
from hdhil.canopen.sdo import (
    ABORT_DEVICE_STATE,
    ABORT_INCOMPATIBLE,
    ABORT_INVALID_VALUE,
    ABORT_STORE,
    ABORT_TEXT,
    SDO_RX_BASE,
    SDO_TX_BASE,
    SdoError,
    SdoServerGate,
    SdoServerNode,
    abort_text,
    check_value_range,
    sdo_read,
    sdo_write,
)
from hdhil.canopen.sync import SYNC_COB_ID, SyncMonitor, SyncProducer

__all__ = [
    "ABORT_DEVICE_STATE",
    "ABORT_INVALID_VALUE",
    "ABORT_TEXT",
    "EMCY_BASE",
    "EMCY_TEXT",
    "HEARTBEAT_BASE",
    "NMT_COB_ID",
    "SDO_RX_BASE",
    "SDO_TX_BASE",
    "SYNC_COB_ID",
    "TIME_EPSILON",
    "BootTimeoutError",
    "CanopenServices",
    "EmcyCode",
    "EmcyEvent",
    "ErrorRegister",
    "MonitoredNode",
    "NmtCommand",
    "NmtState",
    "ResetKind",
    "SdoError",
    "ServiceCounters",
    "SyncMonitor",
    "SyncProducer",
    "abort_text",
    "default_error_register",
    "emcy_text",
    "load_od",
    "sdo_read",
    "sdo_write",
]

#: 0x1010 / 0x1011 signatures: "save" and "load" as little-endian ASCII (CiA 301 §7.5.2.13).
_SAVE = int.from_bytes(b"save", "little")
_LOAD = int.from_bytes(b"load", "little")

# The NMT states the per-frame checks test for, as module globals: an attribute of an Enum
# class (``NmtState.OPERATIONAL``) is looked up through ``EnumType.__getattr__``'s slow
# path in Python 3.11, several times slower than a global.
_OPERATIONAL = NmtState.OPERATIONAL
_PRE_OPERATIONAL = NmtState.PRE_OPERATIONAL


@dataclass
class ServiceCounters:
    """What the services did (never reset, not even by NMT resets)."""

    nmt_commands: int = 0
    sdo_requests: int = 0
    heartbeats_sent: int = 0
    heartbeats_received: int = 0
    #: EMCY frames received from other nodes (those sent: ``emcy.sent``).
    emcy_received: int = 0
    #: Frames of the right COB-ID but wrong length (NMT 2, SDO 8, heartbeat 1, EMCY 8).
    malformed_frames: int = 0
    #: SDO/EMCY frames ignored because of this node's NMT state (INITIALISING, STOPPED).
    ignored_in_state: int = 0
    #: SDO segments outside a transfer, answered with abort 0x05040001.
    sdo_protocol_errors: int = 0


Validator = Callable[[Any], "int | None"]
WriteCallback = Callable[[Any], None]


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

    The protocol objects are attributes, used directly (as ``canopen``'s nodes expose
    theirs): ``nmt``, the NMT master (:class:`~hdhil.canopen.nmt.NmtMaster`: commands,
    boot-up waits, the remote nodes' boot times and states); ``heartbeat`` and
    ``heartbeat_consumer`` (:mod:`~hdhil.canopen.heartbeat`: producer period, monitored
    nodes); ``emcy``, the EMCY producer (:class:`~hdhil.canopen.emcy.EmcyProducer`:
    ``raise_error``, ``clear``, ``reset``, error register, history, frames ``sent``);
    ``sdo``, the SDO server gate (:class:`~hdhil.canopen.sdo.SdoServerGate`); ``sync``,
    the SYNC producer once ``make_sync_producer`` made it (else None).  This class keeps
    what needs the NMT slave state: ``send_sync``, the state gates, resets.

    Per node, the application does, once per cycle::

        services.tick(now)                   # heartbeat producer, heartbeat consumer timeouts
        while (msg := bus.recv(0)) is not None:
            if not services.handle(msg):     # NMT, SDO, heartbeat, EMCY: consumed here
                node.on_message(msg)         # SYNC and PDOs: the node's own business

    ``handle`` costs one dict lookup for frames that are not CANopen service frames;
    ``handle`` feeds SDO requests to ``network.notify`` and the ``LocalNode``'s SDO server
    answers synchronously through ``network.send_message``.

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
        self.node = SdoServerNode(node_id, self.od, length_aborts == "specific")
        self.network = canopen.Network(bus)  # no Notifier: frames come in through handle()
        self.network.add_node(self.node)
        self.node.add_write_callback(self._validate_write)
        self.node.after_write = self._after_write
        self.emcy_on_heartbeat_loss = emcy_on_heartbeat_loss

        self.state = NmtState.INITIALISING
        self._set_permissions(self.state)
        #: The latest ``now`` given to ``boot``/``tick``; frames handled without an explicit
        #: ``now`` are timed with it.
        self.now = 0.0
        self.counters = ServiceCounters()
        self.emcy_log: deque[EmcyEvent] = deque(maxlen=emcy_log_size)
        self.nmt = NmtMaster(bus)
        self.heartbeat = HeartbeatProducer(bus, node_id)
        self.heartbeat_consumer = HeartbeatConsumer(self.nmt)
        self.emcy = EmcyProducer(bus, self.od, self.node.data_store, lambda: self.emcy_allowed)
        self.emcy.cob_id = EMCY_BASE + node_id
        self.sdo = SdoServerGate(self.node, self.network)
        self.sync: SyncProducer | None = None

        self._state_callbacks: list[Callable[[NmtState, NmtState], None]] = []
        self._reset_callbacks: list[Callable[[ResetKind], None]] = []
        self._lost_callbacks: list[Callable[[int], None]] = []
        self._resumed_callbacks: list[Callable[[int], None]] = []
        self._boot_callbacks: list[Callable[[int], None]] = []
        self._emcy_callbacks: list[Callable[[int, int, int, bytes], None]] = []
        self._validators: dict[tuple[int, int], list[Validator]] = {}
        self._write_callbacks: dict[tuple[int, int], list[WriteCallback]] = {}

        self._hb_fallback_ms = 0
        self._consumer_fallback: dict[int, int] = {}
        self._error_behaviour: int | None = None
        self._power_on: dict[tuple[int, int], bytes] = {}
        #: Values saved by 0x1010 ("save"): the node's non-volatile memory.  It lives as
        #: long as this object (NMT resets keep it, a new process starts without it).
        self.saved: dict[tuple[int, int], bytes] = {}
        self._set_power_on_values(heartbeat_producer_ms, heartbeat_consumers)
        self._apply_power_on_values()
        self._load_comm_config()
        self._dispatch = self._build_dispatch()
        #: The identifiers of the service frames :meth:`handle` consumes (fixed per node):
        #: a node's frame handler tests this first and skips :meth:`handle` for the rest.
        self.service_ids: frozenset[int] = frozenset(self._dispatch)

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

    def set_power_on_value(self, index: int, subindex: int, value: Any) -> None:
        """Make ``value`` the power-on value of index:sub: stored now and again after every
        NMT reset that restores its area (the node's configuration instead of the EDS
        default, e.g. a drive's RPDO transmission type from its actuation setting)."""
        var = self._require_variable(index, subindex)
        data = var.encode_raw(value)
        self._power_on[(index, subindex)] = data
        self.node.data_store.setdefault(index, {})[subindex] = data

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
        if now + TIME_EPSILON >= self.heartbeat.next_due:
            self.heartbeat.send(now, self.state)
            self.counters.heartbeats_sent += 1
        consumer = self.heartbeat_consumer
        if now > consumer.next_expiry:  # a float test per cycle; expired() scans the nodes
            for monitor in consumer.expired(now):
                self._heartbeat_lost(monitor)

    def produce_heartbeat(self, now: float) -> None:
        """The heartbeat producer alone (a heartbeat when due, no timeout detection):
        for a master that stays alive outside its node loop, e.g. while it ends a
        session by blocking SDO transfers (its heartbeat must not stop before its entry
        in the drive's consumer 0x1016 is cleared)."""
        self.now = now
        if now + TIME_EPSILON >= self.heartbeat.next_due:
            self.heartbeat.send(now, self.state)
            self.counters.heartbeats_sent += 1

    # --------------------------------------------------------------- NMT slave

    def _set_permissions(self, state: NmtState) -> None:
        """The services ``state`` allows (CiA 301 §7.3.2.2), kept as plain attributes
        because the cyclic path reads them on every frame; :meth:`_set_state` (the one
        place the NMT state changes) calls this."""
        #: PDOs may be sent and received only in OPERATIONAL.
        self.pdo_allowed: bool = state is _OPERATIONAL
        #: SDO, SYNC and EMCY: PRE-OPERATIONAL and OPERATIONAL.
        self.sdo_allowed: bool = state is _OPERATIONAL or state is _PRE_OPERATIONAL
        self.sync_allowed: bool = self.sdo_allowed
        self.emcy_allowed: bool = self.sdo_allowed

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
        self._set_permissions(new)
        if old is NmtState.STOPPED and self.sync is not None:
            self.sync.reset()  # CiA 301: counter restarts when leaving STOPPED
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
            self.emcy.active.clear()
        self._apply_power_on_values(low, high)
        for (index, sub), data in self.saved.items():
            if low <= index <= high:
                store.setdefault(index, {})[sub] = data
        self._load_comm_config()
        self.emcy.store_error_register()
        for callback in self._reset_callbacks:
            callback(kind)
        self._boot_up(now)

    def _boot_up(self, now: float) -> None:
        self.bus.send(boot_up_frame(self.node_id))
        self.heartbeat.start(now)
        if self.sync is not None:
            self.sync.reset()
        self._set_state(NmtState.PRE_OPERATIONAL)

    # --------------------------------------------------------------- heartbeat

    def _on_heartbeat(self, msg: can.Message, now: float) -> None:
        if len(msg.data) != 1:
            self.counters.malformed_frames += 1
            return
        node_id = msg.arbitration_id - HEARTBEAT_BASE
        self.counters.heartbeats_received += 1
        event = self.heartbeat_consumer.on_frame(
            node_id, msg.data[0], now, self.state is not NmtState.INITIALISING
        )
        if event == "boot":
            for callback in self._boot_callbacks:
                callback(node_id)
        elif event == "resumed":
            if self.emcy_on_heartbeat_loss:
                self.emcy.clear(EmcyCode.HEARTBEAT, bytes((node_id,)))
            for callback in self._resumed_callbacks:
                callback(node_id)

    def _heartbeat_lost(self, monitor: MonitoredNode) -> None:
        if self.emcy_on_heartbeat_loss:
            self.emcy.raise_error(EmcyCode.HEARTBEAT, manufacturer=bytes((monitor.node_id,)))
        # 0x1029 sub 1 "communication error" behaviour (CiA 301 §7.5.2.32).
        if self._error_behaviour == 0 and self.state is NmtState.OPERATIONAL:
            self._set_state(NmtState.PRE_OPERATIONAL)
        elif self._error_behaviour == 2 and self.state is not NmtState.INITIALISING:
            self._set_state(NmtState.STOPPED)
        for callback in self._lost_callbacks:
            callback(monitor.node_id)

    # -------------------------------------------------------------------- EMCY

    def _on_emcy(self, msg: can.Message, now: float) -> None:
        if self.state in (NmtState.INITIALISING, NmtState.STOPPED):
            self.counters.ignored_in_state += 1
            return
        if len(msg.data) != 8:
            self.counters.malformed_frames += 1
            return
        code, register, payload = decode_emcy(msg.data)
        node_id = msg.arbitration_id - EMCY_BASE
        self.counters.emcy_received += 1
        self.emcy_log.append(EmcyEvent(node_id, code, register, payload, now))
        for callback in self._emcy_callbacks:
            callback(node_id, code, register, payload)

    # --------------------------------------------------------------------- SDO

    def _on_sdo_request(self, msg: can.Message, now: float) -> None:
        outcome = self.sdo.handle(msg, now, self.sdo_allowed)
        counters = self.counters
        if outcome == "ignored":
            counters.ignored_in_state += 1
        elif outcome == "malformed":
            counters.malformed_frames += 1
        else:
            counters.sdo_requests += 1
            if outcome == "protocol":
                counters.sdo_protocol_errors += 1

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
        var = variable(self.od, index, subindex)
        if var is None:
            raise KeyError(f"0x{index:04X}:{subindex:02X} is not in node {self.node_id}'s OD")
        return var

    def _validate_write(
        self, index: int, subindex: int, od: ODVariable, data: bytes, **_: Any
    ) -> None:
        """LocalNode write callback: runs before the store; raising aborts the write."""
        value = od.decode_raw(data)
        code = check_value_range(od, value) or self._builtin_check(index, subindex, value)
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
        if index in (0x1010, 0x1011) and subindex >= 1:
            signature = _SAVE if index == 0x1010 else _LOAD
            return None if value == signature else ABORT_STORE  # CiA 301 §7.5.2.13/14
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
            if variable(self.od, 0x1006, 0) is not None and self.read(0x1006) != 0:
                return ABORT_DEVICE_STATE  # only writable while the SYNC period is 0
        if is_comm_index(index):
            return check_comm_write(self.od, self.read, index, subindex, value)
        if is_mapping_index(index):
            return check_mapping_write(self.od, self.read, index, subindex, value)
        return None

    def _builtin_apply(self, index: int, subindex: int) -> None:
        if index == 0x1017:
            self.heartbeat.period_s = self.read(0x1017) / 1e3
            if self.state is not NmtState.INITIALISING:
                self.heartbeat.start(self.now)
        elif index == 0x1016:
            self.heartbeat_consumer.configure(self._consumers_from_od())
        elif index == 0x1010:
            self._save_parameters()
            self.node.data_store[0x1010][subindex] = self.od[0x1010][subindex].encode_raw(1)
        elif index == 0x1011:
            self.saved.clear()  # the defaults come back at the next reset (CiA 301)
            self.node.data_store[0x1011][subindex] = self.od[0x1011][subindex].encode_raw(1)
        elif index == 0x1003 and subindex == 0:
            self.node.data_store[0x1003] = {0: b"\x00"}
        elif index in (0x1005, 0x1019) and self.sync is not None:
            self._configure_sync_producer(self.sync)
        elif index in (0x1014, 0x1029):
            self._load_comm_config()

    # ------------------------------------------------------------ configuration

    def _save_parameters(self) -> None:
        """0x1010 "save": every writable value stored now (communication, application and
        profile areas) becomes what NMT resets restore."""
        saved = {}
        for index, subs in self.node.data_store.items():
            if not 0x1000 <= index <= 0x9FFF or index in (0x1010, 0x1011):
                continue
            for sub, data in subs.items():
                var = variable(self.od, index, sub)
                if var is not None and var.writable:
                    saved[(index, sub)] = bytes(data)
        self.saved = saved

    def _set_power_on_values(
        self, heartbeat_ms: int | None, consumers: Mapping[int, int] | None
    ) -> None:
        if heartbeat_ms is not None:
            if not 0 <= heartbeat_ms <= 0xFFFF:
                raise ValueError(f"heartbeat producer time must be 0..65535 ms, got {heartbeat_ms}")
            self._hb_fallback_ms = heartbeat_ms
            if variable(self.od, 0x1017, 0) is not None:
                self._power_on[(0x1017, 0)] = self.od[0x1017].encode_raw(heartbeat_ms)
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
                    entry = self.od[0x1016][sub]
                    self._power_on[(0x1016, sub)] = entry.encode_raw(node << 16 | ms)

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
        if variable(self.od, 0x1017, 0) is not None:
            self.heartbeat.period_s = self.read(0x1017) / 1e3
        else:
            self.heartbeat.period_s = self._hb_fallback_ms / 1e3
        if isinstance(self.od.get(0x1016), (ODArray, ODRecord)):
            self.heartbeat_consumer.configure(self._consumers_from_od())
        else:
            self.heartbeat_consumer.configure(self._consumer_fallback)
        if variable(self.od, 0x1014, 0) is not None:
            cob = self.read(0x1014)
            self.emcy.cob_id = None if cob & 0x80000000 else cob & 0x7FF
        else:
            self.emcy.cob_id = EMCY_BASE + self.node_id
        self._error_behaviour = (
            self.read(0x1029, 1) if variable(self.od, 0x1029, 1) is not None else None
        )
        if self.sync is not None:
            self._configure_sync_producer(self.sync)

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
        if variable(self.od, 0x1006, 0) is None:
            return None
        us = self.read(0x1006)
        return us / 1e6 if us else None

    def make_sync_producer(self) -> SyncProducer:
        """A SYNC producer configured from 0x1005 (COB-ID) and 0x1019 (counter overflow),
        kept in step with SDO writes to them and reset by NMT as CiA 301 requires."""
        producer = SyncProducer(self.bus)
        self._configure_sync_producer(producer)
        self.sync = producer
        return producer

    def send_sync(self) -> bool:
        """Send one SYNC through ``sync`` if the NMT state allows it."""
        if self.sync is None:
            raise RuntimeError("no SYNC producer: call make_sync_producer() first")
        if not self.sync_allowed:
            return False
        self.sync.send()
        return True

    def _configure_sync_producer(self, producer: SyncProducer) -> None:
        has = variable(self.od, 0x1005, 0) is not None
        cob = self.read(0x1005) & 0x7FF if has else SYNC_COB_ID
        overflow = self.read(0x1019) if variable(self.od, 0x1019, 0) is not None else 0
        producer.configure(overflow=overflow, cob_id=cob)

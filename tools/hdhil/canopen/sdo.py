"""SDO (CiA 301 §7.2.4): abort codes, the checked server, a non-blocking client and the
blocking helpers of the host tools.

Command specifiers, the ``<BHB`` header and the abort codes come from
``canopen.sdo.constants``; only the CiA 301 texts of the abort codes are added here.

- :class:`SdoServerNode` is canopen's ``LocalNode`` (its SDO server, expedited and
  segmented) with the CiA 301 aborts it lacks: specific length codes 0x06070012/13,
  sub-indices of arrays that are not defined (0x06090011; canopen invents them), and a
  post-store hook whose failure restores the old value.
- :class:`TransferSdoServer` is canopen's ``SdoServer`` that knows which segmented
  transfer is open (canopen answers an upload segment from whatever buffer is left).
- :class:`SdoServerGate` sits in front of it: SDO only in PRE-OPERATIONAL/OPERATIONAL,
  8-byte frames only, and abort 0x05040001 for a segment of no open transfer (§7.2.4.3).
- :class:`SdoClient` is the client a node in a lockstep loop uses: it sends one request
  and returns at once; the response is fed in as a frame.  Expedited transfers only (all
  a controller needs for words and counters).
- :func:`sdo_read` / :func:`sdo_write` block on canopen's own client (host tools).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can
import canopen
from canopen.objectdictionary import ObjectDictionary, ODArray, ODVariable
from canopen.objectdictionary import datatypes as dt
from canopen.sdo import SdoAbortedError, SdoCommunicationError, SdoServer
from canopen.sdo import constants as sc

from hdhil.canopen.nmt import NMT_COB_ID
from hdhil.canopen.od import variable

__all__ = [
    "ABORT_TEXT",
    "SDO_RX_BASE",
    "SDO_TX_BASE",
    "SdoClient",
    "SdoError",
    "SdoResult",
    "SdoServerGate",
    "SdoServerNode",
    "TransferSdoServer",
    "abort_text",
    "check_value_range",
    "sdo_read",
    "sdo_write",
]

#: SDO server -> client COB-ID base (default server SDO, CiA 301 pre-defined connection set).
SDO_TX_BASE = 0x580
#: SDO client -> server COB-ID base.
SDO_RX_BASE = 0x600

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

# Named abort codes (canopen.sdo.constants).
ABORT_TIMEOUT = sc.ABORT_TIMED_OUT
ABORT_UNKNOWN_COMMAND = sc.ABORT_INVALID_COMMAND_SPECIFIER
ABORT_UNSUPPORTED_ACCESS = sc.ABORT_UNSUPPORTED_ACCESS
ABORT_WRITE_READ_ONLY = sc.ABORT_WRITE_READONLY
ABORT_NOT_MAPPABLE = sc.ABORT_PDO_CANNOT_MAP
ABORT_PDO_LENGTH = sc.ABORT_PDO_LENGTH_EXCEEDED
ABORT_INCOMPATIBLE = sc.ABORT_PARAMETER_INCOMPATIBLE
ABORT_NO_OBJECT = sc.ABORT_NOT_IN_OD
ABORT_LENGTH = sc.ABORT_LENGTH_NOT_MATCHED
ABORT_LENGTH_HIGH = sc.ABORT_LENGTH_TOO_HIGH
ABORT_LENGTH_LOW = sc.ABORT_LENGTH_TOO_LOW
ABORT_NO_SUBINDEX = sc.ABORT_NO_SUBINDEX
ABORT_INVALID_VALUE = sc.ABORT_INVALID_VALUE
ABORT_VALUE_HIGH = sc.ABORT_VALUE_TOO_HIGH
ABORT_VALUE_LOW = sc.ABORT_VALUE_TOO_LOW
ABORT_GENERAL = sc.ABORT_GENERAL_ERROR
ABORT_DEVICE_STATE = sc.ABORT_APPLICATION_DEVICE_STATE
ABORT_STORE = sc.ABORT_STORE_APPLICATION


def abort_text(code: int) -> str:
    """CiA 301 text of an SDO abort code."""
    return ABORT_TEXT.get(code, "unknown abort code")


def check_value_range(od: ODVariable, value: Any) -> int | None:
    """Abort code for a number outside the EDS LowLimit/HighLimit (NaN: 0x06090030)."""
    if od.data_type not in dt.NUMBER_TYPES:
        return None
    limited = od.min is not None or od.max is not None
    if limited and isinstance(value, float) and math.isnan(value):
        return ABORT_INVALID_VALUE
    if od.max is not None and value > od.max:
        return ABORT_VALUE_HIGH
    if od.min is not None and value < od.min:
        return ABORT_VALUE_LOW
    return None


# ------------------------------------------------------------------------ server


class TransferSdoServer(SdoServer):
    """canopen's SDO server that records the segmented transfer in progress.

    ``transfer`` is the client command specifier the next request may carry as a segment:
    ``REQUEST_SEGMENT_UPLOAD`` while a segmented upload has data left,
    ``REQUEST_SEGMENT_DOWNLOAD`` while a segmented download is open, else None.  Every
    request ends the transfer unless it continues it; an abort (sent or received) ends it.
    """

    transfer: int | None = None

    def on_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.transfer = None
        super().on_request(can_id, data, timestamp)

    def init_upload(self, request: bytearray) -> None:
        self._buffer = None  # a segmented upload, and only one, leaves a buffer
        super().init_upload(request)
        if self._buffer:
            self.transfer = sc.REQUEST_SEGMENT_UPLOAD

    def segmented_upload(self, command: int) -> None:
        super().segmented_upload(command)
        if self._buffer:
            self.transfer = sc.REQUEST_SEGMENT_UPLOAD

    def init_download(self, request: bytearray) -> None:
        super().init_download(request)
        if not request[0] & sc.EXPEDITED:
            self.transfer = sc.REQUEST_SEGMENT_DOWNLOAD

    def segmented_download(self, command: int, request: bytearray) -> None:
        super().segmented_download(command, request)
        if not command & sc.NO_MORE_DATA:
            self.transfer = sc.REQUEST_SEGMENT_DOWNLOAD

    def abort(self, abort_code: int = sc.ABORT_GENERAL_ERROR) -> None:
        self.transfer = None
        super().abort(abort_code)


class SdoServerNode(canopen.LocalNode):
    """``LocalNode`` with CiA 301 aborts and post-store callbacks; no threaded heartbeat."""

    def __init__(self, node_id: int, od: ObjectDictionary, specific_length_codes: bool) -> None:
        super().__init__(node_id, od)
        self.sdo: TransferSdoServer = TransferSdoServer(
            SDO_RX_BASE + self.id, SDO_TX_BASE + self.id, self
        )
        # canopen's NmtSlave starts a send_periodic thread on writes of 0x1017 and on its own
        # boot; the heartbeat module produces the heartbeat deterministically instead.
        self._write_callbacks.remove(self.nmt.on_write)
        self.specific_length_codes = specific_length_codes
        #: Called after a write was stored: ``after_write(index, sub, var, data)``.
        self.after_write: Callable[[int, int, ODVariable, bytes], None] | None = None

    def associate_network(self, network: canopen.Network) -> None:
        super().associate_network(network)
        network.unsubscribe(NMT_COB_ID, self.nmt.on_command)  # NMT is the nmt module's job

    def remove_network(self) -> None:
        if self.has_network():
            self.network.subscribe(NMT_COB_ID, self.nmt.on_command)
        super().remove_network()

    def _find_object(self, index: int, subindex: int) -> ODVariable:
        obj = super()._find_object(index, subindex)
        if isinstance(self.object_dictionary[index], ODVariable) and subindex != 0:
            # A single-value object has only sub-index 0 (canopen serves any sub-index).
            raise SdoAbortedError(ABORT_NO_SUBINDEX)
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
            raise SdoAbortedError(ABORT_WRITE_READ_ONLY)
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


class SdoServerGate:
    """The checks in front of canopen's SDO server (CiA 301 §7.2.4, §7.3.2.2).

    ``handle`` returns what happened: "served", "ignored" (NMT state), "malformed"
    (not 8 bytes) or "protocol" (answered with abort 0x05040001: a block transfer, or an
    upload or download segment when no such transfer is open, which also ends the open
    one).  canopen alone would answer a stray upload segment from a stale buffer and
    store a stray download segment into the last object.
    """

    def __init__(self, node: SdoServerNode, network: canopen.Network) -> None:
        self.node = node
        self.network = network

    def handle(self, msg: can.Message, now: float, allowed: bool) -> str:
        if not allowed:
            return "ignored"
        data = msg.data
        if len(data) != 8:
            return "malformed"
        ccs = data[0] & 0xE0
        server = self.node.sdo
        if ccs in (sc.REQUEST_BLOCK_UPLOAD, sc.REQUEST_BLOCK_DOWNLOAD):
            # Block transfers are not implemented: canopen's server would answer a block
            # upload with an expedited response the client cannot parse.  Abort
            # 0x05040001, which every client understands.
            server.transfer = None
            self._abort(int.from_bytes(data[1:3], "little"), data[3], ABORT_UNKNOWN_COMMAND)
            return "protocol"
        segment = ccs in (sc.REQUEST_SEGMENT_UPLOAD, sc.REQUEST_SEGMENT_DOWNLOAD)
        if segment and ccs != server.transfer:
            self.protocol_abort()
            return "protocol"
        try:
            self.network.notify(msg.arbitration_id, data, now)
        except Exception:
            # canopen's server raises out of on_request when it cannot even build its
            # abort: answer for it.
            self.protocol_abort()
            return "protocol"
        return "served"

    def protocol_abort(self) -> None:
        """Abort 0x05040001 for a request that belongs to no transfer; ends any transfer."""
        server = self.node.sdo
        server.transfer = None
        index = getattr(server, "_index", None) or 0
        sub = getattr(server, "_subindex", None) or 0
        self._abort(index, sub, ABORT_UNKNOWN_COMMAND)

    def _abort(self, index: int, sub: int, code: int) -> None:
        response = sc.SDO_STRUCT.pack(sc.RESPONSE_ABORTED, index, sub) + code.to_bytes(4, "little")
        self.network.send_message(SDO_TX_BASE + self.node.id, response)


# ------------------------------------------------------------------------ client


@dataclass(frozen=True)
class SdoResult:
    """The outcome of one :class:`SdoClient` transfer: ``abort`` is None on success,
    ``data`` the uploaded bytes (empty for a download)."""

    index: int
    subindex: int
    data: bytes = b""
    abort: int | None = None

    @property
    def ok(self) -> bool:
        return self.abort is None


class SdoClient:
    """A non-blocking SDO client for one server (expedited transfers, CiA 301 §7.2.4.3).

    A node in the lockstep loop cannot wait for an answer: :meth:`upload` and
    :meth:`download` send the request and return; the node hands every frame from the
    server's response COB-ID to :meth:`on_response`, which returns the finished
    :class:`SdoResult` (or None for a frame that answers nothing pending).  One transfer
    at a time, as CiA 301 allows per SDO channel; a new request replaces a pending one.
    Frames are laid out with ``canopen.sdo.constants``.
    """

    def __init__(self, bus: can.BusABC, server_node_id: int) -> None:
        if not 1 <= server_node_id <= 127:
            raise ValueError(f"SDO server node-ID must be 1..127, got {server_node_id}")
        self.bus = bus
        self.server_node_id = server_node_id
        self.request_id = SDO_RX_BASE + server_node_id
        self.response_id = SDO_TX_BASE + server_node_id
        #: (index, sub, is_upload) of the transfer in progress, None when idle.
        self.pending: tuple[int, int, bool] | None = None
        self.requests = 0
        self.aborts = 0

    def upload(self, index: int, subindex: int = 0) -> None:
        """Request index:sub from the server (initiate upload)."""
        self._send(sc.SDO_STRUCT.pack(sc.REQUEST_UPLOAD, index, subindex) + bytes(4))
        self.pending = (index, subindex, True)

    def download(self, index: int, subindex: int, data: bytes) -> None:
        """Write 1-4 bytes to index:sub (expedited initiate download, size indicated)."""
        if not 1 <= len(data) <= 4:
            raise ValueError(f"expedited download carries 1-4 bytes, got {len(data)}")
        command = sc.REQUEST_DOWNLOAD | sc.EXPEDITED | sc.SIZE_SPECIFIED | ((4 - len(data)) << 2)
        self._send(sc.SDO_STRUCT.pack(command, index, subindex) + bytes(data).ljust(4, b"\0"))
        self.pending = (index, subindex, False)

    def on_response(self, msg: can.Message) -> SdoResult | None:
        """Feed a frame from the server; the result when it completes the pending transfer."""
        data = msg.data
        if self.pending is None or len(data) != 8:
            return None
        command, index, sub = sc.SDO_STRUCT.unpack_from(data)
        want_index, want_sub, upload = self.pending
        if (index, sub) != (want_index, want_sub):
            return None
        scs = command & 0xE0
        if scs == sc.RESPONSE_ABORTED:
            self.pending = None
            self.aborts += 1
            return SdoResult(index, sub, abort=int.from_bytes(data[4:8], "little"))
        if upload and scs == sc.RESPONSE_UPLOAD:
            self.pending = None
            if not command & sc.EXPEDITED:
                # Segmented answer: this client does not continue it; end the transfer.
                self._send(
                    sc.SDO_STRUCT.pack(sc.REQUEST_ABORTED, index, sub)
                    + ABORT_UNKNOWN_COMMAND.to_bytes(4, "little")
                )
                return SdoResult(index, sub, abort=ABORT_UNKNOWN_COMMAND)
            size = 4 - ((command >> 2) & 0x3) if command & sc.SIZE_SPECIFIED else 4
            return SdoResult(index, sub, bytes(data[4 : 4 + size]))
        if not upload and scs == sc.RESPONSE_DOWNLOAD:
            self.pending = None
            return SdoResult(index, sub)
        return None

    def _send(self, data: bytes) -> None:
        self.bus.send(
            can.Message(
                arbitration_id=self.request_id, is_extended_id=False, data=data, check=False
            )
        )
        self.requests += 1


# ------------------------------------------------------------ host tools (blocking)


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
    var = variable(node.object_dictionary, index, subindex)
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
        var = variable(node.object_dictionary, index, subindex)
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

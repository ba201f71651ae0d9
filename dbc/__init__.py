"""CAN database (DBC) and object dictionaries (EDS) of the drive link, and codecs built from them.

``control.dbc`` describes every frame on the control bus, ``truth.dbc`` the emulator's
ground-truth side channel.  ``controller.eds`` and ``drive.eds`` are the two nodes'
CANopen object dictionaries; a test checks that their PDO mappings agree with the DBC.

Frame layouts are never re-typed in code: :class:`FrameCodec` compiles a
``struct`` format from the cantools message definition at start-up (about 10x faster
than ``cantools.Message.encode`` on the 1 kHz path) and is tested against cantools.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from functools import cache
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    import cantools
    from cantools.database.can import Message

BusName = Literal["control", "truth"]
NodeName = Literal["controller", "drive"]

#: python-can channel numbers used for the two buses in traces (BLF/ASC store them 1-based).
CHANNEL_NUMBER: dict[str, int] = {"control": 0, "truth": 1}


def _data_dir() -> Path:
    return Path(str(resources.files(__name__)))


def dbc_path(bus: BusName) -> Path:
    """Path of the DBC file describing ``bus``."""
    return _data_dir() / f"{bus}.dbc"


def eds_path(node: NodeName) -> Path:
    """Path of the EDS (object dictionary) of ``node``."""
    return _data_dir() / f"{node}.eds"


#: The drive mappings shipped here by name: the drive's DCF (None: the EDS defaults, the
#: raw ADC/DAC mapping of [Taghirad97]'s signals; ``drive-cst.dcf``: CiA 402 cyclic
#: synchronous torque; ``drive-cst-sensor.dcf``: the same with the joint-torque sensor
#: 0x2102 beside 0x6077 and 0x6064 in the sensor PDO).
MAPPINGS: dict[str, str | None] = {
    "raw": None,
    "cst": "drive-cst.dcf",
    "cst-sensor": "drive-cst-sensor.dcf",
}


def dcf_path(name: str) -> Path:
    """Path of a device configuration file shipped here (e.g. ``drive-cst.dcf``)."""
    return _data_dir() / name


@cache
def database(bus: BusName) -> cantools.database.can.Database:
    """The cantools database of ``bus`` (loaded once per process, and parsed once per
    machine: :mod:`hdhil.dbc.parsecache`; cantools is imported here, when a database is
    first needed, not when the package is)."""
    import cantools

    from hdhil.dbc.parsecache import cached

    if bus not in CHANNEL_NUMBER:
        raise ValueError(f"unknown bus {bus!r} (known: {', '.join(CHANNEL_NUMBER)})")
    path = str(dbc_path(bus))
    return cached(
        path, "dbc", lambda: cantools.database.load_file(path), ("cantools",), (__file__,)
    )


_INT_CODES = {
    (8, False): "B",
    (8, True): "b",
    (16, False): "H",
    (16, True): "h",
    (32, False): "I",
    (32, True): "i",
    (64, False): "Q",
    (64, True): "q",
}
_FLOAT_CODES = {32: "f", 64: "d"}


class FrameCodec:
    """Fast encoder/decoder for one DBC message, compiled from its cantools definition.

    Supports the layouts this project's DBCs use: little-endian signals that start
    on a byte boundary and are 8/16/32/64 bits wide (integers, optionally scaled) or
    IEEE floats.  Any other layout raises ``ValueError`` at start-up; it is never
    silently mis-packed.  Values are physical (scale and offset applied).  Integer
    signals saturate at their raw range when encoding, like a firmware would clamp
    before writing a mailbox.
    """

    __slots__ = (
        "_bus",
        "_int_raw",
        "_offsets",
        "_scales",
        "_struct",
        "decode",
        "encode",
        "frame_id",
        "is_extended_id",
        "length",
        "message",
        "name",
        "signal_names",
    )

    def __init__(self, message: Message, bus: str = "") -> None:
        self.message = message
        self._bus = f"{bus}.dbc " if bus else ""
        self.name: str = message.name
        self.frame_id: int = message.frame_id
        self.is_extended_id: bool = message.is_extended_frame
        self.length: int = message.length
        if message.is_multiplexed():
            raise ValueError(f"{message.name}: multiplexed messages have no compiled codec")
        signals = sorted(message.signals, key=lambda s: s.start)
        fmt = "<"
        pos = 0
        int_raw: list[tuple[int, int] | None] = []
        for sig in signals:
            if sig.byte_order != "little_endian" or sig.start % 8:
                raise ValueError(
                    f"{message.name}.{sig.name}: only byte-aligned little-endian "
                    "signals are compiled"
                )
            byte = sig.start // 8
            if byte < pos:
                raise ValueError(f"{message.name}.{sig.name}: overlaps the previous signal")
            fmt += "x" * (byte - pos)
            if sig.is_float:
                code = _FLOAT_CODES.get(sig.length)
                int_raw.append(None)
            else:
                code = _INT_CODES.get((sig.length, sig.is_signed))
                lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
                hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
                int_raw.append((lo, hi))
            if code is None:
                raise ValueError(
                    f"{message.name}.{sig.name}: {sig.length}-bit signals are not compiled"
                )
            fmt += code
            pos = byte + sig.length // 8
        if pos > message.length:
            raise ValueError(f"{message.name}: signals exceed the {message.length}-byte payload")
        fmt += "x" * (message.length - pos)
        self._struct = struct.Struct(fmt)
        self.signal_names: tuple[str, ...] = tuple(s.name for s in signals)
        self._scales = tuple(float(s.scale) for s in signals)
        self._offsets = tuple(float(s.offset) for s in signals)
        self._int_raw = tuple(int_raw)
        self._compile()

    def expect(self, *names: str) -> FrameCodec:
        """Check, by name, that ``encode``/``decode`` take and return exactly ``names`` in
        this order; raise ``ValueError`` naming both orders otherwise.

        ``encode``/``decode`` are positional (the 1 kHz path); a node calls this once at
        start-up with the names it packs or unpacks, so a DBC whose signals were reordered,
        renamed, added or removed fails loudly instead of swapping values.
        """
        if tuple(names) != self.signal_names:
            raise ValueError(
                f"{self._bus}{self.name}: the node expects the signals "
                f"({', '.join(names)}) but the DBC lays out "
                f"({', '.join(self.signal_names)}); update the node or the DBC"
            )
        return self

    def at(self, frame_id: int) -> FrameCodec:
        """This codec with the same layout at identifier ``frame_id`` (a PDO whose COB-ID
        the node's object dictionary sets, e.g. the drive's TPDO1 at node-ID 5, 0x185,
        laid out as ``DRIVE_TPDO1``); itself when the identifier is its own."""
        if frame_id == self.frame_id:
            return self
        other = object.__new__(FrameCodec)
        for slot in FrameCodec.__slots__:
            setattr(other, slot, getattr(self, slot))
        other.frame_id = frame_id
        return other

    def decode_named(self, data: bytes | bytearray) -> dict[str, float]:
        """Unpack a payload into ``{signal name: physical value}`` (tools, tests)."""
        return dict(zip(self.signal_names, self.decode(data), strict=True))

    def encode_named(self, **values: float) -> bytes:
        """Pack ``signal name=physical value`` pairs; every signal must be given."""
        missing = set(self.signal_names) - values.keys()
        extra = values.keys() - set(self.signal_names)
        if missing or extra:
            raise ValueError(
                f"{self.name}: missing signals {sorted(missing)}, unknown {sorted(extra)}"
            )
        return self.encode(*(values[n] for n in self.signal_names))

    def _compile(self) -> None:
        """Generate straight-line encode/decode functions for this layout.

        The generated code only inlines the scale, offset and saturation limits read from
        the DBC above; it is equivalent to the generic loop it replaces (and tested
        against cantools).  ``encode`` first tries one ``pack`` of the converted values
        (``round`` of the scaled value for a scaled integer signal, the value itself for a
        float or unscaled integer signal): for finite, in-range values this gives exactly
        the saturating result, as ``round`` is monotonic and the limits are integers.  A
        value the fast line cannot take (out of range, NaN, infinite, a float for an
        unscaled integer signal) makes ``pack`` or ``round`` raise, and the general
        code below it (NaN check, saturation, ``round``) decides, as it always has.
        """
        names = [f"v{i}" for i in range(len(self._scales))]
        enc = [f"def encode({', '.join(names)}):"]
        dec = [
            "def decode(data):",
            "    if len(data) != length:",
            "        raise ValueError(f'{name}: expected {length} data bytes, got {len(data)}')",
            f"    {', '.join(names)}{',' if len(names) == 1 else ''} = unpack(data)",
        ]
        fast = []
        out = []
        for v, scale, offset, limits in zip(
            names, self._scales, self._offsets, self._int_raw, strict=True
        ):
            trivial = scale == 1.0 and offset == 0.0
            scaled = v
            if not trivial:
                # v - 0.0 == v for every float and int, so a zero offset is left out
                scaled = (
                    f"{v} * {1.0 / scale!r}"
                    if offset == 0.0
                    else (f"({v} - {offset!r}) * {1.0 / scale!r}")
                )
            fast.append(scaled if limits is None or trivial else f"round({scaled})")
            out.append(v if trivial else f"{v} * {scale!r} + {offset!r}")
        enc += [
            "    try:",
            f"        return pack({', '.join(fast)})",
            "    except Exception:",
            "        pass  # out of range, NaN, inf, or a non-integer: the general path",
        ]
        for v, scale, offset, limits in zip(
            names, self._scales, self._offsets, self._int_raw, strict=True
        ):
            if not (scale == 1.0 and offset == 0.0):
                enc.append(f"    {v} = ({v} - {offset!r}) * {1.0 / scale!r}")
            if limits is not None:
                lo, hi = limits
                enc.append(f"    if {v} != {v}: raise ValueError(nan_message)")
                enc.append(
                    f"    {v} = {lo} if {v} <= {lo} else {hi} if {v} >= {hi} else round({v})"
                )
        enc.append(f"    return pack({', '.join(names)})")
        dec.append(f"    return ({', '.join(out)}{',' if len(out) == 1 else ''})")
        namespace = {
            "pack": self._struct.pack,
            "unpack": self._struct.unpack,
            "length": self.length,
            "name": self.name,
            "nan_message": f"{self.name}: cannot encode NaN into an integer signal",
        }
        exec("\n".join(enc) + "\n\n" + "\n".join(dec), namespace)
        #: Pack physical values given in ``signal_names`` order into the payload.
        self.encode: Callable[..., bytes] = namespace["encode"]
        #: Unpack a payload into physical values in ``signal_names`` order (unscaled
        #: integers stay ``int``).
        self.decode: Callable[[bytes | bytearray], tuple[float, ...]] = namespace["decode"]


#: The SYNC's COB-ID in CiA 301's pre-defined connection set (object 0x1005's default).
SYNC_COB_ID = 0x080

#: CiA 301's pre-defined connection set: the function code of RPDO/TPDO 1..4, to which a
#: node's PDO COB-ID adds its node-ID.
PDO_FUNCTION_CODES = {
    ("tpdo", 1): 0x180,
    ("rpdo", 1): 0x200,
    ("tpdo", 2): 0x280,
    ("rpdo", 2): 0x300,
    ("tpdo", 3): 0x380,
    ("rpdo", 3): 0x400,
    ("tpdo", 4): 0x480,
    ("rpdo", 4): 0x500,
}


def predefined_cob_id(kind: str, number: int, node_id: int) -> int:
    """The COB-ID CiA 301's pre-defined connection set gives RPDO/TPDO ``number``
    (1..4) of node ``node_id`` (``kind`` ``"rpdo"`` or ``"tpdo"``)."""
    return PDO_FUNCTION_CODES[(kind, number)] + node_id


#: The ground-truth frames' 29-bit identifiers: ``TRUTH_BASE | joint_index << 4 | k``
#: (``truth.dbc`` holds joint 0's, k = 1..3; :mod:`hdhil.canopen.rigdb` numbers a rig's).
TRUTH_BASE = 0x1F0000
TRUTH_SHIFT = 4
#: Joints whose truth frames fit the scheme (bits 4-15 of the identifier).
MAX_TRUTH_JOINTS = 1 << 12


def truth_frame_id(joint_index: int, template_id: int) -> int:
    """The identifier of ``truth.dbc``'s frame ``template_id`` for a rig's
    ``joint_index``-th joint (0: the frame's own identifier)."""
    if not 0 <= joint_index < MAX_TRUTH_JOINTS:
        raise ValueError(f"joint index must be 0..{MAX_TRUTH_JOINTS - 1}, got {joint_index}")
    if template_id & ~0xF != TRUTH_BASE:
        raise ValueError(f"truth frame 0x{template_id:X} is not in 0x{TRUTH_BASE:X}..+0xF")
    return template_id | joint_index << TRUTH_SHIFT


@cache
def codec(bus: BusName, message_name: str) -> FrameCodec:
    """The compiled codec of ``message_name`` in ``bus``'s DBC."""
    try:
        message = database(bus).get_message_by_name(message_name)
    except KeyError:
        raise ValueError(f"no message {message_name!r} in {bus}.dbc") from None
    return FrameCodec(message, bus)


@cache
def known_frames(
    bus: BusName, drive_node_id: int | None = None, controller_node_id: int | None = None
) -> frozenset[tuple[int, bool]]:
    """``(frame_id, is_extended_id)`` of every message in ``bus``'s DBC; with a drive or
    controller at another node-ID than the DBC's, each of that node's identifiers (base
    + node-ID: PDOs, EMCY, SDO, heartbeat) at its node-ID instead.

    A node ignores known frames that are not addressed to it; anything else is unknown
    and counted in its diagnostics.
    """
    ids = node_ids(bus)
    moved = {
        old: new
        for old, new in (
            (ids.get("DRIVE"), drive_node_id),
            (ids.get("CONTROLLER"), controller_node_id),
        )
        if old is not None and new is not None and new != old
    }
    frames = set()
    for m in database(bus).messages:
        fid = m.frame_id
        node = fid & 0x7F
        if moved and not m.is_extended_frame and fid & ~0x7F and node in moved:
            fid = (fid & ~0x7F) + moved[node]
        frames.add((fid, m.is_extended_frame))
    return frozenset(frames)


def _attribute(obj: object, name: str) -> object:
    dbc = getattr(obj, "dbc", None)
    attributes = getattr(dbc, "attributes", None) or {}
    attribute = attributes.get(name)
    return None if attribute is None else attribute.value


@cache
def node_ids(bus: BusName) -> dict[str, int]:
    """CANopen node-ID of each DBC node that has one (attribute ``NodeId``, 1..127)."""
    ids = {}
    for node in database(bus).nodes:
        value = _attribute(node, "NodeId")
        if isinstance(value, int) and 1 <= value <= 127:
            ids[node.name] = value
    return ids


@cache
def node_function_codes(bus: BusName) -> tuple[int, ...]:
    """COB-ID bases that every CANopen node of ``bus`` transmits with its node-ID added.

    Read from the DBC: a message sent by a node with a ``NodeId`` has the base
    ``frame_id - NodeId``; the bases every such node shares are the function codes of
    the CiA 301 pre-defined connection set in use (EMCY, TPDOs, SDO response,
    heartbeat), while frames only one node sends (SYNC, NMT, its RPDOs, SDO requests)
    are not per-node identifiers.
    """
    ids = node_ids(bus)
    per_node: dict[str, set[int]] = {name: set() for name in ids}
    for message in database(bus).messages:
        if message.is_extended_frame:
            continue
        for sender in message.senders:
            if sender in ids and message.frame_id >= ids[sender]:
                per_node[sender].add(message.frame_id - ids[sender])
    if not per_node:
        return ()
    return tuple(sorted(set.intersection(*per_node.values())))


def frame_id(bus: BusName, message_name: str) -> int:
    return codec(bus, message_name).frame_id


def worst_case_frame_bits(length: int, extended: bool = False) -> int:
    """Worst-case bits on the wire of a classical CAN data frame incl. 3-bit interframe space.

    Base frame: 47 + 8n bits plus at most floor((34 + 8n - 1) / 4) stuff bits (the
    34 stuffable header/CRC bits and 8n data bits); extended frame: 67 + 8n plus
    floor((54 + 8n - 1) / 4).  See docs/design.md, "Frame budget".
    """
    if extended:
        return 67 + 8 * length + (54 + 8 * length - 1) // 4
    return 47 + 8 * length + (34 + 8 * length - 1) // 4

"""Decoding frames with the DBCs.

:class:`FrameDecoder` classifies a :class:`can.Message` (decoded, unknown, malformed,
error or remote frame) and decodes it with cantools into a :class:`DecodedFrame`;
:func:`classify_frame` and :func:`decode_frame` do so with the project's control and
truth DBCs.  Decoding never needs channel numbers: control frames use 11-bit identifiers
and truth frames 29-bit ones, so a frame is looked up by ``(is_extended_id,
arbitration_id)`` across both DBCs (an identifier defined in two is refused).  Channel
numbers, where the format stores them, only label the bus.  :meth:`FrameDecoder.describe`
is ``hdhil dump``'s table line in aligned columns, each value printed exactly to its DBC
resolution; a value in the signal's value table as its name and number, as cantools
decodes it with ``decode_choices=True`` (``nmt_state=operational(5)``); bit-field words,
object indices and EMCY codes in hex (``statusword=0x0270``, ``sdo_index=0x6041``).
Decoded values themselves stay numbers (CSV, statistics, analysis).
"""

from __future__ import annotations

import enum
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import can

if TYPE_CHECKING:
    from cantools.database.can import Database
    from cantools.database.can import Message as DbcMessage

from hdhil.dbc import CHANNEL_NUMBER, database

#: Bus label per python-can channel number (inverse of :data:`hdhil.dbc.CHANNEL_NUMBER`).
BUS_OF_CHANNEL: dict[int, str] = {number: name for name, number in CHANNEL_NUMBER.items()}

#: Width of the table's time column (seconds with 6 decimals) and bus column.
TIME_WIDTH = 12
BUS_WIDTH = 7

#: Bus label of a frame with neither channel information nor a known identifier.
UNKNOWN_BUS = "?"


class FrameKind(enum.Enum):
    """What a frame turned out to be."""

    DECODED = "decoded"  #: known identifier, right length, decoded
    UNKNOWN = "unknown"  #: identifier in neither DBC
    MALFORMED = "malformed"  #: known identifier, payload length differs from the DBC
    ERROR = "error"  #: error frame
    REMOTE = "remote"  #: remote frame

    __hash__ = object.__hash__  # members are singletons; Enum's hash is slow Python code


@dataclass(frozen=True, slots=True)
class DecodedFrame:
    """One frame, classified and (if ``kind`` is DECODED) decoded to physical values.

    ``bus`` is the label used for grouping: from the channel when the trace has one
    (``control``/``truth``, ``chN`` for other numbers), else from the DBC that defines
    the identifier, else ``"?"``.  ``message_bus`` is the DBC the identifier belongs to
    (``None`` if unknown); a frame whose channel disagrees is ``on_wrong_bus``.
    """

    time: float
    bus: str
    arbitration_id: int
    is_extended_id: bool
    kind: FrameKind
    data: bytes
    message: str | None = None
    message_bus: str | None = None
    signals: dict[str, float | int] = field(default_factory=dict)
    definition: DbcMessage | None = field(default=None, repr=False, compare=False)

    @property
    def id_text(self) -> str:
        """Identifier as hex: 3 digits for base frames, 8 for extended ones."""
        return format_id(self.arbitration_id, self.is_extended_id)

    @property
    def on_wrong_bus(self) -> bool:
        return (
            self.message_bus is not None
            and self.bus in CHANNEL_NUMBER
            and self.bus != self.message_bus
        )


#: A value-table name printed without quotes.
_BARE_NAME = re.compile(r"[\w.+-]+", re.A)


def format_id(arbitration_id: int, extended: bool) -> str:
    return f"{arbitration_id:08X}" if extended else f"{arbitration_id:03X}"


def _decimals(value: float) -> int:
    """Decimal places needed to print multiples of ``value`` exactly (at most 9)."""
    for digits in range(10):
        scaled = abs(value) * 10**digits
        if abs(scaled - round(scaled)) < 1e-9 * max(1.0, scaled):
            return digits
    return 9


@dataclass(frozen=True)
class _SignalFormat:
    name: str
    column: str  # "Message.Signal"
    unit: str
    decimals: int | None  # None: IEEE float signal
    is_float32: bool
    unit_suffix: str  # " Nm", or "" without a unit
    choices: dict[int, str] = field(default_factory=dict)  # raw value -> value-table name
    hex_digits: int = 0  # > 0: printed in hex with this many digits
    scale: float = 1.0
    offset: float = 0.0

    def number(self, value: float | int) -> str:
        """The number alone: hex words and indices, resolution-exact scaled integers, 6
        significant digits for floats."""
        if self.hex_digits:
            return f"0x{round(value):0{self.hex_digits}X}"
        return self._decimal(value)

    def _decimal(self, value: float | int) -> str:
        if self.decimals is None:
            return f"{value:.6g}"
        if self.decimals == 0:
            return str(round(value))
        return f"{value:.{self.decimals}f}"

    def text(self, value: float | int) -> str:
        """Table text: the number, or ``name(number)`` for a value in the value table
        (the name quoted when it has spaces)."""
        number = self.number(value)
        if self.choices:
            name = self.choices.get(round((value - self.offset) / self.scale))
            if name is not None:
                if not _BARE_NAME.fullmatch(name):
                    name = '"' + name.replace('"', "'") + '"'
                return f"{name}({number})"
        return number

    def csv(self, value: float | int) -> str:
        """CSV text: exact (shortest round-trip repr for IEEE floats)."""
        if self.decimals is None:
            if self.is_float32:  # the shortest text that reads back as the same float32
                import numpy as np

                return str(np.float32(value))
            return repr(float(value))
        return self._decimal(value)


def _hex_digits(name: str, length: int, signed: bool, decimals: int | None) -> int:
    """Hex digits of a signal printed in hex: an unsigned integer bit-field word
    (``*word``), object index (``*index*``) or EMCY error code; 0 for every other."""
    if signed or decimals != 0:
        return 0
    lower = name.lower()
    if lower.endswith("word") or "index" in lower or lower.endswith("error_code"):
        return max(1, -(-length // 4))
    return 0


def _signal_formats(message: DbcMessage) -> tuple[_SignalFormat, ...]:
    formats = []
    for sig in message.signals:
        if sig.is_float:
            decimals = None
        else:
            decimals = max(_decimals(float(sig.scale)), _decimals(float(sig.offset)))
        unit_scale = float(sig.scale) == 1.0 and float(sig.offset) == 0.0
        formats.append(
            _SignalFormat(
                name=sig.name,
                column=f"{message.name}.{sig.name}",
                unit=sig.unit or "",
                decimals=decimals,
                is_float32=sig.is_float and sig.length == 32,
                unit_suffix=f" {sig.unit}" if sig.unit else "",
                choices={int(k): str(v) for k, v in (sig.choices or {}).items()},
                hex_digits=_hex_digits(sig.name, sig.length, sig.is_signed, decimals)
                if unit_scale
                else 0,
                scale=float(sig.scale),
                offset=float(sig.offset),
            )
        )
    return tuple(formats)


class FrameDecoder:
    """Classifies and decodes frames against a set of DBCs (default: control and truth).

    The lookup ``(is_extended_id, arbitration_id) -> (bus, message)`` is built once; an
    identifier defined in two DBCs is refused.
    """

    def __init__(self, databases: Mapping[str, Database] | None = None) -> None:
        if databases is None:
            databases = {bus: database(bus) for bus in CHANNEL_NUMBER}
        self.databases = dict(databases)
        self.lookup: dict[tuple[bool, int], tuple[str, DbcMessage]] = {}
        self.formats: dict[str, tuple[_SignalFormat, ...]] = {}
        for bus, db in self.databases.items():
            for message in db.messages:
                key = (bool(message.is_extended_frame), int(message.frame_id))
                if key in self.lookup:
                    other = self.lookup[key]
                    raise ValueError(
                        f"identifier {format_id(key[1], key[0])} is defined twice: "
                        f"{other[0]}.{other[1].name} and {bus}.{message.name}"
                    )
                self.lookup[key] = (bus, message)
                self.formats[message.name] = _signal_formats(message)
        self.by_name: dict[str, tuple[str, DbcMessage]] = {
            m.name: (bus, m) for bus, m in self.lookup.values()
        }
        #: Width of the table's message column: every name (and ``ERROR FRAME``) fits.
        self.name_width = max([len("ERROR FRAME"), *map(len, self.by_name)])

    def header(self, time_width: int = TIME_WIDTH, time_label: str = "time/s") -> str:
        """The first line of the table :meth:`describe` writes."""
        return (
            f"{time_label:>{time_width}}  {'bus':<{BUS_WIDTH}}  {'id':<8}  "
            f"{'message':<{self.name_width}}  signals"
        )

    def columns(self, messages: Iterable[str] | None = None) -> list[str]:
        """``Message.Signal`` column names in DBC order (optionally only ``messages``)."""
        wanted = None if messages is None else set(messages)
        return [
            fmt.column
            for name, formats in self.formats.items()
            if wanted is None or name in wanted
            for fmt in formats
        ]

    def classify(self, msg: can.Message, decode: bool = True) -> DecodedFrame:
        """Classify ``msg`` and, if ``decode`` and it is a well-formed known frame, decode it."""
        ext = bool(msg.is_extended_id)
        arb = int(msg.arbitration_id)
        data = bytes(msg.data or b"")
        entry = None if msg.is_error_frame else self.lookup.get((ext, arb))
        message_bus, definition = entry if entry is not None else (None, None)
        channel = msg.channel
        if isinstance(channel, int):
            bus = BUS_OF_CHANNEL.get(channel, f"ch{channel}")
        else:
            bus = message_bus or UNKNOWN_BUS
        if msg.is_error_frame:
            kind = FrameKind.ERROR
        elif msg.is_remote_frame:
            kind = FrameKind.REMOTE
        elif definition is None:
            kind = FrameKind.UNKNOWN
        elif len(data) != definition.length:
            kind = FrameKind.MALFORMED
        else:
            kind = FrameKind.DECODED
        signals: dict[str, float | int] = {}
        if kind is FrameKind.DECODED and decode:
            try:
                signals = dict(definition.decode(data, decode_choices=False))  # type: ignore[union-attr, arg-type]
            except Exception:
                kind = FrameKind.MALFORMED
        return DecodedFrame(
            time=float(msg.timestamp),
            bus=bus,
            arbitration_id=arb,
            is_extended_id=ext,
            kind=kind,
            data=data,
            message=definition.name if definition is not None else None,
            message_bus=message_bus,
            signals=signals,
            definition=definition,
        )

    def decode(self, msg: can.Message) -> DecodedFrame | None:
        """The decoded frame, or ``None`` if ``msg`` is not a well-formed known data frame."""
        frame = self.classify(msg)
        return frame if frame.kind is FrameKind.DECODED else None

    def describe(self, frame: DecodedFrame, time_text: str | None = None) -> str:
        """The table line of ``frame``: time (``time_text``, else the frame's own time),
        bus, ID, name, signals (or raw data and a flag), in columns of fixed width."""
        name = frame.message or ""
        kind = frame.kind
        if kind is FrameKind.DECODED:
            signals = frame.signals
            body = "  ".join(
                f"{fmt.name}={fmt.text(signals[fmt.name])}{fmt.unit_suffix}"
                for fmt in self.formats[name]
                if fmt.name in signals
            )
        else:
            raw = frame.data.hex(" ").upper()
            if kind is FrameKind.UNKNOWN:
                name, body = "UNKNOWN", f"[{len(frame.data)}] {raw}"
            elif kind is FrameKind.MALFORMED:
                expected = frame.definition.length if frame.definition is not None else "?"
                body = f"MALFORMED: {len(frame.data)} bytes, DBC says {expected}: {raw}"
            elif kind is FrameKind.ERROR:
                name, body = "ERROR FRAME", raw
            else:
                body = "REMOTE frame request"
        if frame.on_wrong_bus:
            body += f"  (WRONG BUS: defined in {frame.message_bus}.dbc)"
        id_text = "-" if kind is FrameKind.ERROR else frame.id_text
        if time_text is None:
            time_text = f"{frame.time:{TIME_WIDTH}.6f}"
        return (
            f"{time_text}  {frame.bus:<{BUS_WIDTH}.{BUS_WIDTH}}  {id_text:<8}  "
            f"{name:<{self.name_width}}  {body}"
        ).rstrip()


_DEFAULT_DECODER: FrameDecoder | None = None


class ChannelDecoder(FrameDecoder):
    """A decoder for a trace whose channels carry databases that share identifiers (the
    buses of a rig of several joints: each numbers its nodes alike): ``channels`` maps a
    channel number to its bus name and database.  A frame is decoded with its channel's
    database and labelled with that bus's name; a frame of another channel with the
    first definition of its identifier.  ``lookup`` and ``by_name`` hold every bus's
    messages (the first definition of a shared identifier) for ``--id`` and columns."""

    def __init__(self, channels: Mapping[int, tuple[str, Database]]) -> None:
        self._by_channel = {ch: FrameDecoder({name: db}) for ch, (name, db) in channels.items()}
        self._bus_name = {ch: name for ch, (name, _) in channels.items()}
        self.databases = {name: db for name, db in channels.values()}
        self.lookup = {}
        self.formats = {}
        self.by_name = {}
        for decoder in self._by_channel.values():
            for key, entry in decoder.lookup.items():
                self.lookup.setdefault(key, entry)
            for name, formats in decoder.formats.items():
                self.formats.setdefault(name, formats)
            for name, entry in decoder.by_name.items():
                self.by_name.setdefault(name, entry)
        self.name_width = max([len("ERROR FRAME"), *map(len, self.by_name)])

    def classify(self, msg: can.Message, decode: bool = True) -> DecodedFrame:
        decoder = self._by_channel.get(msg.channel)  # type: ignore[arg-type]
        if decoder is None:
            return super().classify(msg, decode)
        frame = decoder.classify(msg, decode)
        return replace(frame, bus=self._bus_name[msg.channel])  # type: ignore[index]


def default_decoder() -> FrameDecoder:
    """The shared decoder for the project's control and truth DBCs."""
    global _DEFAULT_DECODER
    if _DEFAULT_DECODER is None:
        _DEFAULT_DECODER = FrameDecoder()
    return _DEFAULT_DECODER


def classify_frame(msg: can.Message, decode: bool = True) -> DecodedFrame:
    """Classify (and decode) ``msg`` with the project DBCs; see :meth:`FrameDecoder.classify`."""
    return default_decoder().classify(msg, decode)


def decode_frame(msg: can.Message) -> DecodedFrame | None:
    """Decode ``msg`` with the project DBCs; ``None`` unless it is a well-formed known frame."""
    return default_decoder().decode(msg)

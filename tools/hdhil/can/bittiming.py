"""Exact bit counts of classical and CAN FD frames: CRC, bit stuffing (ISO 11898-1).

The time a frame occupies the wire depends on its content: the stuffing rule inserts a
complementary bit after five identical bits from the start-of-frame to the end of the
CRC sequence.  docs/design.md's budget uses the worst case (``hdhil.dbc.worst_case_frame_bits``);
this module gives the real number for one frame, so a simulated bus can time frames the
way a 1 Mbit/s wire does and a trace's actual bus load can be measured.

Layout counted (base frame): SOF, 11-bit identifier, RTR, IDE, r0, 4-bit DLC, data,
15-bit CRC (all stuffed), then CRC delimiter, ACK slot, ACK delimiter, 7-bit EOF and the
3-bit intermission (not stuffed): 47 + 8n bits before stuffing.  Extended frames insert
SRR, IDE = 1 and the 18-bit identifier extension and carry r1, r0: 67 + 8n bits.

Stuffing is counted with a table over bytes: for each byte and each state (value of the
last bit, length of its run) the number of stuff bits and the new state; the CRC of the
data with a table per byte position (the CRC is linear in the bits).  Both are tested
against a plain bit-by-bit implementation.

CAN FD frames (ISO 11898-1:2015; the layout at the section below) are counted by phase,
nominal and data bit rate (:func:`fd_frame_bits`, :func:`fd_bitstream`), with
worst-case bounds per payload length (:func:`worst_case_fd_frame_bits`);
:func:`frame_seconds` times any python-can message.  docs/schedule.md has the formulas.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import can

_CRC15_POLY = 0x4599


def _crc15_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 7
        for _ in range(8):
            crc = (crc << 1) ^ _CRC15_POLY if crc & 0x4000 else crc << 1
            crc &= 0x7FFF
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _crc15_table()


def crc15_bits(value: int, nbits: int, crc: int = 0) -> int:
    """CRC-15/CAN of the ``nbits`` lowest bits of ``value``, most significant first."""
    for i in range(nbits - 1, -1, -1):
        bit = (value >> i) & 1
        feedback = bit ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= _CRC15_POLY
    return crc


def _stuff_step(state: tuple[int, int], bit: int) -> tuple[tuple[int, int], int]:
    last, run = state
    if bit == last:
        run += 1
    else:
        last, run = bit, 1
    if run == 5:  # insert the complement; it starts a run of its own
        return (1 - last, 1), 1
    return (last, run), 0


def _state_index(state: tuple[int, int]) -> int:
    """A stuffing state as a small int: last bit x 4 + (run - 1), 0..7."""
    last, run = state
    return last * 4 + run - 1


def _stuff_table(nbits: int) -> tuple[int, ...]:
    """For every state and every ``nbits``-bit chunk (most significant bit first), the
    stuff bits it adds and the state after it, packed as ``added << 3 | state`` at index
    ``state << nbits | chunk``: one list lookup per chunk on the hot path.

    Chunks wider than 4 bits are their leading bits, then their last 4 (the tables of
    both composed): built at import, so kept cheap."""
    if nbits > 4:
        head, tail = _stuff_table(nbits - 4), _stuff_table(4)
        table = []
        for index in range(8):
            for chunk in range(1 << nbits):
                a = head[index << (nbits - 4) | chunk >> 4]
                b = tail[(a & 7) << 4 | chunk & 0xF]
                table.append(((a >> 3) + (b >> 3)) << 3 | b & 7)
        return tuple(table)
    table = []
    for index in range(8):
        for chunk in range(1 << nbits):
            state, added = (index >> 2, (index & 3) + 1), 0
            for i in range(nbits - 1, -1, -1):
                state, s = _stuff_step(state, (chunk >> i) & 1)
                added += s
            table.append(added << 3 | _state_index(state))
    return tuple(table)


#: Stuffing over a byte, and over the last 7 bits of the CRC sequence.
_STUFF = _stuff_table(8)
_STUFF7 = _stuff_table(7)


def _zero_bytes(crc: int, count: int) -> int:
    """The CRC register after ``count`` more zero bytes."""
    for _ in range(count):
        crc = ((crc << 8) & 0x7FFF) ^ _CRC_TABLE[(crc >> 7) & 0xFF]
    return crc


#: The CRC is linear: over header and n data bytes it is the header's CRC carried
#: through n zero bytes, XOR for each data byte its CRC carried through the bytes after
#: it.  ``_CRC_AT[n][i][b]``: the part of data byte ``i`` (of ``n``) with value ``b``.
def _crc_at() -> tuple[tuple[tuple[int, ...], ...], ...]:
    carried = [_CRC_TABLE]  # [k][b]: byte b followed by k zero bytes
    for _ in range(7):
        carried.append(tuple(_zero_bytes(crc, 1) for crc in carried[-1]))
    return tuple(tuple(carried[n - 1 - i] for i in range(n)) for n in range(9))


_CRC_AT = _crc_at()


@lru_cache(maxsize=4096)
def _header(
    arbitration_id: int, extended: bool, remote: bool, dlc: int, carried: int = 0
) -> tuple[int, int, int, int]:
    """(bits, CRC after the header carried through ``carried`` zero bytes, stuffing state
    index after the header, stuff bits so far)."""
    if extended:
        base, ext = arbitration_id >> 18, arbitration_id & 0x3FFFF
        # SOF, base id, SRR=1, IDE=1, ext id, RTR, r1=0, r0=0, DLC
        header = (((((0 << 11 | base) << 2 | 0b11) << 18 | ext) << 3 | (int(remote) << 2)) << 4
                  | dlc)  # fmt: skip
        nbits = 1 + 11 + 2 + 18 + 3 + 4
    else:
        # SOF, id, RTR, IDE=0, r0=0, DLC
        header = ((arbitration_id << 3 | int(remote) << 2) << 4) | dlc
        nbits = 1 + 11 + 3 + 4
    state = (0, 1)  # SOF: a dominant 0 opens a run of 1
    added = 0
    for i in range(nbits - 2, -1, -1):
        state, s = _stuff_step(state, (header >> i) & 1)
        added += s
    return nbits, _zero_bytes(crc15_bits(header, nbits), carried), _state_index(state), added


#: :data:`_STUFF` for the hot loop: at the same index, ``added << 16 | state << 8``, so
#: one entry masked with 0x700 is the next index's state part, and the entries of a frame
#: summed carry the stuff bits in their high part (fewer than 36 entries: no carry over).
_STUFF_SUM = tuple((v >> 3) << 16 | (v & 7) << 8 for v in _STUFF)
_CRC8 = _CRC_AT[8]


@lru_cache(maxsize=8192)
def frame_bits(arbitration_id: int, extended: bool, remote: bool, data: bytes) -> int:
    """Exact bits on the wire of one classical data or remote frame, incl. 3-bit IFS."""
    stuff = _STUFF_SUM
    if len(data) == 8 and not remote:
        # The 1 kHz PDOs carry 8 bytes and change every cycle (a miss of the cache): the
        # loop below written out for them, a third cheaper.
        nbits, crc, state, added = _header(arbitration_id, extended, False, 8, 8)
        b0, b1, b2, b3, b4, b5, b6, b7 = data
        c0, c1, c2, c3, c4, c5, c6, c7 = _CRC8
        crc ^= c0[b0] ^ c1[b1] ^ c2[b2] ^ c3[b3] ^ c4[b4] ^ c5[b5] ^ c6[b6] ^ c7[b7]
        step = total = stuff[state << 8 | b0]
        step = stuff[step & 0x700 | b1]
        total += step
        step = stuff[step & 0x700 | b2]
        total += step
        step = stuff[step & 0x700 | b3]
        total += step
        step = stuff[step & 0x700 | b4]
        total += step
        step = stuff[step & 0x700 | b5]
        total += step
        step = stuff[step & 0x700 | b6]
        total += step
        step = stuff[step & 0x700 | b7]
        total += step
        n = 8
    else:
        payload = b"" if remote else data
        n = len(payload)
        step, total = 0, 0
        if n <= 8:  # the CRC of each byte by its position (_CRC_AT): a lookup per byte
            nbits, crc, state, added = _header(arbitration_id, extended, remote,
                                               min(len(data), 8), n)  # fmt: skip
            step = state << 8
            for byte, crc_of in zip(payload, _CRC_AT[n]):  # noqa: B905 (same length)
                step = stuff[step & 0x700 | byte]
                total += step
                crc ^= crc_of[byte]
        else:  # longer than a classical frame: the register byte by byte
            nbits, crc, state, added = _header(arbitration_id, extended, remote, 8)
            step = state << 8
            crc_table = _CRC_TABLE
            for byte in payload:
                step = stuff[step & 0x700 | byte]
                added += step >> 16  # any length: no sum that could carry over
                crc = ((crc << 8) & 0x7FFF) ^ crc_table[((crc >> 7) ^ byte) & 0xFF]
    step = stuff[step & 0x700 | crc >> 7]  # CRC bits 14..7
    total += step
    added += (total >> 16) + (_STUFF7[(step & 0x700) >> 1 | crc & 0x7F] >> 3)  # bits 6..0
    return nbits + 8 * n + 15 + added + 13


# --- CAN FD (ISO 11898-1:2015) ---------------------------------------------------------
#
# Layout of an FD data frame (FBFF; the extended FEFF inserts SRR = 1, IDE = 1 and the
# 18-bit identifier extension after the base identifier and moves RRS behind it):
#
#   SOF, 11-bit identifier, RRS = 0, IDE = 0, FDF = 1, res = 0, BRS, ESI, 4-bit DLC, data
#       dynamically stuffed (a complement after five equal bits), from SOF to the last
#       data bit;
#   stuff count (the dynamic stuff bits modulo 8, Gray-coded, and an even parity bit)
#   and the CRC sequence (CRC-17 up to 16 data bytes, CRC-21 above), with a fixed stuff
#   bit (the complement of the bit before it) ahead of the stuff count and after every
#   fourth bit of the two: 6 fixed stuff bits with CRC-17, 7 with CRC-21;
#   CRC delimiter, ACK slot, ACK delimiter, 7-bit EOF, 3-bit intermission (unstuffed).
#
# Exactly one bit separates the last data bit from the stuff count: the first fixed
# stuff bit.  When the last five data bits are equal no dynamic stuff bit is added on top
# (controllers differ only in calling that one bit dynamic or fixed, which changes the
# stuff count's value and the CRC, never the length).  The CRC covers SOF to the end of
# the data field with its dynamic stuff bits, then the stuff count, from the initial
# value 1 followed by zeros; the fixed stuff bits are not in it.
#
# With BRS = 1 the bits after the BRS bit up to the last bit of the CRC sequence go at
# the data bit rate.  The switch happens at the sample points of BRS and of the CRC
# delimiter; both bits are counted here as whole arbitration-phase bits, which
# overestimates the frame's time by less than two nominal bits.

#: The payload lengths an FD frame can carry, indexed by DLC.
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)

_CRC17_POLY = 0x1685B  # x^17+x^16+x^14+x^13+x^11+x^6+x^4+x^3+x+1
_CRC21_POLY = 0x102899  # x^21+x^20+x^13+x^11+x^7+x^4+x^3+1
#: The stuff count's four bits for (count mod 8): its 3-bit Gray code, then even parity.
_STUFF_COUNT_CODE = (0b0000, 0b0011, 0b0110, 0b0101, 0b1100, 0b1111, 0b1010, 0b1001)
#: Bits after the CRC sequence: CRC delimiter, ACK slot, ACK delimiter, EOF, intermission.
_FD_TAIL = 1 + 1 + 1 + 7 + 3


def fd_length(length: int) -> int:
    """The FD payload length that carries ``length`` bytes: ``length`` itself if it is
    one of :data:`FD_LENGTHS`, else the next one (the frame is padded up to it)."""
    if not 0 <= length <= 64:
        raise ValueError(f"an FD frame carries 0 to 64 bytes, not {length}")
    return next(n for n in FD_LENGTHS if n >= length)


def fd_dlc(length: int) -> int:
    """The DLC of an FD frame carrying ``length`` bytes (padded, see :func:`fd_length`)."""
    return FD_LENGTHS.index(fd_length(length))


def _crc_bits(value: int, nbits: int, crc: int, poly: int, width: int) -> int:
    top, mask = width - 1, (1 << width) - 1
    for i in range(nbits - 1, -1, -1):
        feedback = ((value >> i) & 1) ^ ((crc >> top) & 1)
        crc = (crc << 1) & mask
        if feedback:
            crc ^= poly & mask
    return crc


def crc17_bits(value: int, nbits: int, crc: int = 0) -> int:
    """CRC-17/CAN-FD of the ``nbits`` lowest bits of ``value``, most significant first,
    from register ``crc`` (a frame starts from ``1 << 16``)."""
    return _crc_bits(value, nbits, crc, _CRC17_POLY, 17)


def crc21_bits(value: int, nbits: int, crc: int = 0) -> int:
    """CRC-21/CAN-FD of the ``nbits`` lowest bits of ``value``, most significant first,
    from register ``crc`` (a frame starts from ``1 << 20``)."""
    return _crc_bits(value, nbits, crc, _CRC21_POLY, 21)


def _fd_crc_field(length: int) -> int:
    """Bits of the stuff count and CRC sequence with their fixed stuff bits."""
    return 4 + 17 + 6 if length <= 16 else 4 + 21 + 7


def _fd_head(
    arbitration_id: int, extended: bool, brs: bool, esi: bool, dlc: int
) -> list[tuple[str, int]]:
    """The unstuffed fields from SOF to the DLC, one (field, bit) per bit."""
    bits: list[tuple[str, int]] = [("SOF", 0)]

    def put(name: str, value: int, nbits: int) -> None:
        bits.extend((name, (value >> i) & 1) for i in range(nbits - 1, -1, -1))

    if extended:
        put("ID", arbitration_id >> 18, 11)
        put("SRR", 1, 1)
        put("IDE", 1, 1)
        put("ID", arbitration_id & 0x3FFFF, 18)
        put("RRS", 0, 1)
    else:
        put("ID", arbitration_id, 11)
        put("RRS", 0, 1)
        put("IDE", 0, 1)
    put("FDF", 1, 1)
    put("res", 0, 1)
    put("BRS", int(brs), 1)
    put("ESI", int(esi), 1)
    put("DLC", dlc, 4)
    return bits


def _check_id(arbitration_id: int, extended: bool) -> None:
    if not 0 <= arbitration_id < (1 << (29 if extended else 11)):
        kind = "extended" if extended else "base"
        raise ValueError(f"{arbitration_id:#x} is not a {kind} CAN identifier")


def fd_bitstream(
    arbitration_id: int,
    extended: bool,
    data: bytes,
    *,
    brs: bool = True,
    esi: bool = False,
    padding: int = 0,
) -> tuple[tuple[str, int], ...]:
    """Every bit of one FD data frame on the wire, as (field, bit) pairs, IFS included.

    Fields: SOF, ID, SRR, IDE, RRS, FDF, res, BRS, ESI, DLC, D (data), S (dynamic stuff
    bit), FSB (fixed stuff bit), SC (stuff count), P (its parity), CRC, CRC_DEL, ACK,
    ACK_DEL, EOF, IFS.  A payload whose length is not one of :data:`FD_LENGTHS` is
    padded with ``padding`` bytes up to the next one, as a CAN FD controller does.
    Written for clarity (tests, figures); :func:`fd_frame_bits` counts the same bits
    fast."""
    _check_id(arbitration_id, extended)
    length = fd_length(len(data))
    payload = bytes(data) + bytes([padding]) * (length - len(data))
    head = _fd_head(arbitration_id, extended, brs, esi, FD_LENGTHS.index(length))
    head += [("D", (byte >> i) & 1) for byte in payload for i in range(7, -1, -1)]
    out: list[tuple[str, int]] = []
    last, run, stuffed = -1, 0, 0
    for index, (name, bit) in enumerate(head):
        out.append((name, bit))
        run = run + 1 if bit == last else 1
        last = bit
        if run == 5 and index < len(head) - 1:  # none after the last data bit
            out.append(("S", 1 - bit))
            stuffed += 1
            last, run = 1 - bit, 1
    code = _STUFF_COUNT_CODE[stuffed % 8]
    width = 17 if length <= 16 else 21
    crc = 1 << (width - 1)
    for _name, bit in out:
        crc = _crc_bits(bit, 1, crc, _CRC17_POLY if width == 17 else _CRC21_POLY, width)
    crc = _crc_bits(code, 4, crc, _CRC17_POLY if width == 17 else _CRC21_POLY, width)
    sequence = [("SC", (code >> i) & 1) for i in (3, 2, 1)] + [("P", code & 1)]
    sequence += [("CRC", (crc >> i) & 1) for i in range(width - 1, -1, -1)]
    out.append(("FSB", 1 - out[-1][1]))
    for index, (name, bit) in enumerate(sequence, 1):
        out.append((name, bit))
        if index % 4 == 0 and index < len(sequence):
            out.append(("FSB", 1 - bit))
    out += [("CRC_DEL", 1), ("ACK", 0), ("ACK_DEL", 1)]
    out += [("EOF", 1)] * 7 + [("IFS", 1)] * 3
    return tuple(out)


@dataclass(frozen=True)
class FdBits:
    """The bits of an FD frame by phase: ``arbitration`` at the nominal bit rate (SOF to
    BRS, CRC delimiter to the end of the intermission; every bit without BRS), ``data``
    at the data bit rate (after BRS to the end of the CRC sequence, only with BRS)."""

    arbitration: int
    data: int

    @property
    def total(self) -> int:
        return self.arbitration + self.data

    def seconds(self, nominal_bitrate: float, data_bitrate: float) -> float:
        """The time on the wire at these bit rates."""
        if nominal_bitrate <= 0 or data_bitrate <= 0:
            raise ValueError("bit rates must be > 0")
        return self.arbitration / nominal_bitrate + self.data / data_bitrate


def fd_phases(stream: tuple[tuple[str, int], ...]) -> FdBits:
    """Split a :func:`fd_bitstream` into its phases."""
    brs_at = next(i for i, (name, _bit) in enumerate(stream) if name == "BRS")
    del_at = next(i for i, (name, _bit) in enumerate(stream) if name == "CRC_DEL")
    if not stream[brs_at][1]:
        return FdBits(len(stream), 0)
    data = del_at - brs_at - 1
    return FdBits(len(stream) - data, data)


@lru_cache(maxsize=4096)
def _fd_header(
    arbitration_id: int, extended: bool, brs: bool, esi: bool, dlc: int
) -> tuple[int, int, int]:
    """(bits from SOF to BRS, bits from ESI to the DLC, both with their dynamic stuff
    bits; stuffing state index after the DLC).  A stuff bit right after BRS goes at the
    data bit rate and is counted with the second part."""
    head = _fd_head(arbitration_id, extended, brs, esi, dlc)
    state = (0, 1)  # after SOF
    arbitration, control = 1, 0
    last = len(head) - 1
    for index in range(1, len(head)):
        name, bit = head[index]
        state, stuff = _stuff_step(state, bit)
        if stuff and index == last and dlc == 0:  # the DLC is the last stuffed bit
            stuff = 0
            state = (bit, 5)
        count = 1 + stuff
        if name == "BRS":
            arbitration += 1
            control += stuff
        elif name in ("ESI", "DLC"):
            control += count
        else:
            arbitration += count
    return arbitration, control, _state_index(state) if state[1] < 5 else -1


def _fd_phases(arbitration: int, in_data: int, brs: bool) -> FdBits:
    """An FD frame's bits by phase: with bit-rate switching, the bits from BRS to the CRC
    delimiter at the data bit rate, the rest (and the tail) at the nominal one."""
    if brs:
        return FdBits(arbitration + _FD_TAIL, in_data)
    return FdBits(arbitration + in_data + _FD_TAIL, 0)


def fd_frame_bits(
    arbitration_id: int,
    extended: bool,
    data: bytes,
    *,
    brs: bool = True,
    esi: bool = False,
    padding: int = 0,
) -> FdBits:
    """Exact bits on the wire of one FD data frame by phase, incl. the 3-bit IFS.  A
    payload whose length is not one of :data:`FD_LENGTHS` is padded with ``padding``
    bytes up to the next one (:func:`fd_length`)."""
    _check_id(arbitration_id, extended)
    n = fd_length(len(data))
    if n != len(data):
        data = bytes(data) + bytes([padding]) * (n - len(data))
    arbitration, control, state = _fd_header(
        arbitration_id, extended, brs, esi, FD_LENGTHS.index(n)
    )
    added = 0
    if n:
        step = state << 8
        stuff = _STUFF_SUM
        for byte in data[:-1]:
            step = stuff[step & 0x700 | byte]
            added += step >> 16
        # The last byte's first 7 bits may add stuff bits; its 8th never does.
        added += _STUFF7[(step & 0x700) >> 1 | data[-1] >> 1] >> 3
    in_data = control + 8 * n + added + _fd_crc_field(n)
    return _fd_phases(arbitration, in_data, brs)


def fd_frame_seconds(
    arbitration_id: int,
    extended: bool,
    data: bytes,
    nominal_bitrate: float,
    data_bitrate: float,
    *,
    brs: bool = True,
    esi: bool = False,
) -> float:
    """Exact time on the wire of one FD data frame at these bit rates, IFS included."""
    bits = fd_frame_bits(arbitration_id, extended, data, brs=brs, esi=esi)
    return bits.seconds(nominal_bitrate, data_bitrate)


def _most_stuff_bits(free: int, run: int) -> int:
    """The most stuff bits ``free`` unknown bits can add after a run of ``run`` equal
    bits: the first after 5 - run of them, then one after every 4 more."""
    first = 5 - run
    return 0 if free < first else (free - first) // 4 + 1


def worst_case_fd_frame_bits(
    length: int,
    extended: bool = False,
    *,
    brs: bool = True,
    arbitration_id: int | None = None,
) -> FdBits:
    """An upper bound of an FD frame's bits by phase over every payload (and CRC) of
    ``length`` bytes (padded to :func:`fd_length`), IFS included.

    Without ``arbitration_id``: the bound for any identifier: the dynamically stuffed
    bits from SOF to the last data bit (22 + 8n base, 41 + 8n extended) get at most
    floor((bits - 2) / 4) stuff bits (one after the fifth bit, then one after every
    fourth, none after the last), as many as can of them in the arbitration phase (at
    most floor((A - 2) / 4) of its A bits up to BRS: 17 base, 36 extended), the slower
    one.  With it: the header up to the DLC is known and stuffed exactly, the data bits
    get the most stuff bits they can after it (over both ESI values).  The CRC field's
    length is fixed.  The exact count of any frame never exceeds either bound."""
    n = fd_length(length)
    dlc = FD_LENGTHS.index(n)
    if arbitration_id is None:
        head = 36 if extended else 17  # SOF .. BRS
        stuffed = head + 5 + 8 * n  # .. the last data bit
        total = (stuffed - 2) // 4
        early = min((head - 2) // 4, total)
        arbitration, control = head + early, 5 + total - early
        in_data = control + 8 * n + _fd_crc_field(n)
    else:
        _check_id(arbitration_id, extended)
        worst: tuple[int, int] | None = None
        for esi in (False, True):
            arbitration, control, state = _fd_header(arbitration_id, extended, brs, esi, dlc)
            extra = 0
            if n:
                run = (state & 3) + 1
                extra = _most_stuff_bits(8 * n - 1, run)  # none after the last bit
            candidate = (arbitration, control + extra)
            if worst is None or candidate > worst:
                worst = candidate
        assert worst is not None
        arbitration, control = worst
        in_data = control + 8 * n + _fd_crc_field(n)
    return _fd_phases(arbitration, in_data, brs)


def worst_case_fd_frame_seconds(
    length: int,
    nominal_bitrate: float,
    data_bitrate: float,
    extended: bool = False,
    *,
    brs: bool = True,
    arbitration_id: int | None = None,
) -> float:
    """The longest time an FD frame of ``length`` bytes can take at these bit rates
    (:func:`worst_case_fd_frame_bits`)."""
    bits = worst_case_fd_frame_bits(length, extended, brs=brs, arbitration_id=arbitration_id)
    return bits.seconds(nominal_bitrate, data_bitrate)


def worst_case_frame_bits_for(arbitration_id: int, extended: bool, length: int) -> int:
    """An upper bound of a classical data frame's bits over every payload of ``length``
    bytes for a known identifier, IFS included: the header (SOF to DLC) stuffed exactly,
    then the most stuff bits the 8n data and 15 CRC bits can add after it.  Never above
    :func:`hdhil.dbc.worst_case_frame_bits`, which holds for any identifier."""
    _check_id(arbitration_id, extended)
    if not 0 <= length <= 8:
        raise ValueError(f"a classical CAN frame carries 0 to 8 bytes, not {length}")
    nbits, _crc, state, added = _header(arbitration_id, extended, False, length)
    free = 8 * length + 15
    return nbits + free + added + _most_stuff_bits(free, (state & 3) + 1) + 13


def frame_seconds(msg: can.Message, bitrate: float, data_bitrate: float | None = None) -> float:
    """Exact time on the wire of a python-can message, classical or FD, IFS included: an
    FD frame's data phase at ``data_bitrate`` when it has ``bitrate_switch`` set.  A
    classical remote frame counts with its DLC, carrying no data."""
    data = bytes(msg.data or b"")
    if not msg.is_fd:
        if msg.is_remote_frame:
            data = bytes(min(msg.dlc, 8))
        bits = frame_bits(msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, data)
        return bits / bitrate
    if msg.is_remote_frame:
        raise ValueError("CAN FD has no remote frames")
    if msg.bitrate_switch and data_bitrate is None:
        raise ValueError("an FD frame with bit-rate switching needs a data bit rate")
    fd_bits = fd_frame_bits(
        msg.arbitration_id,
        msg.is_extended_id,
        data,
        brs=msg.bitrate_switch,
        esi=msg.error_state_indicator,
    )
    return fd_bits.seconds(bitrate, data_bitrate or bitrate)

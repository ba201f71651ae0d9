"""Exact bit counts of classical CAN frames: CRC-15 and bit stuffing (ISO 11898-1).

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
"""

from __future__ import annotations

from functools import lru_cache

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

"""Exact CAN frame bit counts against a plain bit-by-bit reference and known frames."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hdhil.can.bittiming import frame_bits
from hdhil.dbc import worst_case_frame_bits


def _reference_bits(can_id: int, extended: bool, remote: bool, data: bytes) -> int:
    """Straight from ISO 11898-1: build the bit list, CRC bit by bit, stuff bit by bit."""
    bits: list[int] = [0]  # SOF
    if extended:
        base, ext = can_id >> 18, can_id & 0x3FFFF
        bits += [(base >> i) & 1 for i in range(10, -1, -1)] + [1, 1]  # SRR, IDE
        bits += [(ext >> i) & 1 for i in range(17, -1, -1)] + [int(remote), 0, 0]
    else:
        bits += [(can_id >> i) & 1 for i in range(10, -1, -1)] + [int(remote), 0, 0]
    dlc = len(data)
    bits += [(dlc >> i) & 1 for i in range(3, -1, -1)]
    if not remote:
        for byte in data:
            bits += [(byte >> i) & 1 for i in range(7, -1, -1)]
    crc = 0
    for b in bits:
        nxt = b ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if nxt:
            crc ^= 0x4599
    bits += [(crc >> i) & 1 for i in range(14, -1, -1)]
    stuffed, last, run = 0, None, 0
    for b in bits:
        run = run + 1 if b == last else 1
        last = b
        if run == 5:
            stuffed += 1
            last, run = 1 - b, 1
    return len(bits) + stuffed + 13


@pytest.mark.slow
@settings(max_examples=500, deadline=None)
@given(
    extended=st.booleans(),
    data=st.binary(min_size=0, max_size=8),
    remote=st.booleans(),
    can_id=st.integers(0, (1 << 29) - 1),
)
def test_exact_count_matches_the_bit_by_bit_reference(extended, data, remote, can_id):
    if not extended:
        can_id &= 0x7FF
    expected = _reference_bits(can_id, extended, remote, data)
    assert frame_bits(can_id, extended, remote, data) == expected
    assert expected <= worst_case_frame_bits(0 if remote else len(data), extended)


def test_no_stuffing_below_the_worst_case_and_known_frames():
    # 47 + 8n is the unstuffed length: a real frame is never shorter.
    assert frame_bits(0x080, False, False, b"\x01") >= 55
    # An all-zero payload stuffs heavily; alternating bits do not stuff at all in the data.
    zeros = frame_bits(0x182, False, False, bytes(8))
    alternating = frame_bits(0x182, False, False, b"\x55" * 8)
    assert zeros > alternating
    assert zeros <= worst_case_frame_bits(8)


def test_eight_byte_frames_match_the_reference() -> None:
    """The written-out path of 8-byte data frames, fast-tier: runs of zeros and ones
    across byte borders (stuff bits carried from byte to byte) and random payloads."""
    rng = random.Random(8)
    for _ in range(300):
        extended = rng.random() < 0.5
        can_id = rng.getrandbits(29 if extended else 11)
        data = bytes(rng.choice((0x00, 0xFF, 0x0F, 0xF0, rng.getrandbits(8))) for _ in range(8))
        expected = _reference_bits(can_id, extended, False, data)
        assert frame_bits.__wrapped__(can_id, extended, False, data) == expected


@pytest.mark.parametrize("nbits", [7, 8])
def test_stuff_tables_are_bit_by_bit_stuffing(nbits: int) -> None:
    """The composed chunk tables against stuffing one bit at a time."""
    from hdhil.can import bittiming as bt

    table = bt._STUFF if nbits == 8 else bt._STUFF7
    assert len(table) == 8 << nbits
    for index in range(8):
        for chunk in range(1 << nbits):
            state, added = (index >> 2, (index & 3) + 1), 0
            for i in range(nbits - 1, -1, -1):
                state, s = bt._stuff_step(state, (chunk >> i) & 1)
                added += s
            assert table[index << nbits | chunk] == added << 3 | bt._state_index(state)

"""CAN FD frame timing (ISO 11898-1:2015) against independent facts: published CRC check
values, a frame built by hand bit by bit, a plain string-based reference written here,
and the figures issue 24 states."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hdhil.can.bittiming import (
    FD_LENGTHS,
    FdBits,
    crc15_bits,
    crc17_bits,
    crc21_bits,
    fd_bitstream,
    fd_dlc,
    fd_frame_bits,
    fd_frame_seconds,
    fd_length,
    fd_phases,
    frame_bits,
    frame_seconds,
    worst_case_fd_frame_bits,
    worst_case_fd_frame_seconds,
    worst_case_frame_bits_for,
)
from hdhil.dbc import worst_case_frame_bits

CHECK = int.from_bytes(b"123456789", "big")


def test_crc_polynomials_give_the_catalogued_check_values() -> None:
    # The CRC catalogue's check values (CRC of ASCII "123456789", register from zero,
    # no reflection, no final XOR): CRC-15/CAN 0x059E, CRC-17/CAN-FD 0x04F03,
    # CRC-21/CAN-FD 0x0ED841.
    assert crc15_bits(CHECK, 72) == 0x059E
    assert crc17_bits(CHECK, 72) == 0x04F03
    assert crc21_bits(CHECK, 72) == 0x0ED841


# --- an independent reference -----------------------------------------------------------


def _crc(bits: str, poly: int, width: int) -> int:
    """Bit-serial CRC over a string of '0'/'1', register from 1 followed by zeros."""
    reg = 1 << (width - 1)
    for ch in bits:
        feedback = int(ch) ^ (reg >> (width - 1))
        reg = (reg << 1) & ((1 << width) - 1)
        if feedback:
            reg ^= poly
    return reg


def _stuff(raw: str, after_last: bool) -> str:
    """Dynamic stuffing: a complement after five equal bits (after the last bit only if
    ``after_last``)."""
    out, run = "", 0
    for i, ch in enumerate(raw):
        run = run + 1 if out and out[-1] == ch else 1
        out += ch
        if run == 5 and (after_last or i < len(raw) - 1):
            out += "1" if ch == "0" else "0"
            run = 1
    return out


def _head(can_id: int, extended: bool, brs: bool, esi: bool, length: int) -> tuple[str, str]:
    """(SOF .. BRS, ESI .. DLC), unstuffed."""
    if extended:
        arb = "0" + f"{can_id >> 18:011b}" + "11" + f"{can_id & 0x3FFFF:018b}" + "0"
    else:
        arb = "0" + f"{can_id:011b}" + "00"
    arb += "10" + str(int(brs))  # FDF, res, BRS
    return arb, str(int(esi)) + f"{FD_LENGTHS.index(length):04b}"


def _reference(can_id: int, extended: bool, data: bytes, brs: bool, esi: bool) -> tuple[str, int]:
    """(every bit of the frame as a string, bits at the data bit rate), from the field
    list of ISO 11898-1:2015 written out with strings."""
    length = next(n for n in FD_LENGTHS if n >= len(data))
    data = data + bytes(length - len(data))
    arb, ctrl = _head(can_id, extended, brs, esi, length)
    raw = arb + ctrl + "".join(f"{b:08b}" for b in data)
    stuffed = _stuff(raw, after_last=False)
    count = len(stuffed) - len(raw)
    gray = count % 8 ^ (count % 8) >> 1
    sc = f"{gray:03b}" + str(bin(gray).count("1") % 2)
    width, poly = (17, 0x1685B) if length <= 16 else (21, 0x102899)
    seq = sc + f"{_crc(stuffed + sc, poly, width):0{width}b}"
    field = ""
    for i, ch in enumerate(seq):
        if i % 4 == 0:
            field += "1" if (field or stuffed)[-1] == "0" else "0"  # fixed stuff bit
        field += ch
    frame = stuffed + field + "1" + "0" + "1" + "1" * 7 + "1" * 3
    # A stuff bit right after BRS is sent at the data bit rate.
    nominal_head = len(_stuff(arb, after_last=False))
    in_data = len(stuffed) + len(field) - nominal_head if brs else 0
    return frame, in_data


def _stream_bits(stream) -> str:
    return "".join(str(bit) for _name, bit in stream)


def test_a_frame_built_by_hand() -> None:
    """Base ID 0x123, one data byte 0x00, BRS, error active: written out field by
    field, stuff bits placed by hand."""
    head = (
        "0"  # SOF
        "00100100011"  # ID 0x123
        "0"  # RRS
        "0"  # IDE
        "1"  # FDF
        "0"  # res
        "1"  # BRS: the data phase starts after this bit
        "0"  # ESI
        "0001"  # DLC 1
        "00000"  # data bits 7..3: five equal bits (ESI and DLC ended on a 1) ...
        "1"  # ... a dynamic stuff bit
        "000"  # data bits 2..0: a run of 3, the last data bit (no stuff after it)
    )
    # One dynamic stuff bit: stuff count 1, Gray 001, even parity 1.
    sc = "0011"
    crc = _crc(head + sc, 0x1685B, 17)  # CRC-17: one data byte (<= 16)
    seq = sc + f"{crc:017b}"
    field = ""
    for i in range(0, len(seq), 4):  # a fixed stuff bit ahead of every 4 bits
        previous = (field or head)[-1]
        field += ("1" if previous == "0" else "0") + seq[i : i + 4]
    assert len(field) == 4 + 17 + 6  # 6 fixed stuff bits around 21 bits
    tail = "1" + "0" + "1" + "1111111" + "111"  # CRC del, ACK, ACK del, EOF, IFS
    expected = head + field + tail
    stream = fd_bitstream(0x123, False, b"\x00")
    assert _stream_bits(stream) == expected
    assert [name for name, _ in stream].count("S") == 1
    assert [name for name, _ in stream].count("FSB") == 6
    # 30 unstuffed bits + 1 stuff bit up to the data's end, a 27-bit CRC field, 13 after.
    assert len(expected) == 71
    # Nominal: SOF..BRS (17) and CRC delimiter..IFS (13); data: ESI..CRC (41).
    assert fd_frame_bits(0x123, False, b"\x00") == FdBits(30, 41)
    assert fd_phases(stream) == FdBits(30, 41)
    # Without BRS every bit is nominal, and BRS = 0 makes res, BRS, ESI and the DLC's
    # three zeros a run that takes one more stuff bit.
    assert fd_frame_bits(0x123, False, b"\x00", brs=False) == FdBits(72, 0)


def test_five_equal_bits_at_the_end_of_the_data_add_no_second_bit() -> None:
    # DLC 0001 then 0xE0 = 1110 0000: the data ends with five zeros; exactly one bit (the
    # fixed stuff bit, a 1) separates the last data bit from the stuff count.
    stream = fd_bitstream(0x123, False, b"\xe0")
    names = [name for name, _ in stream]
    last_data = len(names) - 1 - names[::-1].index("D")
    assert names[last_data + 1 : last_data + 3] == ["FSB", "SC"]
    assert stream[last_data + 1][1] == 1
    assert _stream_bits(stream) == _reference(0x123, False, b"\xe0", True, False)[0]


def test_crc_21_above_16_bytes_and_dlc_padding() -> None:
    assert [fd_length(n) for n in (0, 8, 9, 12, 13, 17, 33, 49, 64)] == [
        0, 8, 12, 12, 16, 20, 48, 64, 64,
    ]  # fmt: skip
    assert fd_dlc(10) == 9 and fd_dlc(64) == 15
    with pytest.raises(ValueError, match="0 to 64"):
        fd_length(65)
    # 16 bytes: 17 CRC bits + 6 fixed stuff; 20 bytes: 21 + 7.
    names16 = [n for n, _ in fd_bitstream(0x10, False, bytes(range(16)))]
    names20 = [n for n, _ in fd_bitstream(0x10, False, bytes(range(20)))]
    assert (names16.count("CRC"), names16.count("FSB")) == (17, 6)
    assert (names20.count("CRC"), names20.count("FSB")) == (21, 7)
    # A payload between FD lengths is padded (with zeros) to the next one.
    assert fd_frame_bits(0x10, False, b"\x55" * 10) == fd_frame_bits(
        0x10, False, b"\x55" * 10 + b"\x00\x00"
    )


def _payload(rng: random.Random, n: int) -> bytes:
    return bytes(rng.choice((0x00, 0xFF, 0x0F, 0xF0, 0x55, rng.getrandbits(8))) for _ in range(n))


def test_bitstream_and_fast_count_match_the_reference() -> None:
    rng = random.Random(24)
    for _ in range(150):
        extended = rng.random() < 0.5
        can_id = rng.getrandbits(29 if extended else 11)
        data = _payload(rng, rng.choice(FD_LENGTHS))
        brs, esi = rng.random() < 0.7, rng.random() < 0.3
        frame, in_data = _reference(can_id, extended, data, brs, esi)
        stream = fd_bitstream(can_id, extended, data, brs=brs, esi=esi)
        assert _stream_bits(stream) == frame
        expected = FdBits(len(frame) - in_data, in_data)
        assert fd_frame_bits(can_id, extended, data, brs=brs, esi=esi) == expected
        assert fd_phases(stream) == expected


def _unstuffed(length: int, extended: bool) -> int:
    n = fd_length(length)
    return (17 + 19 * extended) + 5 + 8 * n + (27 if n <= 16 else 32) + 13


@settings(max_examples=120, deadline=None)
@given(
    extended=st.booleans(),
    can_id=st.integers(0, (1 << 29) - 1),
    data=st.binary(min_size=0, max_size=64),
    brs=st.booleans(),
    esi=st.booleans(),
)
def test_exact_bits_between_unstuffed_and_worst_case(extended, can_id, data, brs, esi) -> None:
    if not extended:
        can_id &= 0x7FF
    exact = fd_frame_bits(can_id, extended, data, brs=brs, esi=esi)
    for_id = worst_case_fd_frame_bits(len(data), extended, brs=brs, arbitration_id=can_id)
    any_id = worst_case_fd_frame_bits(len(data), extended, brs=brs)
    assert _unstuffed(len(data), extended) <= exact.total <= for_id.total <= any_id.total
    for rates in ((1e6, 5e6), (5e5, 2e6), (1e6, 1e6)):
        assert exact.seconds(*rates) <= for_id.seconds(*rates) <= any_id.seconds(*rates)


def test_the_worst_case_for_an_identifier_is_reached() -> None:
    """The bound for a known identifier is tight: after the header's final run, data
    bits that repeat its bit until the first stuff bit, then runs of four, stuff at every
    chance (the FD stuff count does not depend on the CRC)."""
    cases = ((0x182, False, 8), (0x7FF, False, 64), (0x000, False, 1), (0x1ABCDE, True, 20))
    for can_id, extended, length in cases:
        arb, ctrl = _head(can_id, extended, True, False, length)
        head = _stuff(arb + ctrl, after_last=True)
        last = head[-1]
        run = len(head) - len(head.rstrip(last))
        bits, value = last * (5 - run), "1" if last == "0" else "0"
        while len(bits) < 8 * length:
            bits += value * 4
            value = "1" if value == "0" else "0"
        data = int(bits[: 8 * length], 2).to_bytes(length, "big")
        exact = fd_frame_bits(can_id, extended, data)
        assert exact == worst_case_fd_frame_bits(length, extended, arbitration_id=can_id)


def test_classical_bound_for_an_identifier() -> None:
    """Below the identifier-free budget, never below an exact frame (runs of equal bits
    and random payloads)."""
    rng = random.Random(402)
    for _ in range(300):
        extended = rng.random() < 0.3
        can_id = rng.getrandbits(29 if extended else 11)
        n = rng.randint(0, 8)
        bound = worst_case_frame_bits_for(can_id, extended, n)
        assert bound <= worst_case_frame_bits(n, extended)
        for data in (bytes(n), b"\xff" * n, _payload(rng, n)):
            assert frame_bits(can_id, extended, False, data) <= bound


def test_classical_bound_for_an_identifier_by_hand() -> None:
    """The header (SOF to DLC) stuffed here, then the data and CRC bits at their worst:
    the first stuff bit after 5 - run of them, one after every 4 more (the last CRC bit
    included: classical stuffing runs to the end of the CRC)."""
    for can_id, n in ((0x080, 1), (0x182, 8), (0x000, 8), (0x7FF, 0), (0x555, 3)):
        header = _stuff("0" + f"{can_id:011b}" + "000" + f"{n:04b}", after_last=True)
        run = len(header) - len(header.rstrip(header[-1]))
        free = 8 * n + 15
        stuff = (free - (5 - run)) // 4 + 1
        assert worst_case_frame_bits_for(can_id, False, n) == len(header) + free + stuff + 13


def test_figures_of_the_issue() -> None:
    # Classical 1 Mbit/s: SYNC (1 byte) <= 65 us, an 8-byte frame <= 135 us, stuffing
    # at its worst; the bounds for the CANopen identifiers are within them.
    assert worst_case_frame_bits(1) / 1e6 == pytest.approx(65e-6)
    assert worst_case_frame_bits(8) / 1e6 == pytest.approx(135e-6)
    assert worst_case_frame_bits_for(0x080, False, 1) <= 65
    for cob_id in (0x182, 0x202, 0x183, 0x203):
        assert worst_case_frame_bits_for(cob_id, False, 8) <= 135
    # CAN FD, 64 bytes at 1/5 Mbit/s: "about 150 us".  Without stuff bits 30 nominal bits
    # (SOF..BRS 17, CRC delimiter..IFS 13) and 549 data-phase bits (ESI, DLC, 512 data,
    # stuff count, CRC-21, 7 fixed stuff bits): 30 + 109.8 = 139.8 us.
    assert _unstuffed(64, False) == 30 + 549
    worst = worst_case_fd_frame_seconds(64, 1e6, 5e6)
    assert 139.8e-6 < worst < 170e-6
    rng = random.Random(5)
    typical = [fd_frame_seconds(0x181, False, rng.randbytes(64), 1e6, 5e6) for _ in range(200)]
    mean = sum(typical) / len(typical)
    assert min(typical) > 139.8e-6 and max(typical) <= worst
    assert mean == pytest.approx(150e-6, rel=0.07)
    # The data phase is what BRS speeds up: the same frame without BRS at 1 Mbit/s.
    assert worst_case_fd_frame_seconds(64, 1e6, 5e6, brs=False) > 4 * worst


def test_python_can_messages_are_timed_by_their_format() -> None:
    import can

    data = bytes(range(20))
    fd = can.Message(
        arbitration_id=0x181, data=data, is_extended_id=False, is_fd=True, bitrate_switch=True
    )
    assert frame_seconds(fd, 1e6, 5e6) == fd_frame_bits(0x181, False, data).seconds(1e6, 5e6)
    with pytest.raises(ValueError, match="data bit rate"):
        frame_seconds(fd, 1e6)
    slow = can.Message(
        arbitration_id=0x181,
        data=data,
        is_extended_id=False,
        is_fd=True,
        error_state_indicator=True,
    )
    assert (
        frame_seconds(slow, 1e6)
        == fd_frame_bits(0x181, False, data, brs=False, esi=True).total / 1e6
    )
    classic = can.Message(arbitration_id=0x182, data=b"\x00" * 8, is_extended_id=False)
    assert frame_seconds(classic, 1e6) == frame_bits(0x182, False, False, bytes(8)) / 1e6
    remote = can.Message(arbitration_id=0x182, is_remote_frame=True, dlc=8, is_extended_id=False)
    assert frame_seconds(remote, 1e6) == frame_bits(0x182, False, True, bytes(8)) / 1e6

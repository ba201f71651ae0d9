"""The compiled frame codecs agree with cantools for every message of both DBCs."""

from __future__ import annotations

import math

import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hdhil.dbc import FrameCodec, codec, database, worst_case_frame_bits

ALL_MESSAGES = [(bus, m.name) for bus in ("control", "truth") for m in database(bus).messages]


def _physical_strategy(sig):
    if sig.is_float:
        return st.floats(-1e6, 1e6, allow_nan=False, width=32)
    lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
    hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
    return st.integers(lo, hi).map(lambda raw: raw * sig.scale + sig.offset)


@pytest.mark.parametrize(("bus", "name"), ALL_MESSAGES)
@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_encode_decode_agree_with_cantools(bus, name, data):
    c = codec(bus, name)
    message = database(bus).get_message_by_name(name)
    values = [data.draw(_physical_strategy(message.get_signal_by_name(n))) for n in c.signal_names]
    ours = c.encode(*values)
    theirs = message.encode(dict(zip(c.signal_names, values, strict=True)), strict=False)
    assert ours == theirs
    decoded_ours = c.decode(ours)
    decoded_theirs = message.decode(theirs, decode_choices=False)
    for n, v in zip(c.signal_names, decoded_ours, strict=True):
        assert math.isclose(v, decoded_theirs[n], rel_tol=1e-12, abs_tol=1e-12)


def test_integer_signals_saturate_instead_of_wrapping():
    c = codec("control", "CTRL_TPDO1")
    T_meas, T_filtered, velocity, current = c.decode(c.encode(1e9, -1e9, 400.0, -40.0))
    assert T_meas == pytest.approx(131.068)
    assert T_filtered == pytest.approx(-131.072)
    assert velocity == pytest.approx(327.67)
    assert current == pytest.approx(-32.768)


def test_nan_into_integer_signal_is_refused():
    with pytest.raises(ValueError, match="NaN"):
        codec("control", "CTRL_TPDO1").encode(float("nan"), 0.0, 0.0, 0.0)


def test_wrong_payload_length_is_refused():
    with pytest.raises(ValueError, match="expected 8 data bytes"):
        codec("control", "DRIVE_TPDO1").decode(b"\x00\x01")


def test_layouts_outside_the_compiled_subset_are_rejected_at_start_up():
    db = cantools.database.load_string(
        'VERSION ""\nBS_:\nBU_: A\nBO_ 1 M: 2 A\n SG_ s : 3|12@1+ (1,0) [0|4095] "" A\n'
    )
    with pytest.raises(ValueError, match="byte-aligned"):
        FrameCodec(db.get_message_by_name("M"))


def test_required_signal_names_exist():
    control = database("control")
    tele = control.get_message_by_name("CTRL_TPDO1")
    for name in ("T_meas", "T_filtered", "velocity"):
        assert tele.get_signal_by_name(name) is not None
    assert database("truth").get_message_by_name("TRUTH_TORQUE").get_signal_by_name("T_true")


def test_truth_and_control_identifiers_cannot_be_confused():
    control = {(m.frame_id, m.is_extended_frame) for m in database("control").messages}
    truth = {(m.frame_id, m.is_extended_frame) for m in database("truth").messages}
    assert not control & truth
    assert all(ext for _, ext in truth)
    assert not any(ext for _, ext in control)


def test_worst_case_frame_bits_match_design_budget():
    # DESIGN.md: SYNC (1 byte) <= 65 us and an 8-byte PDO <= 135 us at 1 Mbit/s.
    assert worst_case_frame_bits(1) == 65
    assert worst_case_frame_bits(8) == 135
    assert worst_case_frame_bits(0) == 47 + 33 // 4

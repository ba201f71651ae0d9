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


@pytest.mark.slow
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


def _edge_strategy(sig):
    """Physical values around and beyond an integer signal's raw range: half-way ties,
    the limits themselves, infinities, and (for unscaled signals) ints and floats."""
    if sig.is_float:
        return st.floats(-1e6, 1e6, allow_nan=False, width=32)
    lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
    hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
    raw = st.one_of(
        st.integers(lo - 3, hi + 3).map(lambda k: k + 0.5),
        st.integers(lo - 3, hi + 3).map(float),
        st.floats(lo - 3.0, hi + 3.0),
        st.sampled_from([lo - 0.5, lo - 0.25, hi + 0.25, hi + 0.5, math.inf, -math.inf]),
    )
    physical = raw.map(lambda r: r * sig.scale + sig.offset)
    if sig.scale == 1 and sig.offset == 0:
        return st.one_of(physical, st.integers(lo - 3, hi + 3), st.booleans())
    return physical


def _saturating_reference(c, message, values):
    """Scale, refuse NaN, saturate at the raw range, round half to even, then pack."""
    raws = []
    for name, v in zip(c.signal_names, values, strict=True):
        sig = message.get_signal_by_name(name)
        if not (sig.scale == 1 and sig.offset == 0):
            v = (v - float(sig.offset)) * (1.0 / float(sig.scale))
        if not sig.is_float:
            if math.isnan(v):
                raise ValueError("NaN")
            lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
            hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
            v = lo if v <= lo else hi if v >= hi else round(v)
        raws.append(v)
    return c._struct.pack(*raws)


@pytest.mark.slow
@pytest.mark.parametrize(("bus", "name"), ALL_MESSAGES)
@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_encode_saturates_and_rounds_like_the_reference_at_the_edges(bus, name, data):
    """The one-``pack`` fast line of ``encode`` and its general path agree with the
    saturating reference for ties, limits, out-of-range and infinite values."""
    c = codec(bus, name)
    message = database(bus).get_message_by_name(name)
    values = [data.draw(_edge_strategy(message.get_signal_by_name(n))) for n in c.signal_names]
    try:
        expected = _saturating_reference(c, message, values)
    except (ValueError, OverflowError):
        with pytest.raises((ValueError, OverflowError)):
            c.encode(*values)
        return
    assert c.encode(*values) == expected


def test_ties_round_to_even_and_limits_saturate_in_one_frame():
    c = codec("truth", "TRUTH_JOINT")  # four int16 signals, scale 0.005
    raw = c._struct.unpack(c.encode(2.5 * 0.005, 3.5 * 0.005, 32767.5 * 0.005, -1e300))
    assert raw == (2, 4, 32767, -32768)
    unscaled = codec("control", "DRIVE_RPDO1")
    assert unscaled.encode(-2.5, 65535.5, 1.5) == unscaled.encode(-2, 65535, 2)
    assert unscaled.encode(True, 70000, -1) == unscaled.encode(1, 65535, 0)


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
    # docs/design.md: SYNC (1 byte) <= 65 us and an 8-byte PDO <= 135 us at 1 Mbit/s.
    assert worst_case_frame_bits(1) == 65
    assert worst_case_frame_bits(8) == 135
    assert worst_case_frame_bits(0) == 47 + 33 // 4


# ------------------------------------------------------------- signals checked by name


def _reordered_control_dbc(tmp_path):
    """control.dbc with DRIVE_TPDO1's first two signals swapped on the wire (the tacho
    now in bytes 0-1, the torque in bytes 2-3): a valid DBC a node must not misread."""
    from hdhil.dbc import dbc_path

    text = dbc_path("control").read_text()
    a = ' SG_ ADC_torque : 0|16@1- (1,0) [-2048|2047] "count" CONTROLLER,HOST'
    b = ' SG_ ADC_tacho : 16|16@1- (1,0) [-2048|2047] "count" CONTROLLER,HOST'
    assert a in text and b in text
    text = text.replace(a, a.replace(": 0|16", ": 16|16"))
    text = text.replace(b, b.replace(": 16|16", ": 0|16"))
    path = tmp_path / "control.dbc"
    path.write_text(text)
    return cantools.database.load_file(str(path))


def test_a_dbc_with_reordered_signals_fails_loudly_at_start_up(tmp_path):
    db = _reordered_control_dbc(tmp_path)
    reordered = FrameCodec(db.get_message_by_name("DRIVE_TPDO1"), "control")
    expected = ("ADC_torque", "ADC_tacho", "ADC_current", "ENC_count")
    with pytest.raises(ValueError, match=r"control\.dbc DRIVE_TPDO1: the node expects") as err:
        reordered.expect(*expected)
    assert "ADC_tacho, ADC_torque, ADC_current, ENC_count" in str(err.value)
    # The shipped DBC passes the same check.
    assert codec("control", "DRIVE_TPDO1").expect(*expected).signal_names == expected


def test_decoding_by_name_gives_the_right_values_whatever_the_order(tmp_path):
    db = _reordered_control_dbc(tmp_path)
    message = db.get_message_by_name("DRIVE_TPDO1")
    reordered = FrameCodec(message, "control")
    values = {"ADC_torque": 1234, "ADC_tacho": -567, "ADC_current": 89, "ENC_count": 40000}
    payload = message.encode(values)  # cantools packs by name
    assert reordered.decode_named(payload) == values
    assert reordered.encode_named(**values) == payload
    # Positional decoding follows the wire order: the first value is now the tacho.
    assert reordered.decode(payload)[0] == -567
    shipped = codec("control", "DRIVE_TPDO1")
    assert shipped.decode_named(shipped.encode_named(**values)) == values
    with pytest.raises(ValueError, match="missing signals"):
        shipped.encode_named(ADC_torque=1)


def test_every_node_expects_the_shipped_layouts():
    """Building both nodes runs every ``expect`` against the shipped DBCs."""
    import can

    from hdhil.firmware.config import FirmwareConfig
    from hdhil.firmware.controller import ControllerNode
    from hdhil.hostsim.drive import DriveNode
    from hdhil.hostsim.plant import Plant, PlantConfig

    bus = can.Bus(interface="virtual", channel="t-expect", receive_own_messages=False)
    try:
        ControllerNode(bus, FirmwareConfig())
        DriveNode(bus, Plant(PlantConfig()))
    finally:
        bus.shutdown()


def test_node_function_codes_come_from_the_dbc():
    from hdhil.dbc import node_function_codes, node_ids

    assert node_ids("control") == {"CONTROLLER": 1, "DRIVE": 2}
    # EMCY, TPDO1, TPDO2, SDO response, heartbeat: what both nodes transmit with their ID.
    assert node_function_codes("control") == (0x080, 0x180, 0x280, 0x580, 0x700)

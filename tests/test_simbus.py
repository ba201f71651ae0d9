"""The simulated-time bus: python-can plug-in, ordering, timing model, isolation."""

from __future__ import annotations

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hdhil.can.bittiming import frame_bits
from hdhil.can.busload import schedule_load
from hdhil.can.simbus import (
    _MESSAGE_FIELDS,
    SimClock,
    _snapshot_checked,
    _snapshot_fast,
    received_copy,
)


@pytest.fixture
def pair():
    clock = SimClock()
    a = can.Bus(interface="simbus", channel="t-pair", clock=clock, timing="worst-case")
    b = can.Bus(interface="simbus", channel="t-pair")
    yield clock, a, b
    a.shutdown()
    b.shutdown()


def _frame(can_id: int, n: int) -> can.Message:
    return can.Message(arbitration_id=can_id, data=bytes(range(n)), is_extended_id=False)


def test_frames_arrive_in_order_with_serialised_timestamps(pair):
    clock, a, b = pair
    clock.now = 0.010
    a.send(_frame(0x80, 1))
    a.send(_frame(0x182, 8))
    first, second = b.recv(0), b.recv(0)
    assert b.recv(0) is None
    assert (first.arbitration_id, second.arbitration_id) == (0x80, 0x182)
    # 65 bits then 135 bits at 1 Mbit/s, back to back from 10 ms.
    assert first.timestamp == pytest.approx(0.010 + 65e-6)
    assert second.timestamp == pytest.approx(0.010 + 200e-6)
    assert bytes(second.data) == bytes(range(8))


def test_exact_timing_uses_the_real_stuff_bits():
    clock = SimClock(0.5)
    a = can.Bus(interface="simbus", channel="t-exact", clock=clock)
    b = can.Bus(interface="simbus", channel="t-exact")
    try:
        a.send(_frame(0x182, 8))
        got = b.recv(0)
        bits = frame_bits(0x182, False, False, bytes(range(8)))
        assert bits < 135  # fewer than the worst case for this payload
        assert got.timestamp == pytest.approx(0.5 + bits * 1e-6)
    finally:
        a.shutdown()
        b.shutdown()


def test_simultaneous_requests_arbitrate_by_identifier():
    clock = SimClock()
    a = can.Bus(interface="simbus", channel="t-arb", clock=clock, timing="worst-case")
    b = can.Bus(interface="simbus", channel="t-arb")
    c = can.Bus(interface="simbus", channel="t-arb")
    try:
        a.send(_frame(0x202, 5))  # requested first, but a higher identifier
        b.send(_frame(0x181, 8))
        a.send(_frame(0x7FF, 0))
        order = [c.recv(0) for _ in range(3)]
        assert [m.arbitration_id for m in order] == [0x181, 0x202, 0x7FF]
        assert order[0].timestamp == pytest.approx(135e-6)
        assert order[1].timestamp == pytest.approx((135 + 105) * 1e-6)
    finally:
        for bus in (a, b, c):
            bus.shutdown()


def test_requests_on_an_idle_wire_arbitrate_by_identifier_too():
    """Frames requested at the same instant after the wire has been idle start together
    and arbitrate: a heartbeat sent just before the SYNC of the same instant loses to it
    (send order decided it, which delayed the SYNC by one frame every heartbeat)."""
    clock = SimClock()
    a = can.Bus(interface="simbus", channel="t-idle", clock=clock, timing="worst-case")
    c = can.Bus(interface="simbus", channel="t-idle")
    try:
        a.send(_frame(0x181, 8))
        assert c.recv(0).arbitration_id == 0x181  # the wire is idle from 135 µs on
        clock.now = 1e-3
        a.send(_frame(0x701, 1))  # requested first, but a higher identifier
        a.send(_frame(0x080, 0))
        order = [c.recv(0) for _ in range(2)]
        assert [m.arbitration_id for m in order] == [0x080, 0x701]
        assert order[0].timestamp == pytest.approx(1e-3 + 55e-6)  # starts at the request
    finally:
        for bus in (a, c):
            bus.shutdown()


def test_a_node_cannot_answer_before_it_received_the_frame():
    clock = SimClock()
    a = can.Bus(interface="simbus", channel="t-causal", clock=clock, timing="worst-case")
    b = can.Bus(interface="simbus", channel="t-causal")
    try:
        a.send(_frame(0x80, 1))  # the SYNC: delivered at 65 us
        sync = b.recv(0)
        b.send(_frame(0x182, 8))  # the answer is requested when b received the SYNC
        answer = a.recv(0)
        assert answer.timestamp == pytest.approx(sync.timestamp + 135e-6)
    finally:
        a.shutdown()
        b.shutdown()


def test_sender_does_not_receive_its_own_frames_unless_asked():
    a = can.Bus(interface="simbus", channel="t-own", receive_own_messages=True)
    b = can.Bus(interface="simbus", channel="t-own")
    try:
        a.send(_frame(0x1, 0))
        assert a.recv(0) is not None
        b.send(_frame(0x2, 0))
        assert a.recv(0).arbitration_id == 0x2
        assert b.recv(0).arbitration_id == 0x1
        assert b.recv(0) is None
    finally:
        a.shutdown()
        b.shutdown()


def test_channels_are_isolated_and_removed_on_shutdown():
    a = can.Bus(interface="simbus", channel="t-iso-1")
    b = can.Bus(interface="simbus", channel="t-iso-2")
    a.send(_frame(0x5, 1))
    assert b.recv(0) is None
    a.shutdown()
    b.shutdown()
    c = can.Bus(interface="simbus", channel="t-iso-1")
    assert c.frames_sent == 0
    c.shutdown()


def test_zero_bitrate_stamps_with_the_clock():
    clock = SimClock(1.5)
    a = can.Bus(interface="simbus", channel="t-zero", bitrate=0, clock=clock)
    b = can.Bus(interface="simbus", channel="t-zero")
    a.send(_frame(0x7, 8))
    assert b.recv(0).timestamp == 1.5
    a.shutdown()
    b.shutdown()


def test_zero_bitrate_delivers_at_once_in_the_order_sent():
    """Without a wire there is no arbitration: frames arrive as sent (a higher
    identifier first here), each stamped with the clock's time when it was sent."""
    clock = SimClock(2.0)
    a = can.Bus(interface="simbus", channel="t-zero-order", bitrate=0, clock=clock)
    b = can.Bus(interface="simbus", channel="t-zero-order")
    try:
        a.send(_frame(0x300, 2))
        assert b.pending() == 1  # already delivered
        clock.now = 2.5
        a.send(_frame(0x100, 2))
        got = [b.recv(0), b.recv(0)]
        assert [(m.arbitration_id, m.timestamp) for m in got] == [(0x300, 2.0), (0x100, 2.5)]
        assert b.recv(0) is None and a.frames_sent == 2
    finally:
        a.shutdown()
        b.shutdown()


def _exchange(channel: str, use_dispatch: bool) -> list[tuple[str, int, float]]:
    """Node a sends three frames; node b answers each of the first two with two frames,
    the higher identifier sent first.  Returns what b and c received, in order, with
    timestamps."""
    clock = SimClock(0.001)
    a = can.Bus(interface="simbus", channel=channel, clock=clock)
    b = can.Bus(interface="simbus", channel=channel)
    c = can.Bus(interface="simbus", channel=channel)
    seen: list[tuple[str, int, float]] = []
    try:
        for can_id in (0x300, 0x301, 0x302):
            a.send(_frame(can_id, 8))

        def answer(msg: can.Message) -> None:
            seen.append(("b", msg.arbitration_id, msg.timestamp))
            if msg.arbitration_id in (0x300, 0x301):
                b.send(_frame(msg.arbitration_id - 0x100, 4))
                b.send(_frame(msg.arbitration_id - 0x200, 4))

        if use_dispatch:
            assert b.dispatch(answer) == 3
            c.dispatch(lambda m: seen.append(("c", m.arbitration_id, m.timestamp)))
        else:
            while (msg := b.recv(0)) is not None:
                answer(msg)
            while (msg := c.recv(0)) is not None:
                seen.append(("c", msg.arbitration_id, msg.timestamp))
        return seen
    finally:
        for bus in (a, b, c):
            bus.shutdown()


def test_dispatch_is_a_recv_loop_without_the_calls():
    """Same frames, same order, same timestamps, answers arbitrated the same way."""
    by_recv = _exchange("t-disp-recv", use_dispatch=False)
    by_dispatch = _exchange("t-disp", use_dispatch=True)
    assert by_dispatch == by_recv
    # a's frames were all on the wire when b first polled; each pair of answers
    # arbitrates (lower identifier first), and the second pair waits for b's next poll
    assert [i for who, i, _ in by_recv if who == "c"] == [
        0x300, 0x301, 0x302, 0x100, 0x200, 0x101, 0x201
    ]  # fmt: skip
    times = [t for who, _, t in by_recv if who == "c"]
    assert times == sorted(times) and len(set(times)) == len(times)


def test_dispatch_honours_receive_filters():
    clock = SimClock()
    a = can.Bus(interface="simbus", channel="t-disp-filter", clock=clock)
    b = can.Bus(interface="simbus", channel="t-disp-filter",
                can_filters=[{"can_id": 0x182, "can_mask": 0x7FF}])  # fmt: skip
    try:
        a.send(_frame(0x080, 1))
        a.send(_frame(0x182, 8))
        got: list[can.Message] = []
        assert b.dispatch(got.append) == 1
        assert [m.arbitration_id for m in got] == [0x182]
    finally:
        a.shutdown()
        b.shutdown()


def test_a_channel_cannot_be_joined_with_another_clock():
    a = can.Bus(interface="simbus", channel="t-clock", clock=SimClock())
    with pytest.raises(ValueError, match="another clock"):
        can.Bus(interface="simbus", channel="t-clock", clock=SimClock())
    a.shutdown()


def test_blocking_receive_times_out():
    a = can.Bus(interface="simbus", channel="t-block")
    assert a.recv(0.01) is None
    a.shutdown()


def test_control_schedule_fits_the_budget():
    load = schedule_load("control", 1_000_000, 1e-3)
    names = {name for name, _, _ in load.frames}
    assert names == {"SYNC", "DRIVE_TPDO1", "DRIVE_RPDO1", "CTRL_TPDO1", "CTRL_TPDO2"}
    # Each frame at its worst case for its identifier (docs/design.md's table): SYNC 62,
    # 8 bytes 132, 5 bytes 102 us per 1 ms cycle, below the bounds for any identifier
    # (65, 135, 105); the worst case counts CTRL_TPDO2 although it is only sent with a
    # control law active.
    assert load.worst_case_load == pytest.approx((62 + 132 + 102 + 132 + 132) / 1000)
    assert load.worst_case_load < (65 + 135 + 105 + 135 + 135) / 1000
    assert load.fits()
    # The same schedule at 500 kbit/s needs twice the time: over budget.
    assert not schedule_load("control", 500_000, 1e-3).fits()


@settings(max_examples=200, deadline=None)
@given(
    can_id=st.integers(0, 0x1FFFFFFF),
    extended=st.booleans(),
    remote=st.booleans(),
    error=st.booleans(),
    data=st.binary(max_size=8),
    fd=st.booleans(),
)
def test_the_received_copy_equals_a_constructed_message(can_id, extended, remote, error, data, fd):
    """The bus's field-by-field copy of a sent frame is what Message's constructor makes."""
    msg = can.Message(
        arbitration_id=can_id if extended else can_id & 0x7FF,
        is_extended_id=extended,
        is_remote_frame=remote,
        is_error_frame=error,
        data=data,
        dlc=len(data),
        is_fd=fd,
        bitrate_switch=fd,
        check=False,
    )
    fast, checked = _snapshot_fast(msg, 3), _snapshot_checked(msg, 3)
    assert {f: getattr(fast, f) for f in _MESSAGE_FIELDS} == {
        f: getattr(checked, f) for f in _MESSAGE_FIELDS
    }
    # A private copy: the sender may reuse its (bytearray) payload for the next frame.
    assert isinstance(fast.data, bytes) and fast.data is not msg.data


def test_the_fast_copy_is_used_only_while_it_covers_every_message_field():
    fields = set(can.Message.__slots__) - {"__weakref__"}
    assert (received_copy is _snapshot_fast) == (fields == _MESSAGE_FIELDS)


@pytest.mark.parametrize("bitrate", [0, 1_000_000])
def test_send_frames_delivers_what_sending_each_does(bitrate):
    """``send_frames`` (the truth channel's one call per cycle) leaves every receiver, the
    sender too with ``receive_own_messages``, with the frames, times and counts that one
    ``send`` per frame gives, on an untimed and on a timed channel."""

    def deliveries(batched: bool) -> list[tuple]:
        clock = SimClock(0.25)
        name = f"t-batch-{bitrate}-{batched}"
        a = can.Bus(interface="simbus", channel=name, bitrate=bitrate, clock=clock,
                    receive_own_messages=True)  # fmt: skip
        b = can.Bus(interface="simbus", channel=name, bitrate=bitrate)
        try:
            a.send(_frame(0x300, 2))
            assert b.recv(0) is not None
            b.send(_frame(0x301, 1))  # b answers later than the clock: a receives it
            frames = [_frame(0x1F0001 + i, 8 - i) for i in range(3)]
            assert a.recv(0) is not None and a.recv(0) is not None  # own frame, b's answer
            if batched:
                a.send_frames(frames)
            else:
                for f in frames:
                    a.send(f)
            got: list[tuple] = []
            for label, bus in (("a", a), ("b", b)):
                while (m := bus.recv(0)) is not None:
                    got.append((label, m.arbitration_id, bytes(m.data), m.timestamp))
            return [*got, (a.frames_requested, a.frames_sent)]
        finally:
            a.shutdown()
            b.shutdown()

    assert deliveries(batched=True) == deliveries(batched=False)


@pytest.mark.parametrize("filtered", [False, True])
def test_drain_into_takes_what_dispatch_takes(filtered):
    """A listen-only handle drained in one step gets the frames, times and order that
    dispatching them one by one gives, requested frames put on the wire first."""
    got: list[list[tuple[int, float]]] = []
    for take_all in (False, True):
        clock = SimClock(now=0.002)
        a = can.Bus(interface="simbus", channel="t-drain", clock=clock)
        tap = can.Bus(interface="simbus", channel="t-drain")
        if filtered:
            tap.set_filters([{"can_id": 0x100, "can_mask": 0x100}])
        for can_id, n in ((0x182, 8), (0x80, 0), (0x101, 3), (0x182, 2)):
            a.send(_frame(can_id, n))  # requested together: arbitration decides
        frames: list[can.Message] = [_frame(0x7FF, 0)]
        n = tap.drain_into(frames) if take_all else tap.dispatch(frames.append)
        assert n == len(frames) - 1
        assert tap.recv(0) is None
        got.append([(m.arbitration_id, m.timestamp) for m in frames])
        a.shutdown()
        tap.shutdown()
    assert got[0] == got[1]
    assert sorted(i for i, _ in got[1][1:]) == ([0x101, 0x182, 0x182] if filtered
                                                 else [0x80, 0x101, 0x182, 0x182])  # fmt: skip


def test_an_fd_frame_takes_its_phases_at_their_bit_rates():
    """A CAN FD frame with bit-rate switching on a channel with a data bit rate: its time
    on the wire is the exact FD frame time (arbitration at the nominal, data at the data
    bit rate), a classical frame's as before."""
    from hdhil.can.bittiming import frame_seconds

    clock = SimClock(0.0)
    a = can.Bus(interface="simbus", channel="t-fd", clock=clock, data_bitrate=5_000_000)
    b = can.Bus(interface="simbus", channel="t-fd")
    try:
        fd = can.Message(arbitration_id=0x182, data=bytes(range(32)), is_extended_id=False,
                         is_fd=True, bitrate_switch=True)  # fmt: skip
        a.send(fd)
        got = b.recv(0)
        expected = frame_seconds(fd, 1_000_000, 5_000_000)
        assert got.is_fd and got.bitrate_switch and bytes(got.data) == bytes(range(32))
        assert got.timestamp == pytest.approx(expected)
        assert expected < 110e-6  # a classical bus would need four frames of 8 bytes
    finally:
        a.shutdown()
        b.shutdown()

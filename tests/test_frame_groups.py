"""Frame groups on the truth channel: every listener sees what a simulated bus delivers.

The in-process truth channel of a lockstep run is a :class:`GroupChannel`; these tests
publish the same truth through it and through a :class:`SimBus` channel, with control
frames between, and compare what the tap hands each kind of listener: messages field by
field, the trace writer's records byte for byte, frame counts and torque scores.
"""

from __future__ import annotations

import itertools
import math

import can
import pytest

from hdhil.can.groups import FrameGroup, GroupChannel, expand_groups, group_messages
from hdhil.can.simbus import SimBus, SimClock
from hdhil.can.traces.tap import BusTap, FrameCounter
from hdhil.can.traces.writer import _records
from hdhil.dbc import CHANNEL_NUMBER, codec
from hdhil.hostsim.drive.truth_channel import TruthPublisher
from hdhil.hostsim.plant.truth import Truth
from hdhil.rig.score import TorqueScorer

_names = itertools.count()
TELEMETRY = codec("control", "CTRL_TPDO1")


class Collect(can.Listener):
    """Keeps every frame handed on, one by one (takes no frame groups)."""

    def __init__(self) -> None:
        self.frames: list[can.Message] = []

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append(msg)


class Records:
    """Keeps the trace writer's pipe records of what it is handed (takes frame groups)."""

    takes_frame_groups = True

    def __init__(self) -> None:
        self.data = b""

    def on_frames(self, frames: list) -> None:
        self.data += b"".join(_records(frames))

    def stop(self) -> None:
        pass


def _truth(k: int) -> Truth:
    return Truth(0.3 * math.sin(k), 7.0 * k, 0.07 * k, 50.0 - k, 0.5, 1.5, 1.25,
                 0.01 * math.cos(3 * k), 0.2, -0.1)  # fmt: skip


def _run(grouped: bool, cycles: int = 40, poll_every: int = 3) -> tuple[list, ...]:
    """Publish ``cycles`` of truth (and a telemetry frame after each) and tap both channels
    with a message listener, a record listener, a frame counter and a torque scorer."""
    clock = SimClock()
    n = next(_names)
    control = SimBus(channel=f"g{n}-control", clock=clock, trace_channel=CHANNEL_NUMBER["control"])
    control_tap = SimBus(channel=f"g{n}-control", clock=clock,
                         trace_channel=CHANNEL_NUMBER["control"])  # fmt: skip
    if grouped:
        truth_send = truth_tap = GroupChannel(clock, CHANNEL_NUMBER["truth"])
    else:
        truth_send = SimBus(channel=f"g{n}-truth", clock=clock, bitrate=0,
                            trace_channel=CHANNEL_NUMBER["truth"])  # fmt: skip
        truth_tap = SimBus(channel=f"g{n}-truth", clock=clock, bitrate=0,
                           trace_channel=CHANNEL_NUMBER["truth"])  # fmt: skip
    publisher = TruthPublisher(truth_send)  # type: ignore[arg-type]
    collect, records, counter, scorer = Collect(), Records(), FrameCounter(), TorqueScorer()
    tap = BusTap({CHANNEL_NUMBER["control"]: control_tap, CHANNEL_NUMBER["truth"]: truth_tap},
                 [records, collect, counter, scorer])  # fmt: skip
    try:
        for k in range(cycles):
            clock.now = k * 1e-3
            clock.horizon = (k + 1) * 1e-3
            publisher.publish(_truth(k))
            data = TELEMETRY.encode(0.1 * k, 0.2 * k, 1.0, 0.5)
            control.send(
                can.Message(arbitration_id=TELEMETRY.frame_id, is_extended_id=False, data=data)
            )
            if k % poll_every == 0:
                tap.poll()
        tap.poll()
    finally:
        for bus in (control, control_tap, truth_send, truth_tap):
            bus.shutdown()
    frames = [(m.timestamp, m.channel, m.arbitration_id, m.is_extended_id, m.is_remote_frame,
               m.is_error_frame, m.is_rx, m.dlc, type(m.data), bytes(m.data), m.is_fd,
               m.bitrate_switch, m.error_state_indicator) for m in collect.frames]  # fmt: skip
    return frames, records.data, counter.counts, scorer.result(), truth_send.frames_sent


def test_a_group_channel_hands_every_listener_what_a_simulated_bus_delivers():
    frames, records, counts, score, sent = _run(grouped=True)
    frames_bus, records_bus, counts_bus, score_bus, sent_bus = _run(grouped=False)
    assert len(frames) == 40 * 4
    assert frames == frames_bus  # order, timestamps, channels, every field
    assert records == records_bus  # the trace writer's bytes
    assert counts == counts_bus
    assert score == score_bus and score.samples == 40
    assert sent == sent_bus == 120


def test_groups_are_stamped_like_a_channel_without_a_wire():
    clock = SimClock()
    channel = GroupChannel(clock, 1)
    clock.now = 0.002
    channel.send_group((1, 2), True, (b"a", b"b"))
    clock.now = 0.001  # a clock set back: never before the previous delivery
    channel.send_group((3,), False, (b"c",))
    batch: list = []
    assert channel.drain_into(batch) == 2 and channel.drain_into(batch) == 0
    assert [g.timestamp for g in batch] == [0.002, 0.002]
    assert channel.frames_sent == 3
    messages = expand_groups([batch[0], "x", batch[1]])
    assert [getattr(m, "arbitration_id", m) for m in messages] == [1, 2, "x", 3]
    assert [m.is_extended_id for m in group_messages(batch[1])] == [False]


def test_a_tap_refuses_a_group_channel_under_another_channel_number():
    with pytest.raises(ValueError, match="tapped as channel"):
        BusTap({0: GroupChannel(SimClock(), 1)}, [])


def test_the_scorer_ignores_a_group_without_the_truth_torque_frame():
    scorer = TorqueScorer()
    scorer.on_frames([FrameGroup(0.0, 1, (0x1F0002,), True, (bytes(8),))])
    assert scorer._T_true is None

"""CanNode's dispatch on simbus: frames routed by identifier straight to their handler
reach what ``on_message`` would give them, an override's intercepted identifiers and
error frames still go through it, and a handler registered during a poll takes the
next frames of that poll."""

from __future__ import annotations

import can
import pytest

from hdhil.can.node import CanNode
from hdhil.can.simbus import SimClock


@pytest.fixture
def buses():
    clock = SimClock()
    tx = can.Bus(interface="simbus", channel="t-node", clock=clock, bitrate=0)  # in order sent
    rx = can.Bus(interface="simbus", channel="t-node")
    yield tx, rx
    tx.shutdown()
    rx.shutdown()


class _Intercepting(CanNode):
    """An override that consumes 0x100 before the table (as CANopen services do)."""

    def __init__(self, bus: can.BusABC, says: bool) -> None:
        super().__init__(bus)
        self.says = says
        self.intercepted: list[int] = []

    def intercepted_ids(self) -> frozenset[int] | None:
        return frozenset({0x100}) if self.says else None

    def on_message(self, msg: can.Message) -> None:
        if msg.arbitration_id == 0x100 and not msg.is_extended_id:
            self.intercepted.append(msg.arbitration_id)
            return
        CanNode.on_message(self, msg)


def _send_all(tx: can.BusABC) -> None:
    for can_id, ext, err in ((0x100, False, False), (0x180, False, False),
                             (0x180, False, True), (0x180, True, False),
                             (0x181, False, False), (0x180, False, False),
                             (0x7E5, False, False)):  # fmt: skip
        tx.send(can.Message(arbitration_id=can_id, is_extended_id=ext, is_error_frame=err,
                            data=b"\x01"))  # fmt: skip


def _poll_once(tx: can.BusABC, rx: can.BusABC, says: bool, routed: bool) -> tuple:
    node = _Intercepting(rx, says)
    if not routed:
        node._dispatch_routed = None  # the plain path: every frame via on_message
    got: list[tuple[str, int, bool]] = []
    node.handle(0x180, lambda m: got.append(("a", m.arbitration_id, m.is_extended_id)))
    node.handle(0x100, lambda m: got.append(("table", m.arbitration_id, False)))

    def register(msg: can.Message) -> None:
        got.append(("b", msg.arbitration_id, msg.is_extended_id))
        node.unhandle(0x180)  # takes effect for the frames after this one
        node.handle(0x181, lambda m: got.append(("c", m.arbitration_id, False)))

    node.handle(0x180, register, extended=True)
    _send_all(tx)
    assert node.poll() == 7
    return got, node.intercepted, node.error_frames, node.unknown_frames


@pytest.mark.parametrize("says", [True, False])
def test_routed_frames_reach_what_on_message_gives_them(buses, says):
    tx, rx = buses
    plain = _poll_once(tx, rx, says, routed=False)
    assert _poll_once(tx, rx, says, routed=True) == plain
    got, intercepted, errors, unknown = plain
    assert intercepted == [0x100] and errors == 1
    assert unknown == {0x180: 1, 0x7E5: 1}  # 0x180 no longer handled
    assert got == [("a", 0x180, False), ("b", 0x180, True), ("c", 0x181, False)]

"""The one node loop (hdhil.rig.loop) on a non-simulated bus: a drive that goes silent
costs each cycle the cycle timeout, the controller's sensor hold takes it to "safe", and
the run ends with a one-line error that says so."""

from __future__ import annotations

import pytest
from runs import lockstep

from hdhil.hostsim.drive import DriveNode
from hdhil.rig import loop
from hdhil.rig.factories import NodeSite, scenario_drive
from hdhil.rig.phases import SilentPeerError
from hdhil.rig.scenario import load_scenario


def test_a_drive_that_goes_silent_ends_a_virtual_bus_run_with_the_reason(monkeypatch):
    monkeypatch.setattr(loop, "CYCLE_TIMEOUT_S", 0.05)  # keep the test short
    scenario = load_scenario("free-motion")
    emulator = scenario_drive(scenario)

    def falls_silent(site: NodeSite) -> DriveNode:
        drive = emulator(site)
        send = site.bus.send

        def send_until(msg, timeout=None):
            if drive.diagnostics.sensor_frames < 50:
                send(msg, timeout)

        site.bus.send = send_until  # type: ignore[method-assign]
        return drive

    with pytest.raises(SilentPeerError, match="went silent"):
        lockstep(scenario, duration_s=1.0, interface="virtual", evaluate=False,
                     drive_factories=[falls_silent])  # fmt: skip


class _WaitingProducer:
    """A SYNC producer on a python-can virtual bus whose peer never answers: it records
    the times its timers ran (where its heartbeat would go out)."""

    def __init__(self) -> None:
        import can

        self.bus = can.Bus(interface="virtual", channel="hdhil-test-timers")
        self.ticks: list[float] = []

    def boot(self, now: float) -> None:
        pass

    def tick(self, now: float) -> None:
        self.ticks.append(now)

    def poll(self) -> int:
        return 0

    def on_message(self, msg: object) -> None:
        pass

    def send_sync(self) -> bool:
        return True


def test_the_timers_run_while_a_cycle_waits_for_its_answer() -> None:
    """A cycle that waits for an answer (up to its timeout) keeps running the nodes'
    timers every TIMER_SLICE_S: a controller's heartbeat does not stop while its drive is
    slow to answer, so the drive does not time the controller out (CiA 301 heartbeat
    consumer, 250 ms) at the end of a session."""
    node = _WaitingProducer()
    try:
        nl = loop.NodeLoop([node], producer=node, answers=lambda: 0, timeout_s=0.3)  # type: ignore[list-item]
        nl.cycle()
    finally:
        node.bus.shutdown()
    assert nl.timeouts == 1
    gaps = [b - a for a, b in zip(node.ticks[:-1], node.ticks[1:], strict=True)]
    assert len(node.ticks) >= 10 and max(gaps) < 0.1, gaps


class _Echo:
    """A CanNode-like node on a simulated bus: as producer it sends SYNC; on SYNC it
    answers with a PDO, and on that PDO the other node sends a command (a cycle of
    three frames per bus, each frame requested on receiving the one before)."""

    def __init__(self, bus, answers: dict[int, int], sync: bool) -> None:
        self.bus = bus
        self.answers = answers
        self.sync = sync
        self.got: list[tuple[int, float]] = []

    def boot(self, now: float) -> None:
        pass

    def tick(self, now: float) -> None:
        pass

    def poll(self) -> int:
        return self.bus.dispatch(self.on_message)

    def on_message(self, msg) -> None:
        import can

        self.got.append((msg.arbitration_id, msg.timestamp))
        reply = self.answers.get(msg.arbitration_id)
        if reply is not None:
            self.bus.send(can.Message(arbitration_id=reply, data=bytes(8), is_extended_id=False))

    def send_sync(self) -> bool:
        import can

        self.bus.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        return True


def test_several_simulated_buses_complete_every_cycle_each_on_its_own_wire() -> None:
    """A rig of two buses in one process: each bus's SYNC starts its cycle, the frames
    each node requests on receiving one are handled in the same cycle on both buses, and
    each bus's frames are timed on its own wire (the second bus at half the bit rate
    takes twice as long)."""
    from hdhil.can.simbus import SimBus, SimClock

    clock = SimClock()
    nodes, pumps = [], []
    for name, bitrate in (("a", 1_000_000), ("b", 500_000)):
        channel = f"hdhil-test-buses-{name}"
        master = _Echo(SimBus(channel=channel, clock=clock, bitrate=bitrate), {0x181: 0x201}, True)
        slave = _Echo(SimBus(channel=channel, clock=clock, bitrate=bitrate), {0x080: 0x181}, False)
        nodes += [master, slave]
        pumps.append((master, master.bus))
    try:
        nl = loop.NodeLoop(nodes, producer=pumps[0][0], sim_clock=clock, node_time=None,
                           pump=pumps[0][1], more_buses=pumps[1:])  # fmt: skip
        for _ in range(3):
            nl.cycle()
    finally:
        for node in nodes:
            node.bus.shutdown()
    for master, slave in (nodes[0:2], nodes[2:4]):
        # every cycle: the slave got SYNC and the command, the master the PDO
        assert [i for i, _ in slave.got] == [0x080, 0x201] * 3
        assert [i for i, _ in master.got] == [0x181] * 3
    # the command ends at the same place in each cycle, twice as late on the slower bus
    end_a = nodes[1].got[1][1]
    end_b = nodes[3].got[1][1]
    assert end_b == pytest.approx(2 * end_a)
    assert nodes[1].got[3][1] == pytest.approx(1e-3 + end_a)  # the second cycle's


def test_more_buses_need_the_first_pump() -> None:
    with pytest.raises(ValueError, match="first one's pump"):
        loop.NodeLoop([], node_time=None, sim_clock=object(), more_buses=[(object(), object())])  # type: ignore[list-item,arg-type]

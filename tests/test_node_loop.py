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

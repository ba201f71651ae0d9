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

"""Every EDS DefaultValue is the value the node boots with, as a third-party master sees it.

canopen's ``RemoteNode`` built from the project's EDS uploads every readable object of the
booted drive and controller (PRE-OPERATIONAL, default configuration) with its own SDO
client, and each answer must equal the EDS default byte for byte, as a master that checks
a device against its EDS would require.  The objects whose boot value is the node's state,
not a parameter, are listed in ``LIVE`` with the reason.  Simulated time on ``simbus``: the
master's network lets the nodes answer on every send.
"""

from __future__ import annotations

from collections.abc import Callable

import can
import canopen
import pytest
from canopen.objectdictionary import ODVariable
from conftest import BusHarness

from hdhil.dbc import eds_path
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.controller import ControllerNode
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant, PlantConfig

#: (node, index, sub) -> why its boot value is not the EDS default.
LIVE: dict[tuple[str, int, int], str] = {
    ("drive", 0x6041, 0): (
        "statusword: the CiA 402 state machine's state (SWITCH ON DISABLED once the drive "
        "has initialised); the EDS default 0 is NOT READY TO SWITCH ON"
    ),
}

NODES: dict[str, tuple[int, Callable[[can.BusABC], object]]] = {
    "drive": (2, lambda bus: DriveNode(bus, Plant(PlantConfig()), DriveConfig())),
    "controller": (1, lambda bus: ControllerNode(bus, FirmwareConfig())),
}


class PumpedNetwork(canopen.Network):
    """canopen's network without threads: each send lets the harness's nodes answer."""

    def __init__(self, bus: can.BusABC, harness: BusHarness) -> None:
        super().__init__(bus)
        self.harness = harness

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        super().send_message(can_id, data, remote)
        self.harness.pump()
        while (msg := self.bus.recv(0)) is not None:
            self.notify(msg.arbitration_id, msg.data, msg.timestamp)


def _variables(node: canopen.RemoteNode) -> list[ODVariable]:
    out: list[ODVariable] = []
    for obj in node.object_dictionary.values():
        out += [obj] if isinstance(obj, ODVariable) else list(obj.values())
    return out


def _boot_values(name: str) -> tuple[list[ODVariable], dict[tuple[int, int], bytes]]:
    node_id, make = NODES[name]
    with BusHarness(f"t-od-{name}") as harness:
        node = harness.add(make(harness.bus()))
        node.boot(0.0)
        harness.pump()
        network = PumpedNetwork(harness.bus(), harness)
        master = canopen.RemoteNode(node_id, str(eds_path(name)))
        network.add_node(master)
        variables = [v for v in _variables(master) if v.readable]
        uploaded = {
            (v.index, v.subindex): master.sdo.upload(v.index, v.subindex) for v in variables
        }
    return variables, uploaded


@pytest.mark.parametrize("name", sorted(NODES))
def test_every_readable_object_boots_with_its_eds_default(name):
    variables, uploaded = _boot_values(name)
    assert len(variables) > 50
    mismatches = []
    for var in variables:
        key = (var.index, var.subindex)
        if (name, *key) in LIVE:
            continue
        expected = None if var.default is None else var.encode_raw(var.default)
        if uploaded[key] != expected:
            got = var.decode_raw(uploaded[key])
            mismatches.append(f"0x{key[0]:04X}:{key[1]:02X} {var.name}: EDS {var.default!r}, "
                              f"node {got!r}")  # fmt: skip
    assert mismatches == []


def test_the_live_objects_exist_and_are_readable():
    for name, index, sub in LIVE:
        od = canopen.import_od(str(eds_path(name)), NODES[name][0])
        var = od[index] if isinstance(od[index], ODVariable) else od[index][sub]
        assert var.readable, (name, hex(index))


def test_motor_rated_torque_is_the_default_plants_full_scale_command():
    """0x6076 boots as torque_per_volt x the DAC's full scale: 60000 mNm, the EDS default."""
    _, uploaded = _boot_values("drive")
    plant = Plant(PlantConfig())
    rated_mNm = round(PlantConfig().torque_per_volt * plant.dac.full_scale_V * 1e3)
    assert int.from_bytes(uploaded[(0x6076, 0)], "little") == rated_mNm == 60000

"""The firmware as a CANopen master configuring its drive at boot from a DCF (CiA 306):
the DCF's values reach the drive by SDO before NMT start, in the CiA 301 order for PDOs,
and a value the drive refuses stops the controller with the abort code and its text."""

from __future__ import annotations

import pytest
from conftest import BusHarness

from hdhil.canopen.dcf import configuration_writes
from hdhil.dbc import eds_path
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.controller import ControllerNode
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant, PlantConfig

Ts = 1e-3


def _dcf(tmp_path, values: dict[str, str]):
    """drive.eds with ParameterValue lines for the given sections."""
    text = eds_path("drive").read_text()
    for section, value in values.items():
        head = f"[{section}]\n"
        assert head in text, section
        i = text.index(head) + len(head)
        text = text[:i] + f"ParameterValue={value}\n" + text[i:]
    path = tmp_path / "drive.dcf"
    path.write_text(text)
    return path


def _run(dcf, cycles: int = 400):
    with BusHarness("t-dcf", period_s=Ts) as harness:
        ctrl = harness.add(ControllerNode(harness.bus(), FirmwareConfig(), drive_dcf=dcf),
                           sync=True)  # fmt: skip
        drive = harness.add(DriveNode(harness.bus(), Plant(PlantConfig()), DriveConfig()))
        ctrl.boot(0.0)
        drive.boot(0.0)
        for _ in range(cycles):
            if harness.cycle(stop=lambda: ctrl.phase in ("stopped", "safe")) is None:
                break
        return ctrl, drive


@pytest.mark.slow
def test_dcf_values_reach_the_drive_before_nmt_start(tmp_path):
    dcf = _dcf(tmp_path, {"1801sub5": "50", "605A": "5", "1A01sub0": "1"})
    writes = configuration_writes(dcf, 2)
    # PDO order (CiA 301): not valid, parameters, mapping 0, entries, mapping n, valid.
    tpdo2 = [(i, s) for i, s, _ in writes if i in (0x1801, 0x1A01)]
    assert tpdo2 == [(0x1801, 1), (0x1801, 5), (0x1A01, 0), (0x1A01, 0), (0x1801, 1)]
    assert writes[0][:2] == (0x605A, 0)
    ctrl, drive = _run(dcf)
    assert ctrl.diagnostics.dcf_writes == len(writes)
    assert ctrl.phase == "operational"
    assert drive.services.read(0x1801, 5) == 50
    assert drive.services.read(0x605A) == 5
    assert drive.state_machine.quick_stop_option == 5


def test_a_value_the_drive_refuses_stops_the_controller_with_the_abort(tmp_path):
    dcf = _dcf(tmp_path, {"1800sub2": "245"})  # reserved transmission type
    ctrl, _ = _run(dcf, cycles=100)
    assert ctrl.phase == "safe"
    assert ctrl.boot_error is not None
    assert "0x1800:02" in ctrl.boot_error and "0x06090030" in ctrl.boot_error


def test_a_dcf_that_cannot_be_read_is_refused_at_start_up(tmp_path):
    bad = tmp_path / "bad.dcf"
    bad.write_text("[1000]\nParameterName=x\nObjectType=0x7\nDataType=0x0009\n"
                   "AccessType=rw\nDefaultValue=abc\nParameterValue=a long string\n")  # fmt: skip
    with pytest.raises(ValueError, match=r"needs \d+ bytes"):
        configuration_writes(bad, 2)


@pytest.mark.realtime
def test_hdhil_firmware_configures_a_served_drive_from_its_dcf(tmp_path, serve_drive, capsys):
    import json

    from hdhil.cli import main

    dcf = _dcf(tmp_path, {"1801sub5": "40", "605A": "6"})
    drive, bus_args = serve_drive(lambda bus: DriveNode(bus, Plant(PlantConfig()), DriveConfig()))
    code = main(["firmware", *bus_args, "--lockstep", "--duration", "0.2", "--drive-dcf", str(dcf)])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0 and out["phase"] == "stopped"
    assert drive.services.read(0x1801, 5) == 40
    assert drive.services.read(0x605A) == 6
    bad = tmp_path / "bad.dcf"
    bad.write_text("not an ini file")
    assert (
        main(["firmware", *bus_args, "--lockstep", "--duration", "0.1", "--drive-dcf", str(bad)])
        == 2
    )
    assert "hdhil: error:" in capsys.readouterr().err

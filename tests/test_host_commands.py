"""hdhil sdo and hdhil nmt against a drive node served in real time on python-can's virtual bus."""

from __future__ import annotations

import time

import pytest

from hdhil.cli import main
from hdhil.firmware.config import FirmwareConfig
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant
from hdhil.rig.scenario import load_scenario


@pytest.fixture
def drive(serve_drive):
    sc = load_scenario("free-motion")
    fw = FirmwareConfig()
    return serve_drive(
        lambda bus: DriveNode(
            bus, Plant(sc.plant, 1), DriveConfig(sample_period_s=fw.sample_period_s)
        )
    )


def test_sdo_read_and_write_through_the_cli(drive, capsys):
    _node, bus = drive
    assert main(["sdo", "read", "2", "0x1017", *bus]) == 0
    assert capsys.readouterr().out.strip() == "100"  # producer heartbeat, ms
    assert main(["sdo", "write", "2", "0x2300:1", "0.3", *bus]) == 0
    assert main(["sdo", "read", "2", "0x2300:1", *bus]) == 0
    assert float(capsys.readouterr().out.strip().splitlines()[-1]) == pytest.approx(0.3)


@pytest.mark.parametrize(
    ("args", "code"),
    [(["write", "2", "0x2300:1", "50"], "0x06090031"),
     (["write", "2", "0x2300:1", "-1"], "0x06090032"),
     (["write", "2", "0x6041", "1"], "0x06010002"),
     (["read", "2", "0x5FFF"], "0x06020000")],
)  # fmt: skip
def test_sdo_aborts_are_one_line_errors(drive, capsys, args, code):
    _node, bus = drive
    assert main(["sdo", *args, *bus]) == 2
    err = capsys.readouterr().err.strip()
    assert code in err and "Traceback" not in err and len(err.splitlines()) == 1


def _wait_state(node: DriveNode, name: str) -> str:
    deadline = time.monotonic() + 2
    while node.nmt_state.name != name and time.monotonic() < deadline:
        time.sleep(0.01)
    return node.nmt_state.name


def test_nmt_start_and_stop_through_the_cli(drive):
    node, bus = drive
    assert _wait_state(node, "PRE_OPERATIONAL") == "PRE_OPERATIONAL"
    assert main(["nmt", "start", "2", *bus]) == 0
    assert _wait_state(node, "OPERATIONAL") == "OPERATIONAL"
    assert main(["nmt", "stop", "2", *bus]) == 0
    assert _wait_state(node, "STOPPED") == "STOPPED"


def test_sdo_write_to_an_object_the_eds_lacks_is_a_clear_error(drive, capsys):
    _node, bus = drive
    assert main(["sdo", "write", "2", "0x5FFF", "1", *bus]) == 2
    err = capsys.readouterr().err.strip()
    assert "0x5FFF" in err and "Traceback" not in err and len(err.splitlines()) == 1


def test_sdo_to_a_silent_node_times_out_cleanly(capsys):
    bus = ["--interface", "virtual", "--channel", f"hdhil-silent-{time.monotonic_ns()}"]
    assert main(["sdo", "read", "2", "0x1017", *bus, "--timeout", "0.2"]) == 2
    err = capsys.readouterr().err
    assert "0x05040000" in err and "Traceback" not in err

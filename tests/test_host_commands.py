"""hdhil sdo and hdhil nmt against a drive node served in real time on python-can's virtual bus."""

from __future__ import annotations

import time

import can
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
    """No answer is the system's doing, not the input's: exit 1 (not 2), one line."""
    bus = ["--interface", "virtual", "--channel", f"hdhil-silent-{time.monotonic_ns()}"]
    assert main(["sdo", "read", "2", "0x1017", *bus, "--timeout", "0.2"]) == 1
    err = capsys.readouterr().err.strip()
    assert "0x05040000" in err and "did not answer within 0.2 s" in err
    assert err.startswith("hdhil: sdo read 0x1017:00") and len(err.splitlines()) == 1


class _UnacknowledgedBus(can.BusABC):
    """A bus on which no node acknowledges a frame: every send times out, as a real
    controller's transmit queue does with nobody else on the bus."""

    def __init__(self) -> None:
        super().__init__(channel="unacknowledged")
        self.timeouts: list[float | None] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.timeouts.append(timeout)
        raise can.CanOperationError("Transmit buffer full")

    def _recv_internal(self, timeout):
        return None, False


def test_nmt_that_no_node_acknowledges_exits_1(monkeypatch, capsys):
    from hdhil.commands import netcmd

    bus = _UnacknowledgedBus()
    monkeypatch.setattr(netcmd, "_control_bus", lambda args: bus)
    assert main(["nmt", "start", "2", "--interface", "virtual", "--timeout", "0.3"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("hdhil: nmt start node 2: the command was not sent within 0.3 s")
    assert "Transmit buffer full" in err and len(err.splitlines()) == 1
    assert bus.timeouts == [0.3]


@pytest.mark.parametrize(
    "argv",
    [["sdo", "read", "2", "0x1017", "-i", "simbus"],
     ["nmt", "start", "2", "--interface", "simbus"],
     ["emulate", "--interface", "simbus"],
     ["emulate", "-i", "virtual", "--truth-interface", "simbus"],
     ["firmware", "-i", "simbus"],
     ["log", "x.blf", "--interface", "simbus"]],
    ids=lambda argv: "-".join(a for a in argv if a.isalpha() or a == "simbus"),
)  # fmt: skip
def test_the_in_process_simbus_is_refused_between_processes(argv, capsys):
    """simbus lives inside one process: a node alone on it would wait for peers that can
    never join. One line, exit 2, at once."""
    t0 = time.monotonic()
    assert main(argv) == 2
    assert time.monotonic() - t0 < 1.0  # refused before anything waits
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"hdhil: error: {argv[0]}: ") and len(err.splitlines()) == 1
    assert "simbus" in err and "hdhil run" in err and "udp_multicast" in err

"""``hdhil conformance``: the suite passes against the emulated drive (in-process on
simbus, and as two processes over udp_multicast in a network namespace), and finds the
defects planted in a deliberately broken slave built with canopen's ``LocalNode``."""

from __future__ import annotations

import contextlib
import signal
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from typing import ClassVar

import can
import canopen
import pytest
from test_multiprocess import _hdhil

from hdhil.cli import main
from hdhil.conformance import Options, run_suite
from hdhil.dbc import eds_path
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant, PlantConfig
from hdhil.rig.loop import serve

GROUP = "239.74.163.25"


@contextlib.contextmanager
def _served(interface: str) -> Iterator[str]:
    """The emulated drive served in real time on a fresh channel of ``interface``, as
    ``hdhil emulate`` serves it; the channel's name."""
    channel = f"conformance-{time.monotonic_ns()}"
    bus = can.Bus(interface=interface, channel=channel, bitrate=0)
    node = DriveNode(bus, Plant(PlantConfig()), DriveConfig())
    stop = threading.Event()

    def run() -> None:
        node.boot(time.monotonic())
        serve(node, stop.is_set)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield channel
    finally:
        stop.set()
        thread.join(5)
        bus.shutdown()


@pytest.fixture
def drive_channel() -> Iterator[str]:
    """The emulated drive on a simbus channel (the suite's own tests, in-process)."""
    with _served("simbus") as channel:
        yield channel


@pytest.fixture
def virtual_drive_channel() -> Iterator[str]:
    """The emulated drive on a python-can ``virtual`` channel: the command refuses
    simbus, which has no peer outside its process."""
    with _served("virtual") as channel:
        yield channel


def _suite(channel: str, **options):
    bus = can.Bus(interface="simbus", channel=channel, bitrate=0)
    try:
        od = canopen.import_od(str(eds_path("drive")), 2)
        return run_suite(bus, od, Options(**options), "drive.eds")
    finally:
        bus.shutdown()


def _status(result, name: str) -> str:
    hits = [o for o in result.outcomes if o.case.name.startswith(name)]
    assert hits, name
    return hits[0].status


@pytest.mark.slow
@pytest.mark.realtime
def test_every_case_passes_against_the_emulated_drive_in_process(drive_channel):
    result = _suite(drive_channel)
    failed = [f"{o.case.name}: {o.detail}" for o in result.outcomes
              if o.status in ("fail", "error")]  # fmt: skip
    assert failed == []
    assert len(result.outcomes) >= 120
    assert result.count("pass") >= 120
    # Every readable object of the EDS was uploaded and compared with its default.
    od = canopen.import_od(str(eds_path("drive")), 2)
    n_vars = sum(1 if isinstance(o, canopen.objectdictionary.ODVariable) else len(o)
                 for o in od.values())  # fmt: skip
    assert sum(o.case.group == "objects" for o in result.outcomes) == 2 * n_vars
    assert result.seconds < 15
    # Object dictionary consistency (#25 item 6): the boot value of 0x6076 equals its EDS
    # default, and a stray upload segment is answered with abort 0x05040001.
    assert _status(result, "0x6076:00 motor_rated_torque: boot value") == "pass"
    assert _status(result, "§7.2.4.3.17 upload segment, no transfer") == "pass"


@pytest.mark.slow
@pytest.mark.realtime
def test_command_writes_junit_and_exits_0(virtual_drive_channel, tmp_path, capsys):
    junit = tmp_path / "conformance.xml"
    code = main(["conformance", "--interface", "virtual", "--channel", virtual_drive_channel,
                 "--only", "nmt,sdo", "--no-motion", "--junit", str(junit)])  # fmt: skip
    out = capsys.readouterr().out
    assert code == 0, out
    assert "0 failed" in out
    root = ET.parse(junit).getroot()
    assert root.tag == "testsuites" and root.get("failures") == "0"
    assert {s.get("name") for s in root} == {"nmt", "sdo"}
    assert int(root.get("tests")) == sum(int(s.get("tests")) for s in root) > 40


@pytest.mark.slow
@pytest.mark.realtime
def test_no_motion_never_commands_enable_operation(drive_channel):
    bus = can.Bus(interface="simbus", channel=drive_channel, bitrate=0)
    words: list[int] = []

    class Spy(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            data = msg.data
            if msg.arbitration_id == 0x602 and data[0] & 0xE0 == 0x20 and data[1:3] == b"\x40\x60":
                words.append(int.from_bytes(data[4:6], "little"))

    spy_bus = can.Bus(interface="simbus", channel=drive_channel, bitrate=0)
    notifier = can.Notifier(spy_bus, [Spy()], 0.05)
    try:
        od = canopen.import_od(str(eds_path("drive")), 2)
        result = run_suite(bus, od, Options(motion=False, only=("cia402",)), "drive.eds")
    finally:
        notifier.stop()
        spy_bus.shutdown()
        bus.shutdown()
    assert result.ok
    assert words and 0x0F not in words and not any(w & 0x0F == 0x0F for w in words)
    assert _status(result, "transition 4") == "skip"


@pytest.mark.slow
def test_no_node_on_the_bus_fails_every_case_after_one_boot_wait(capsys):
    """Nobody answers: one wait for the boot-up, then every case fails at once (exit 1)."""
    start = time.monotonic()
    channel = f"nobody-{time.monotonic_ns()}"
    code = main(["conformance", "--interface", "virtual", "--channel", channel,
                 "--only", "nmt,objects"])  # fmt: skip
    out = capsys.readouterr().out
    assert code == 1
    assert "the node never booted; group set-up: no boot-up message (0x702 00)" in out
    assert time.monotonic() - start < 10
    # one line per group for the cases failed for one reason, not one per case
    fails = [line for line in out.splitlines() if line.startswith("  FAIL")]
    assert len(fails) == 2, out
    assert fails[0].startswith("  FAIL 16 cases from ") and " cases from 0x1000:00 " in fails[1]


@pytest.mark.parametrize(
    "argv",
    [
        ["--only", "bogus"],
        ["--skip", "nmt,nope"],
        ["--eds", "/nonexistent/drive.eds"],
        ["--master-id", "2"],
        ["--interface", "simbus"],  # no peer outside this process: refused, not waited on
    ],
)
def test_bad_input_exits_2_with_one_line(argv, capsys):
    assert main(["conformance", "--interface", "virtual", "--channel", "x", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hdhil: error: ") and err.count("\n") == 1


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.netns
@pytest.mark.realtime
def test_every_case_passes_against_hdhil_emulate_over_udp_multicast(netns, tmp_path):
    bus = ["--interface", "udp_multicast", "--channel", GROUP]
    emulator = _hdhil(netns, "emulate", *bus)
    try:
        time.sleep(1.5)
        junit = tmp_path / "udp.xml"
        suite = _hdhil(netns, "conformance", *bus, "--junit", str(junit))
        out, err = suite.communicate(timeout=180)
        assert suite.returncode == 0, out + err
        root = ET.parse(junit).getroot()
        assert int(root.get("tests")) >= 120 and root.get("failures") == "0"
    finally:
        emulator.send_signal(signal.SIGTERM)
        emulator.communicate(timeout=20)


# ------------------------------------------------------------------ a broken slave
class BrokenSlave:
    """A drive built on canopen's ``LocalNode`` from the drive's EDS, with the NMT slave,
    heartbeat producer and a CiA 402 state machine written here, and the defects asked
    for: ``od_edit`` changes its object dictionary (a default that differs from the EDS
    the suite reads), ``heartbeat_factor`` stretches its heartbeat period, ``broken_6``
    makes shutdown in SWITCHED ON go to SWITCH ON DISABLED (transition 6 broken).
    canopen's LocalNode checks no LowLimit/HighLimit: its missing aborts are a defect of
    its own."""

    STATES: ClassVar[dict[str, int]] = {
        "SOD": 0x0240,
        "RTSO": 0x0221,
        "SO": 0x0223,
        "OE": 0x0227,
        "QSA": 0x0207,
    }

    def __init__(self, channel: str, od_edit=None, heartbeat_factor: float = 1.0,
                 broken_6: bool = False) -> None:  # fmt: skip
        od = canopen.import_od(str(eds_path("drive")), 2)
        if od_edit is not None:
            od_edit(od)
        self.bus = can.Bus(interface="simbus", channel=channel, bitrate=0)
        self.network = canopen.Network(self.bus)
        self.node = canopen.LocalNode(2, od)
        self.network.add_node(self.node)
        self.network.unsubscribe(0, self.node.nmt.on_command)
        self.network.subscribe(0, self._nmt)
        self.node.add_write_callback(self._written)
        self.network.notifier = can.Notifier(self.bus, self.network.listeners, 0.05)
        self.factor = heartbeat_factor
        self.broken_6 = broken_6
        self.state = 0x7F
        self._set_state("SOD")
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._beat, daemon=True)
        self.thread.start()
        self.network.send_message(0x702, b"\x00")

    def _set_state(self, name: str) -> None:
        self.pds = name
        self.node.data_store.setdefault(0x6041, {})[0] = self.STATES[name].to_bytes(2, "little")

    def _nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if data[1] not in (0, 2):
            return
        cs = data[0]
        if cs in (0x81, 0x82):
            if cs == 0x81:
                self.node.data_store.clear()
                self._set_state("SOD")
            self.state = 0x7F
            self.network.send_message(0x702, b"\x00")
        elif cs in (0x01, 0x02, 0x80):
            self.state = {0x01: 0x05, 0x02: 0x04, 0x80: 0x7F}[cs]

    def _written(self, index: int, subindex: int, od, data: bytes) -> None:
        if index != 0x6040:
            return
        word = int.from_bytes(data, "little")
        s = self.pds
        if word & 0x82 == 0:  # disable voltage
            self._set_state("SOD")
        elif word & 0x87 == 0x06:  # shutdown
            self._set_state("SOD" if (self.broken_6 and s == "SO") else "RTSO")
        elif word & 0x8F == 0x07 and s in ("RTSO", "SO", "OE"):
            self._set_state("SO")
        elif word & 0x8F == 0x0F and s in ("SO", "OE"):
            self._set_state("OE")
        elif word & 0x86 == 0x02:
            self._set_state("SOD")

    def _beat(self) -> None:
        while not self.stop.is_set():
            period = int.from_bytes(self.node.sdo.upload(0x1017, 0), "little")
            if period:
                self.network.send_message(0x702, bytes((self.state,)))
            self.stop.wait((period or 100) * 1e-3 * self.factor)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        self.network.notifier.stop()
        self.bus.shutdown()


def _against(slave_kwargs: dict, only: tuple[str, ...]):
    channel = f"broken-{time.monotonic_ns()}"
    slave = BrokenSlave(channel, **slave_kwargs)
    try:
        return _suite(channel, only=only)
    finally:
        slave.close()


def _wrong_max_torque(od) -> None:
    od[0x6072].default = 900


@pytest.mark.slow
@pytest.mark.realtime
def test_broken_slave_a_wrong_eds_default_is_found():
    result = _against({"od_edit": _wrong_max_torque}, ("objects",))
    assert _status(result, "0x6072:00 max_torque: boot value") == "fail"
    assert _status(result, "0x1000:00 Device type: boot value") == "pass"


@pytest.mark.slow
@pytest.mark.realtime
def test_broken_slave_a_missing_abort_is_found():
    result = _against({}, ("sdo",))
    # canopen's LocalNode stores a value above the EDS HighLimit instead of aborting.
    assert _status(result, "0x6072:00 max_torque: above HighLimit") == "fail"
    assert _status(result, "§7.2.4.3.3 expedited upload") == "pass"


@pytest.mark.slow
@pytest.mark.realtime
def test_broken_slave_a_wrong_heartbeat_period_is_found():
    result = _against({"heartbeat_factor": 1.3}, ("timing",))
    assert _status(result, "0x1017 heartbeat period accuracy") == "fail"
    good = _against({}, ("timing",))
    assert _status(good, "0x1017 heartbeat period accuracy") == "pass"


@pytest.mark.slow
@pytest.mark.realtime
def test_broken_slave_a_broken_402_transition_is_found():
    result = _against({"broken_6": True}, ("cia402",))
    assert _status(result, "transition 6") == "fail"
    assert _status(result, "transition 2") == "pass"
    assert _status(result, "transition 3") == "pass"

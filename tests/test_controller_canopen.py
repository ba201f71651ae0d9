"""The controller as CANopen NMT master, CiA 402 controlling device and SDO server.

Every test runs the controller in lockstep on ``simbus`` against a small scripted drive
(node 2): boot-up, NMT slave, heartbeat, sensor TPDO on SYNC, the CiA 402 state machine of
:mod:`hdhil.canopen.cia402` driven by the controlword of ``DRIVE_RPDO1`` (applied on receipt),
the statusword in ``DRIVE_TPDO2`` on change, and an SDO upload of 0x6041.  Faults (a lost
statusword, silence, a fault) are scripted, so the tests do not depend on the real
drive's timing.  SDO requests to the controller are hand-made frames (CiA 301 §7.2.4).
"""

from __future__ import annotations

import dataclasses
import math
import struct
from collections.abc import Callable

import can
import pytest
from conftest import BusHarness

from hdhil.canopen.cia402 import DriveStateMachine, State
from hdhil.canopen.services import load_od
from hdhil.dbc import codec, database, eds_path
from hdhil.firmware.config import (
    FirmwareConfig,
    Law,
    PlausibilityConfig,
    ReferenceConfig,
    Wave,
    paper_config,
)
from hdhil.firmware.controller import PARAMETERS, ControllerNode

TS = 1e-3
SENSOR = codec("control", "DRIVE_TPDO1")
COMMAND = codec("control", "DRIVE_RPDO1")
STATUS = codec("control", "DRIVE_TPDO2")
TELEMETRY = codec("control", "CTRL_TPDO1")


def f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


class FakeDrive:
    """A scripted CANopen drive, node-ID 2 (see the module docstring)."""

    def __init__(self, bus: can.BusABC, heartbeat_ms: int = 100) -> None:
        self.bus = bus
        self.nmt = 0x00  # INITIALISING until boot
        self.fsm = DriveStateMachine()
        self.fsm.complete_initialisation()
        self.heartbeat_s = heartbeat_ms / 1e3
        self.next_heartbeat = math.inf
        self.silent = False  # no frames at all (power loss)
        self.mute_heartbeat = False
        self.mute_sensor = False
        self.drop_statusword = 0  # statusword frames to lose
        self.ignore_controlword = False
        self.controlwords: list[int] = []
        self.dac: list[int] = []
        self.sample = 0
        #: The sensor frame's (torque, tacho, current, encoder) per sample; None: fixed.
        self.sensor: Callable[[int], tuple[int, int, int, int]] | None = None

    def _send(self, can_id: int, data: bytes) -> None:
        if not self.silent:
            self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def boot(self, now: float) -> None:
        self._send(0x702, b"\x00")
        self.nmt = 0x7F
        self.next_heartbeat = now + self.heartbeat_s

    def tick(self, now: float) -> None:
        if now + 1e-9 >= self.next_heartbeat:
            if not self.mute_heartbeat:
                self._send(0x702, bytes((self.nmt,)))
            self.next_heartbeat += self.heartbeat_s

    def fault(self, code: int = 0x2310, persists: bool = False) -> None:
        before = self.fsm.statusword
        self.fsm.fault(code, persists=persists)
        self._statusword_changed(before)

    def _statusword_changed(self, before: int) -> None:
        after = self.fsm.statusword
        if after == before or self.nmt != 0x05:
            return
        if self.drop_statusword:
            self.drop_statusword -= 1
            return
        self._send(STATUS.frame_id, STATUS.encode(after))

    def poll(self) -> int:
        n = 0
        while (msg := self.bus.recv(0)) is not None:
            n += 1
            can_id, data = msg.arbitration_id, bytes(msg.data)
            if can_id == 0x000 and data[1] in (0, 2):
                self.nmt = {0x01: 0x05, 0x02: 0x04, 0x80: 0x7F}.get(data[0], self.nmt)
            elif can_id == 0x080 and self.nmt == 0x05 and not self.mute_sensor:
                self.sample += 1
                values = (  # the torque wobbles a count: a live sensor, not a stuck one
                    (100 + (self.sample & 1), 20, 0, (7 * self.sample) & 0xFFFF)
                    if self.sensor is None
                    else self.sensor(self.sample)
                )
                self._send(SENSOR.frame_id, SENSOR.encode(*values))
            elif can_id == COMMAND.frame_id and self.nmt == 0x05:
                dac, cw, _ = COMMAND.decode(data)
                self.controlwords.append(cw)
                self.dac.append(dac)
                if not self.ignore_controlword:
                    before = self.fsm.statusword
                    self.fsm.apply_controlword(cw)
                    self._statusword_changed(before)
            elif can_id == 0x602 and data[:4] == b"\x40\x41\x60\x00" and self.nmt in (0x05, 0x7F):
                sw = struct.pack("<H", self.fsm.statusword)
                self._send(0x582, b"\x4b\x41\x60\x00" + sw + b"\x00\x00")
        return n


class Link(BusHarness):
    """Controller + fake drive on the shared bus harness (the controller sends SYNC); its
    host logs every frame and plays the SDO client."""

    def __init__(self, config: FirmwareConfig | None = None, **kwargs) -> None:
        super().__init__("t-ctrl-canopen")
        node_bus, drive_bus = self.bus(), self.bus()
        self.node = self.add(ControllerNode(node_bus, config or FirmwareConfig(), **kwargs),
                             sync=True)  # fmt: skip
        self.drive = self.add(FakeDrive(drive_bus))

    def boot(self, drive: bool = True) -> None:
        if drive:
            self.drive.boot(0.0)
        self.node.boot(0.0)

    def run_until(self, phase: str, limit: int = 5000) -> None:
        for _ in range(limit):
            if self.node.phase == phase:
                return
            self.cycle()
        raise AssertionError(f"phase {phase!r} not reached, still {self.node.phase}")

    # SDO client (expedited, by hand)
    def _request(self, data: bytes) -> bytes:
        self.host.send(can.Message(arbitration_id=0x601, data=data, is_extended_id=False))
        answers = [d for i, d in self.pump() if i == 0x581]
        assert len(answers) == 1, answers
        return answers[0]

    def download(self, index: int, sub: int, data: bytes) -> int | None:
        """Write 1..4 bytes; None on success, else the abort code."""
        command = 0x23 | ((4 - len(data)) << 2)
        answer = self._request(struct.pack("<BHB", command, index, sub) + data.ljust(4, b"\0"))
        assert struct.unpack_from("<HB", answer, 1) == (index, sub)
        if answer[0] == 0x80:
            return struct.unpack_from("<I", answer, 4)[0]
        assert answer[0] == 0x60
        return None

    def write_real(self, index: int, sub: int, value: float) -> int | None:
        return self.download(index, sub, struct.pack("<f", value))

    def upload(self, index: int, sub: int) -> bytes | int:
        """Read; the data bytes, or the abort code."""
        answer = self._request(struct.pack("<BHB4x", 0x40, index, sub))
        if answer[0] == 0x80:
            return struct.unpack_from("<I", answer, 4)[0]
        n = 4 - ((answer[0] >> 2) & 3)
        return answer[4 : 4 + n]

    def read_real(self, index: int, sub: int) -> float:
        return struct.unpack("<f", self.upload(index, sub))[0]


@pytest.fixture
def link():
    links: list[Link] = []

    def make(config: FirmwareConfig | None = None, **kwargs) -> Link:
        lk = Link(config, **kwargs)
        links.append(lk)
        return lk

    yield make
    for lk in links:
        lk.close()


def operational(make, config: FirmwareConfig | None = None, **kwargs) -> Link:
    lk = make(config, **kwargs)
    lk.boot()
    lk.run_until("operational", 50)
    return lk


def ids(frames) -> list[int]:
    return [f[-2] for f in frames]


def commands(frames) -> list[tuple[int, int]]:
    """(DAC, controlword) of the DRIVE_RPDO1 frames."""
    return [COMMAND.decode(f[-1])[:2] for f in frames if f[-2] == COMMAND.frame_id]


# ===================================================================== object dictionary


def test_parameter_objects_default_to_the_firmware_config_defaults():
    od = load_od(eds_path("controller"), 1)
    cfg = FirmwareConfig()
    for p in PARAMETERS:
        var = od[p.index][p.sub]
        assert var.name == p.name
        expected = p.get(cfg)
        if isinstance(expected, float):
            assert var.data_type == 0x8, p.name  # REAL32
            assert var.default == pytest.approx(f32(expected), rel=1e-6), p.name
        else:
            assert var.default == int(expected), p.name
        writable = p.put is not None
        assert (var.access_type == "rw") is writable, p.name
        if writable and p.name not in ("num_samples",):
            assert var.min is not None and var.max is not None, f"{p.name} has no limits"


def test_communication_objects_per_the_services_table():
    od = load_od(eds_path("controller"), 1)
    assert od[0x1001].access_type == "ro"
    assert [od[0x1003][s].access_type for s in range(9)] == ["rw"] + ["ro"] * 8
    assert od[0x1014].default == 0x81
    assert od[0x1016][0].default == 2 and od[0x1016][1].default == 0x000200FA
    assert od[0x1016][2].default == 0  # a second drive (a node serving two joints)
    assert od[0x1017].default == 100
    assert (od[0x1019].default, od[0x1019].min, od[0x1019].max) == (240, 0, 240)
    assert od[0x1029][1].default == 1
    # RPDO2: the drive's statusword, event-driven, as DRIVE_TPDO2 in the DBC.
    msg = database("control").get_message_by_name("DRIVE_TPDO2")
    assert od[0x1401][1].default == msg.frame_id == 0x282
    assert od[0x1401][2].default == 255
    assert od[0x1601][0].default == 1 and od[0x1601][1].default == 0x20110010
    var = od[0x2011]
    assert (var.name, var.data_type, var.pdo_mappable) == ("statusword", 0x6, True)
    (signal,) = msg.signals
    assert (signal.name, signal.length, signal.is_signed) == ("statusword", 16, False)


def test_sdo_segments_of_no_open_transfer_are_aborted(link):
    """CiA 301 §7.2.4.3.4: an upload or download segment with no such transfer open is
    answered with abort 0x05040001 (raw frames to the controller)."""
    lk = link()
    lk.boot()
    lk.pump()
    device_name = struct.pack("<BHB4x", 0x40, 0x1008, 0)
    for before, stray in [
        ([], b"\x60" + bytes(7)),
        ([], b"\x00" + bytes(7)),
        # "hdhil controller", 16 bytes: three segments, then none
        (
            [device_name, b"\x60" + bytes(7), b"\x70" + bytes(7), b"\x60" + bytes(7)],
            b"\x70" + bytes(7),
        ),
        ([device_name], b"\x00" + bytes(7)),
    ]:
        for request in before:
            lk._request(request)
        answer = lk._request(stray)
        assert (answer[0], struct.unpack_from("<I", answer, 4)[0]) == (0x80, 0x05040001)


def test_the_scenario_configuration_is_what_an_sdo_read_returns(link):
    cfg = FirmwareConfig(
        sample_period_s=5e-4,
        num_samples=1234,
        reference=ReferenceConfig(wave=Wave.STEP, amplitude_V=0.654296875, step_time_s=0.05),
    )
    from hdhil.firmware.config import paper_config

    cfg = paper_config(cfg)
    lk = link(cfg, sync_overflow=16)
    lk.boot()
    assert lk.upload(0x2400, 1) == b"\x04"
    assert lk.read_real(0x2400, 3) == f32(0.654296875)
    assert lk.read_real(0x2400, 6) == f32(0.05)
    assert lk.upload(0x2401, 1) == struct.pack("<I", 1234)
    assert lk.read_real(0x2401, 2) == f32(5e-4)
    assert lk.upload(0x2410, 1) == b"\x00"  # paper
    assert lk.read_real(0x2410, 2) == 1.0 and lk.read_real(0x2410, 5) == 1000.0
    assert lk.upload(0x1006, 0) == struct.pack("<I", 500)
    assert lk.upload(0x1019, 0) == b"\x10"
    assert lk.upload(0x1801, 1) == struct.pack("<I", 0x80000281)  # no law: not valid


# =========================================================================== boot


def test_boot_sends_the_boot_up_and_nothing_cyclic_before_it(link):
    lk = link()
    assert lk.node.phase == "wait-boot"
    assert lk.node.send_sync() is False  # INITIALISING: nothing on the bus
    lk.node.boot(0.0)
    lk.pump()
    assert ids(lk.log) == [0x701]
    assert lk.log[0][2] == b"\x00"
    with pytest.raises(RuntimeError):
        lk.node.boot(0.1)


def test_boot_timeout_gives_a_one_line_error_and_stops_the_sync(link):
    lk = link(boot_timeout_s=2.0)
    lk.boot(drive=False)
    frames = lk.run(2001)  # up to t = 2.000 s: still waiting (deadline not passed)
    assert lk.node.phase == "wait-boot" and lk.node.boot_error is None
    assert ids(frames).count(0x080) == 2001  # SYNC in PRE-OPERATIONAL while waiting
    frames = lk.run(1)
    assert lk.node.boot_error == (
        "drive (node 2) sent no boot-up within 2.0 s: check power, node-ID and bit rate"
    )
    assert "\n" not in lk.node.boot_error
    assert lk.node.phase == "safe"
    assert 0x080 not in ids(frames + lk.run(5))
    assert 0x202 not in ids(lk.log) and 0x000 not in ids(lk.log)


def test_nmt_start_on_the_drives_boot_up(link):
    lk = link()
    lk.boot()
    frames = lk.cycle()
    assert (0x000, b"\x01\x02") in frames  # NMT start remote node 2
    assert lk.node.phase == "starting"
    assert lk.node.services.state == 0x05  # the controller itself: OPERATIONAL
    assert lk.node.diagnostics.boot_time_s == 0.0
    lk.run(100)
    assert (0x701, b"\x05") in [(i, d) for _, i, d in lk.log]  # heartbeat: OPERATIONAL


def test_a_drive_that_booted_earlier_is_found_by_its_heartbeat(link):
    lk = link()
    lk.drive.boot(-0.05)  # booted before the controller: only its heartbeat is seen
    lk.drive.bus.recv(0)
    lk.node.bus.recv(0)
    lk.host.recv(0)
    lk.node.boot(0.0)
    lk.run(60)
    assert lk.node.phase == "operational"
    assert "heartbeat" in lk.node.diagnostics.phase_history[1].reason


# ====================================================================== CiA 402 walk


def test_start_up_walks_the_drive_to_operation_enabled_step_by_step(link):
    lk = link()
    lk.boot()
    states, cws = [], []
    for _ in range(6):
        frames = lk.cycle()
        cws.append([cw for _, cw in commands(frames)])
        states.append(lk.node.drive_state)
        if lk.node.phase == "operational":
            break
    # cycle 0: boot-up -> NMT start; 1: shutdown; 2: switch on; 3: enable operation
    assert cws == [[], [0x0006], [0x0007], [0x000F]]
    # cycle 0: the SDO read after NMT start finds SWITCH ON DISABLED
    assert states == [
        State.SWITCH_ON_DISABLED,
        State.READY_TO_SWITCH_ON,
        State.SWITCHED_ON,
        State.OPERATION_ENABLED,
    ]
    assert all(dac == 0 for dac in lk.drive.dac)  # DAC 0 while not operational
    d = lk.node.diagnostics
    assert d.startup_cycles == 3 and d.operational_at_s == pytest.approx(3 * TS)
    assert [c.phase for c in d.phase_history] == ["wait-boot", "starting", "operational"]
    assert lk.node.isr.samplecount == 0  # the handler has not run yet
    frames = lk.cycle()  # cycle 4: the first operational sample
    assert lk.node.isr.samplecount == 1
    assert [cw for _, cw in commands(frames)] == [0x000F]
    assert 0x181 in ids(frames)
    assert 0x181 not in ids(lk.log[: -len(frames)])  # no telemetry during the walk
    assert lk.node.services.read(0x6040) == 0x000F
    assert lk.node.services.read(0x2011) == lk.drive.fsm.statusword


def test_fault_at_start_up_is_reset_once_then_the_walk_goes_on(link):
    lk = link()
    lk.drive.fsm.fault(0x2310)  # the drive comes up in FAULT and never says so by PDO
    lk.boot()
    lk.run_until("operational", 20)
    # the SDO read after NMT start finds FAULT: reset (edge of bit 7), then the walk
    assert [cw for _, cw in commands(lk.log)] == [0x0080, 0x0006, 0x0007, 0x000F]
    d = lk.node.diagnostics
    assert (d.fault_resets, d.statusword_sdo_reads, d.startup_cycles) == (1, 1, 4)


@pytest.mark.slow
def test_fault_during_operation_resets_and_walks_again_a_second_one_is_safe(link):
    lk = operational(link)
    lk.run(5)
    samples = lk.node.isr.samplecount
    lk.drive.fault(0x2310)
    assert lk.node.phase == "operational"
    lk.pump()
    assert lk.node.phase == "starting"
    frames = lk.run(4)
    assert [cw for _, cw in commands(frames)][:1] == [0x0080]
    lk.run_until("operational", 20)
    assert lk.node.isr.samplecount == samples  # the handler paused during the walk
    lk.run(3)
    assert lk.node.isr.samplecount == samples + 3
    lk.drive.fault(0x2310)
    lk.pump()
    assert lk.node.phase == "safe"
    assert "drive fault again after a fault reset" in lk.node.diagnostics.safe_reason
    assert lk.log[-1][1:] == (0x000, b"\x80\x02")
    assert 0x202 not in ids(lk.run(5))


def test_a_refused_fault_reset_ends_in_safe(link):
    lk = operational(link)
    lk.drive.fault(0x2310, persists=True)
    lk.pump()
    lk.run(40)
    assert lk.node.phase == "safe"
    assert "refused the fault reset" in lk.node.diagnostics.safe_reason
    assert lk.node.diagnostics.statusword_sdo_reads >= 1


def test_a_lost_statusword_is_read_by_sdo(link):
    lk = link()
    lk.drive.drop_statusword = 1  # READY TO SWITCH ON is never announced
    lk.boot()
    frames = lk.run(25)
    assert lk.node.phase == "starting" or lk.node.phase == "operational"
    assert (0x602, b"\x40\x41\x60\x00\x00\x00\x00\x00") in [(i, d) for _, i, d in frames]
    lk.run_until("operational", 10)
    d = lk.node.diagnostics
    assert (d.statusword_timeouts, d.statusword_sdo_reads, d.statusword_sdo_answers) == (1, 2, 2)
    # shutdown was repeated for 20 ms (the timeout); the SDO answer of cycle 20 loses
    # arbitration to the sensor frame (0x182 < 0x582), so switch on goes out in cycle 21
    assert d.startup_cycles == 22


def test_a_drive_that_never_gets_enabled_times_out_into_safe(link):
    lk = link()
    lk.drive.ignore_controlword = True
    lk.boot()
    lk.run(1002)
    assert lk.node.phase == "safe"
    assert lk.node.diagnostics.safe_reason.startswith(
        "drive (node 2) did not reach OPERATION ENABLED within 1.0 s (SWITCH ON DISABLED"
    )
    assert lk.node.diagnostics.statusword_timeouts == 49


# ============================================================================ stop


def test_stop_walks_back_and_leaves_the_drive_pre_operational(link):
    lk = operational(link)
    lk.run(5)
    lk.node.request_stop()
    assert lk.node.phase == "stopping"
    frames = lk.run(3)
    assert commands(frames) == [(0, 0x0007), (0, 0x0006)]  # disable operation, shutdown
    assert (0x000, b"\x80\x02") in [(i, d) for _, i, d in frames]
    assert lk.node.phase == "stopped" and lk.drive.nmt == 0x7F
    assert lk.drive.fsm.state is State.READY_TO_SWITCH_ON
    assert lk.node.services.state == 0x7F  # controller PRE-OPERATIONAL
    frames = lk.run(200)
    assert set(ids(frames)) == {0x701, 0x702}  # heartbeats only: no SYNC, no PDO
    assert lk.upload(0x2400, 3) == struct.pack("<f", 0.0)  # SDO still served
    lk.node.request_stop()
    assert lk.node.phase == "stopped"


def test_num_samples_ends_the_run_with_the_stop_walk(link):
    lk = operational(link, FirmwareConfig(num_samples=5))
    lk.run(5)
    assert lk.node.isr.samplecount == 5 and lk.node.done
    assert lk.node.phase == "stopping"
    lk.run(3)
    assert lk.node.phase == "stopped"
    assert lk.node.isr.samplecount == 5
    assert "num_samples = 5 reached" in lk.node.diagnostics.phase_history[-2].reason


def test_stop_before_the_drive_booted(link):
    lk = link()
    lk.boot(drive=False)
    lk.run(3)
    lk.node.request_stop()
    assert lk.node.phase == "stopped"
    assert lk.node.send_sync() is False


# ======================================================================= monitoring


def test_drive_heartbeat_loss_is_safe_within_one_tick_with_emcy(link):
    lk = operational(link)
    lk.run(300)
    last = max(k for k, i, _ in lk.log if i == 0x702) * TS  # last drive heartbeat
    lk.drive.mute_heartbeat = True  # the PDOs go on: only the heartbeat is missing
    start = len(lk.log)
    while lk.node.phase != "safe":
        lk.cycle()
    detected = lk.node.diagnostics.heartbeat_lost_at_s
    assert 0.25 < detected - last <= 0.25 + TS + 1e-9
    frames = [(i, d) for _, i, d in lk.log[start:]]
    emcy = [d for i, d in frames if i == 0x081]
    assert emcy == [struct.pack("<HB5s", 0x8130, 0x11, b"\x02")]
    assert lk.node.diagnostics.heartbeat_losses == 1
    assert lk.node.diagnostics.emcy_sent == 1
    assert "heartbeat of drive (node 2) lost" in lk.node.diagnostics.safe_reason
    # NMT: drive to PRE-OPERATIONAL, no RPDO; requested with the EMCY, it wins arbitration
    assert frames[-2:] == [(0x000, b"\x80\x02"), (0x081, emcy[0])]
    after = lk.run(20)
    assert not {0x080, 0x202, 0x181} & set(ids(after))
    assert (0x701, b"\x7f") in [(i, d) for _, i, d in lk.run(100)]  # PRE-OPERATIONAL


def test_sensor_hold_keeps_the_last_command_then_safe(link):
    lk = operational(link, sensor_hold_cycles=10)
    lk.run(5)
    lk.drive.mute_sensor = True  # one short gap first: tolerated
    lk.run(3)
    lk.drive.mute_sensor = False
    lk.run(2)
    assert lk.node.phase == "operational"
    assert lk.node.diagnostics.sensor_frames_missed == 3
    lk.drive.mute_sensor = True
    commands_before = len(lk.drive.controlwords)
    frames = lk.run(12)
    assert ids(frames).count(0x080) == 10  # 10 SYNCs without a sensor frame, then stop
    assert lk.node.phase == "safe"
    assert len(lk.drive.controlwords) == commands_before  # the drive held the last one
    assert (0x000, b"\x80\x02") in [(i, d) for _, i, d in frames]
    assert lk.drive.nmt == 0x7F
    emcy = [d for _, i, d in frames if i == 0x081]
    assert emcy == [struct.pack("<HB5s", 0x8250, 0x11, b"\x02\x0a")]
    d = lk.node.diagnostics
    assert (d.sensor_frames_missed, d.sensor_hold_longest) == (13, 10)


class SensorScript:
    """Sensor frames of a motor whose tacho reads ``tacho(sample)`` counts and whose
    encoder counts the velocity it really has, ``true(sample)`` tacho counts (the same
    as the tacho unless that is faulty); ``stuck`` freezes the encoder count."""

    VOLT_PER_COUNT = 10.0 / 2048
    RADPS_PER_COUNT = VOLT_PER_COUNT * 56.2565

    def __init__(self, tacho: Callable[[int], int], true: Callable[[int], int] | None = None):
        self.tacho = tacho
        self.true = true or tacho
        self.angle = 0.0  # rad
        self.count = 0
        self.stuck: range = range(0)

    def __call__(self, sample: int) -> tuple[int, int, int, int]:
        self.angle += self.true(sample) * self.RADPS_PER_COUNT * TS
        if sample not in self.stuck:
            self.count = round(self.angle * 8000 / (2 * math.pi))
        return 100, self.tacho(sample), 0, self.count & 0xFFFF


def _emcy(frames) -> list[tuple[int, int]]:
    """(error code, error register) of the controller's EMCY frames."""
    return [struct.unpack_from("<HB", d) for _, i, d in frames if i == 0x081]


def _scripted(make, script: SensorScript, config: FirmwareConfig | None = None) -> Link:
    """A link whose drive sends the script's sensor frames from its first one."""
    lk = make(config)
    lk.drive.sensor = script
    lk.boot()
    lk.run_until("operational", 50)
    return lk


def test_a_tacho_spike_is_counted_but_sends_no_emcy(link):
    lk = _scripted(link, SensorScript(lambda s: 400 if s == 50 else 20, lambda s: 20))
    frames = lk.run(100)
    d = lk.node.diagnostics
    assert (d.tacho_rejections, d.encoder_rejections, d.plausibility_errors) == (1, 0, 0)
    assert _emcy(frames) == []


def test_persistent_implausible_velocity_sends_emcy_0x7301_then_the_reset(link):
    """The tacho jumps to a level the joint cannot reach even over M samples and stays:
    the M-th replaced sample raises EMCY 0x7301 "tacho fault" (CiA 402) once; the level
    is then accepted and M plausible samples later EMCY 0x0000 clears the error.  (Paper
    mode: the encoder, which would disagree with the new level, is not checked.)"""
    script = SensorScript(lambda s: 1500 if s >= 50 else 20)  # 5 -> 412 rad/s
    # paper mode asks for the stage explicitly (off there by default: the listing has none)
    paper = dataclasses.replace(
        paper_config(FirmwareConfig()),
        plausibility=PlausibilityConfig(enabled=True),
        startup_settle_s=0.0,
    )
    lk = _scripted(link, script, paper)
    m = lk.node.config.plausibility.max_rejections
    start = len(lk.log)
    lk.run(100)
    emcy = [(k, *struct.unpack_from("<HB", d)) for k, i, d in lk.log[start:] if i == 0x081]
    assert [(code, reg) for _, code, reg in emcy] == [(0x7301, 0x21), (0x0000, 0x00)]
    raised_cycle, cleared_cycle = emcy[0][0], emcy[1][0]
    assert cleared_cycle - raised_cycle == m + 1  # M replaced, 1 new level, M plausible
    d = lk.node.diagnostics
    assert (d.tacho_rejections, d.tacho_reseeds, d.plausibility_errors) == (m, 1, 1)
    assert d.encoder_rejections == 0 and lk.node.phase == "operational"
    assert d.emcy_sent == 2


def test_a_stuck_encoder_sends_emcy_0x7305_while_it_stays_stuck(link):
    """The encoder stops counting for 30 samples at 55 rad/s: M increments replaced,
    EMCY 0x7305 "incremental sensor 1 fault" once, the stuck count followed (no
    lock-out), and EMCY 0x0000 once it counts again."""
    script = SensorScript(lambda s: 200)  # 55 rad/s, 70 counts per sample
    script.stuck = range(50, 80)
    lk = _scripted(link, script)
    m = lk.node.config.plausibility.max_rejections

    def until(sample: int) -> list[tuple[int, int, bytes]]:
        frames = []
        while lk.drive.sample < sample:
            frames += lk.run(1)
        return frames

    assert _emcy(until(50)) == []
    assert _emcy(until(50 + m + 2)) == [(0x7305, 0x21)]
    assert _emcy(until(80 + m + 2)) == [(0x0000, 0x00)]
    d = lk.node.diagnostics
    # 30 samples without an increment, then the whole 30 x 70 counts at once: M replaced,
    # the rest followed
    assert d.encoder_rejections == m and d.encoder_reseeds == 30 - m + 1
    assert d.tacho_rejections == 0 and d.plausibility_errors == 1


def test_a_drive_reboot_or_another_masters_nmt_stop_is_safe(link):
    lk = operational(link)
    lk.drive.boot(lk.now)
    lk.pump()
    assert lk.node.phase == "safe" and "it was reset" in lk.node.diagnostics.safe_reason
    lk2 = operational(link)
    lk2.host.send(can.Message(arbitration_id=0x000, data=b"\x02\x01", is_extended_id=False))
    lk2.pump()
    assert lk2.node.phase == "safe"
    assert lk2.node.diagnostics.safe_reason == "NMT STOPPED commanded by another master"


def test_sync_counter_overflow_from_the_constructor(link):
    lk = link(sync_overflow=4)
    lk.boot()
    frames = lk.run(6)
    assert [d[0] for _, i, d in frames if i == 0x080] == [1, 2, 3, 4, 1, 2]


# ==================================================================== SDO: good writes


def test_amplitude_write_changes_the_dac_command_at_the_next_cycle(link):
    cfg = FirmwareConfig(reference=ReferenceConfig(wave=Wave.STEP, amplitude_V=0.5))
    lk = operational(link, cfg)
    lk.run(2)
    assert lk.drive.dac[-1] == 102  # 0.5 V / 4.88 mV (12 bits, +/-10 V)
    # the request is handled during the cycle, before the sensor frame: not used yet
    lk.host.send(
        can.Message(
            arbitration_id=0x601,
            data=struct.pack("<BHB", 0x23, 0x2400, 3) + struct.pack("<f", 1.0),
            is_extended_id=False,
        )
    )
    lk.cycle()
    assert lk.drive.dac[-1] == 102
    assert lk.node.config.reference.amplitude_V == 0.5
    lk.cycle()
    assert lk.drive.dac[-1] == 205
    assert lk.node.config.reference.amplitude_V == 1.0
    assert lk.read_real(0x2400, 3) == 1.0
    assert lk.node.diagnostics.parameter_updates_applied == 1


def test_writes_in_one_cycle_are_applied_together(link):
    lk = operational(link)
    assert lk.write_real(0x2400, 2, 1.0) is None  # bias
    assert lk.download(0x2400, 1, bytes((Wave.STEP,))) is None
    assert lk.write_real(0x2400, 3, 0.5) is None  # amplitude
    assert lk.node.config.reference == ReferenceConfig()  # nothing applied yet
    lk.cycle()
    ref = lk.node.config.reference
    assert (ref.wave, ref.bias_V, ref.amplitude_V) == (Wave.STEP, 1.0, 0.5)
    assert lk.drive.dac[-1] == 307  # 1.5 V
    d = lk.node.diagnostics
    assert (d.parameter_writes, d.parameter_updates_applied) == (3, 1)


def test_filter_r_write_restarts_the_ripple_filter(link):
    lk = operational(link)
    lk.run(10)
    chain = lk.node.isr.chain
    assert lk.write_real(0x2410, 2, 0.002) is None
    assert lk.node.isr.chain is chain  # not before the cycle boundary
    lk.cycle()
    assert lk.node.isr.chain is not chain
    assert lk.node.isr.chain.differentiator is chain.differentiator  # carried over
    assert lk.node.config.ripple.r == f32(0.002)
    assert lk.node.isr.chain.kalman.cfg.r == f32(0.002)
    assert lk.node.diagnostics.filter_restarts == 1
    assert lk.read_real(0x2410, 2) == f32(0.002)


def test_a_filter_restart_keeps_the_plausibility_history_and_counts(link):
    lk = _scripted(link, SensorScript(lambda s: 400 if s == 20 else 20, lambda s: 20))
    lk.run(30)
    check = lk.node.isr.chain.plausibility
    assert check.tacho_rejections == 1 and check.check_encoder
    assert lk.download(0x2410, 1, b"\x00") is None  # paper: the encoder is not used
    lk.cycle()
    assert lk.node.isr.chain.plausibility is check and not check.check_encoder
    assert lk.download(0x2410, 1, b"\x01") is None  # recommended again
    lk.run(30)
    assert check.check_encoder and lk.node.diagnostics.filter_restarts == 2
    d = lk.node.diagnostics
    assert (d.tacho_rejections, d.encoder_rejections, d.plausibility_errors) == (1, 0, 0)


def test_filter_mode_write_gives_the_modes_default_tuning(link):
    lk = operational(link)
    assert lk.download(0x2410, 1, b"\x00") is None  # paper
    assert lk.read_real(0x2410, 2) == 1.0  # r and q follow at once in the OD
    assert lk.read_real(0x2410, 5) == 1000.0
    lk.cycle()
    assert lk.node.config.ripple.mode == "paper"
    assert type(lk.node.isr.chain.kalman).__name__ == "RippleKalman"
    assert lk.write_real(0x2410, 6, 500.0) is None
    lk.cycle()
    assert [o.q for o in lk.node.config.ripple.oscillators] == [1000.0, 500.0]


def test_law_write_switches_the_control_stage_and_ctrl_tpdo2(link):
    lk = operational(link)
    assert 0x281 not in ids(lk.run(3))
    assert lk.download(0x2420, 1, bytes((Law.JTF1,))) is None
    assert lk.upload(0x1801, 1) == struct.pack("<I", 0x80000281)  # not yet applied
    lk.cycle()
    assert lk.node.isr.control is not None and lk.node.control_pdo_valid
    frames = lk.run(3)
    assert ids(frames).count(0x281) == 3
    assert lk.upload(0x1801, 1) == struct.pack("<I", 0x00000281)
    control = lk.node.isr.control
    assert lk.write_real(0x2420, 2, -10.0) is None  # desired amplitude: observer kept
    lk.cycle()
    assert lk.node.isr.control is control
    assert control.desired.cfg.amplitude_V == -10.0
    assert lk.node.diagnostics.control_rebuilds == 1
    assert lk.download(0x2420, 1, b"\x00") is None
    lk.cycle()
    assert 0x281 not in ids(lk.run(3)) and lk.node.isr.control is None
    assert lk.upload(0x1801, 1) == struct.pack("<I", 0x80000281)


def test_calibration_write_scales_the_measured_torque(link):
    lk = operational(link)
    lk.run(2)
    t_meas = TELEMETRY.decode(next(d for _, i, d in reversed(lk.log) if i == 0x181))[0]
    assert lk.write_real(0x2430, 1, 13.2) is None
    lk.run(2)
    doubled = TELEMETRY.decode(next(d for _, i, d in reversed(lk.log) if i == 0x181))[0]
    assert doubled == pytest.approx(2 * t_meas, abs=0.009)  # 0.004 Nm telemetry steps


# ===================================================================== SDO: bad writes


@pytest.mark.parametrize(
    ("index", "sub", "data", "abort"),
    [
        (0x2400, 3, struct.pack("<f", 10.5), 0x06090031),  # amplitude above 10 V
        (0x2400, 2, struct.pack("<f", -10.5), 0x06090032),  # bias below -10 V
        (0x2400, 4, struct.pack("<f", 0.0), 0x06090032),  # frequency must be > 0
        (0x2400, 4, struct.pack("<f", 501.0), 0x06090031),
        (0x2400, 1, b"\x07", 0x06090031),  # no wave 7
        (0x2400, 3, struct.pack("<f", math.nan), 0x06090030),
        (0x2400, 3, b"\x00\x00", 0x06070013),  # REAL32 needs 4 bytes
        (0x2400, 1, b"\x01\x00", 0x06070012),  # UNSIGNED8 gets 2
        (0x2401, 2, struct.pack("<f", 0.002), 0x06010002),  # sample period: read-only
        (0x2410, 4, b"\x03", 0x06010002),  # number of harmonics: read-only
        (0x2500, 0, b"\x01", 0x06020000),  # no such object
        (0x2410, 2, struct.pack("<f", 0.0), 0x06090032),  # r > 0
        (0x2410, 7, struct.pack("<f", 1.0), 0x08000022),  # q of a 3rd harmonic: none
        (0x2420, 1, b"\x05", 0x06090031),  # no law 5
        (0x2430, 1, struct.pack("<f", 0.0), 0x06090030),  # a zero gain
        (0x1006, 0, struct.pack("<I", 2000), 0x08000022),  # the runner paces the cycle
        (0x1006, 0, struct.pack("<I", 0), 0x08000022),
        (0x1019, 0, b"\x04", 0x08000022),  # fixed while 0x1006 is not 0 (CiA 301)
    ],
)
def test_bad_writes_abort_and_change_nothing(link, index, sub, data, abort):
    lk = operational(link)
    lk.run(2)
    before = lk.upload(index, sub)
    config = lk.node.config
    dac = lk.drive.dac[-1]
    assert lk.download(index, sub, data) == abort
    assert lk.upload(index, sub) == before
    lk.run(2)
    assert lk.node.config is config
    assert lk.drive.dac[-1] == dac
    assert lk.node.diagnostics.parameter_writes == 0


def test_a_chirp_at_nyquist_is_refused_by_the_generator(link):
    cfg = FirmwareConfig(reference=ReferenceConfig(wave=Wave.CHIRP, frequency_Hz=2.0))
    lk = operational(link, cfg)
    assert lk.write_real(0x2400, 4, 500.0) == 0x06090030  # within the EDS range, not valid
    assert lk.read_real(0x2400, 4) == 2.0
    assert lk.write_real(0x2400, 4, 5.0) is None

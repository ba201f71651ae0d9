"""The drive node as a CANopen device: NMT gating, CiA 402 wiring, statusword TPDO2,
heartbeat and command-hold faults, EMCY, and the SDO-reachable emulator parameters.

Every test runs in simulated time on ``simbus``: a peer bus plays the controller (SYNC,
DRIVE_RPDO1, heartbeat, NMT, SDO requests) one lockstep cycle at a time, like the runner:
tick at t(k), SYNC k, the drive's frames, the command, the drive handles it.  The state
machine's own transitions are tested in ``test_cia402``; here the wiring is.
"""

from __future__ import annotations

import dataclasses
import math
import struct

import pytest
from conftest import BusHarness

from hdhil.canopen.cia402 import (
    SW_INTERNAL_LIMIT,
    SW_WARNING,
    State,
    state_from_statusword,
)
from hdhil.canopen.services import NmtCommand, NmtState
from hdhil.dbc import codec
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant, PlantConfig, RippleConfig, SensorConfig

SYNC, TPDO1, TPDO2, RPDO1 = 0x080, 0x182, 0x282, 0x202
EMCY, HEARTBEAT, BOOT = 0x082, 0x702, 0x702
SDO_RX, SDO_TX = 0x602, 0x582
CTRL_HEARTBEAT = 0x701
SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_VOLTAGE, QUICK_STOP, FAULT_RESET = (
    0x06,
    0x07,
    0x0F,
    0x00,
    0x02,
    0x80,
)
TRUTH_IDS = {0x1F0001, 0x1F0002, 0x1F0003}
Ts = 1e-3


class Rig(BusHarness):
    """A drive on the shared bus harness; the host plays the controller and host tools."""

    def __init__(
        self,
        config: DriveConfig | None = None,
        plant_cfg: PlantConfig | None = None,
        truth: bool = True,
    ) -> None:
        super().__init__("t-drive")
        drive_bus = self.bus()
        self.truth_peer = None
        truth_bus = None
        if truth:
            truth_bus = self.bus("-truth", bitrate=0)
            self.truth_peer = self.bus("-truth", bitrate=0)
        self.plant = Plant(plant_cfg or PlantConfig(), seed=3)
        self.drive = self.add(DriveNode(drive_bus, self.plant, config or DriveConfig(), truth_bus))
        self._command = codec("control", "DRIVE_RPDO1")

    def truth_frames(self) -> list[int]:
        out = []
        while self.truth_peer is not None and (msg := self.truth_peer.recv(0)) is not None:
            out.append(msg.arbitration_id)
        return out

    def boot(self) -> list[tuple[int, bytes]]:
        self.drive.boot(self.now)
        return self.frames()

    def nmt(self, command: int, node: int = 2) -> list[tuple[int, bytes]]:
        self.send(0x000, bytes((command, node)))
        self.drive.poll()
        return self.frames()

    def start(self) -> None:
        """Boot and NMT start; discard the frames."""
        self.boot()
        self.nmt(NmtCommand.START)

    def cycle(
        self,
        controlword: int | None = None,
        dac: int = 0,
        heartbeat: bool = False,
        sync: bool = True,
    ) -> list[tuple[int, bytes]]:
        """One lockstep cycle at t(k): tick, (controller heartbeat), SYNC, the drive's
        answer, the command (when ``controlword`` is given).  Returns the drive's frames."""
        self.tick()
        if heartbeat:
            self.send(CTRL_HEARTBEAT, b"\x05")
        if sync:
            self.send_sync()
        out = self.pump()
        if controlword is not None:
            self.send(RPDO1, self._command.encode(dac, controlword, self.k & 0xFF))
            out += self.pump()
        self.k += 1
        return out

    def enable(self, dac: int = 0) -> None:
        """Walk the drive to OPERATION ENABLED the way the controller does."""
        for cw in (SHUTDOWN, SWITCH_ON, ENABLE):
            self.cycle(cw, dac)
        self.cycle(ENABLE, dac)  # the last controlword is actuated at this SYNC
        assert self.drive.drive_state is State.OPERATION_ENABLED


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def ids(frames: list[tuple[int, bytes]]) -> list[int]:
    return [can_id for can_id, _ in frames]


def statuswords(frames: list[tuple[int, bytes]]) -> list[int]:
    return [struct.unpack("<H", data)[0] for can_id, data in frames if can_id == TPDO2]


def emcys(frames: list[tuple[int, bytes]]) -> list[tuple[int, int, bytes]]:
    return [struct.unpack("<HB5s", data) for can_id, data in frames if can_id == EMCY]


def sdo_download(r: Rig, index: int, sub: int, data: bytes) -> int | None:
    """Expedited download (1..4 bytes); the abort code or None."""
    command = 0x23 | ((4 - len(data)) << 2)
    r.send(SDO_RX, struct.pack("<BHB", command, index, sub) + data.ljust(4, b"\0"))
    r.drive.poll()
    ((cob, response),) = [f for f in r.frames() if f[0] == SDO_TX]
    assert cob == SDO_TX
    if response[0] == 0x80:
        return struct.unpack_from("<I", response, 4)[0]
    assert response[0] == 0x60
    return None


def sdo_segmented_download(r: Rig, index: int, sub: int, data: bytes) -> int | None:
    """Segmented download of ``data`` (any length); the abort code or None."""
    r.send(SDO_RX, struct.pack("<BHBI", 0x21, index, sub, len(data)))
    r.drive.poll()
    ((_, response),) = r.frames()
    if response[0] == 0x80:
        return struct.unpack_from("<I", response, 4)[0]
    toggle = 0
    for pos in range(0, len(data), 7):
        chunk = data[pos : pos + 7]
        last = pos + 7 >= len(data)
        cs = (toggle << 4) | ((7 - len(chunk)) << 1) | int(last)
        r.send(SDO_RX, bytes((cs,)) + chunk.ljust(7, b"\0"))
        r.drive.poll()
        ((_, response),) = r.frames()
        if response[0] == 0x80:
            return struct.unpack_from("<I", response, 4)[0]
        toggle ^= 1
    return None


def sdo_upload(r: Rig, index: int, sub: int) -> bytes | tuple[str, int]:
    r.send(SDO_RX, struct.pack("<BHB4x", 0x40, index, sub))
    r.drive.poll()
    ((_, response),) = r.frames()
    if response[0] == 0x80:
        return ("abort", struct.unpack_from("<I", response, 4)[0])
    n = 4 - ((response[0] >> 2) & 3)
    return response[4 : 4 + n]


# ========================================================================== config


@pytest.mark.parametrize(
    "kwargs",
    [
        {"node_id": 0},
        {"node_id": 128},
        {"node_id": 1},  # same as the controller
        {"heartbeat_ms": -1},
        {"controller_heartbeat_timeout_ms": 70000},
        {"command_hold_cycles": -1},
        {"command_hold_cycles": 2.5},
        {"sync_overflow": 1},
        {"quick_stop_time_s": -0.1},
        {"quick_stop_time_s": math.nan},
    ],
)
def test_config_refuses_bad_values(kwargs):
    with pytest.raises(ValueError):
        DriveConfig(**kwargs)


# ============================================================================= NMT


def test_boot_up_frame_and_states(rig):
    drive = rig.drive
    assert drive.nmt_state is NmtState.INITIALISING
    assert drive.drive_state is State.NOT_READY_TO_SWITCH_ON
    assert rig.boot() == [(BOOT, b"\x00")]
    assert drive.nmt_state is NmtState.PRE_OPERATIONAL
    assert drive.drive_state is State.SWITCH_ON_DISABLED
    assert not drive.torque_enabled
    with pytest.raises(RuntimeError, match="already booted"):
        drive.boot(0.0)


def test_heartbeat_producer_every_100_ms(rig):
    rig.boot()
    sent = []
    for _ in range(350):
        frames = rig.cycle(sync=False)
        sent += [(rig.clock.now, data) for can_id, data in frames if can_id == HEARTBEAT]
    assert [t for t, _ in sent] == pytest.approx([0.1, 0.2, 0.3])
    assert {data for _, data in sent} == {bytes((NmtState.PRE_OPERATIONAL,))}


def test_pdos_only_in_operational_while_the_plant_always_advances(rig):
    rig.boot()
    for k in range(5):
        frames = rig.cycle(SHUTDOWN)
        assert frames == [], f"cycle {k}: no PDO before NMT start"
    assert rig.truth_frames() == []
    assert rig.drive.diagnostics.pdos_ignored == 5
    assert rig.drive.drive_state is State.SWITCH_ON_DISABLED  # commands were not taken
    assert rig.plant.time == pytest.approx(4 * Ts)  # the first SYNC marks t(0)

    started = rig.nmt(NmtCommand.START)
    assert rig.drive.nmt_state is NmtState.OPERATIONAL
    assert statuswords(started) == [rig.drive.statusword]  # once on entering OPERATIONAL
    frames = rig.cycle(SHUTDOWN)
    assert ids(frames) == [TPDO1]
    assert sorted(rig.truth_frames()) == sorted(TRUTH_IDS)
    assert rig.plant.time == pytest.approx(5 * Ts)

    rig.nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
    assert rig.cycle(SHUTDOWN) == []
    assert rig.truth_frames() == []
    assert rig.plant.time == pytest.approx(6 * Ts)


def test_stopped_answers_no_sdo_and_keeps_the_heartbeat(rig):
    rig.start()
    assert rig.nmt(NmtCommand.STOP) == []
    assert rig.drive.nmt_state is NmtState.STOPPED
    rig.send(SDO_RX, struct.pack("<BHB4x", 0x40, 0x1000, 0))
    rig.drive.poll()
    assert rig.frames() == []
    frames = []
    for _ in range(101):
        frames += rig.cycle(ENABLE)
    assert frames == [(HEARTBEAT, bytes((NmtState.STOPPED,)))]
    assert rig.plant.time == pytest.approx(100 * Ts)  # physics goes on


@pytest.mark.parametrize(
    ("option", "state", "emcy_code"),
    [
        (2, State.SWITCH_ON_DISABLED, None),  # default: disable voltage (transition 9)
        (3, State.SWITCH_ON_DISABLED, None),  # quick stop (11, then 12 with option 2)
        (1, State.FAULT, 0x8100),  # fault signal
    ],
)
def test_leaving_operational_takes_the_power_stage_off(rig, option, state, emcy_code):
    """Abort connection option code 0x6007 (CiA 402-2) on NMT enter pre-operational."""
    rig.start()
    assert sdo_download(rig, 0x6007, 0, struct.pack("<h", option)) is None
    rig.enable(dac=500)
    assert rig.drive.amplifier_input_V == pytest.approx(500 * 10 / 2048)
    frames = rig.nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
    assert rig.drive.drive_state is state
    assert not rig.drive.torque_enabled
    assert [code for code, _, _ in emcys(frames)] == ([emcy_code] if emcy_code else [])
    assert statuswords(frames) == []  # no PDOs outside OPERATIONAL
    rig.cycle()
    assert rig.drive.amplifier_input_V == 0.0
    started = rig.nmt(NmtCommand.START)
    assert state_from_statusword(statuswords(started)[0]) is state
    if emcy_code:
        assert emcys(started) == [(0x0000, 0x00, bytes(5))]


def test_abort_connection_no_action_leaves_it_to_the_command_hold(rig):
    rig.start()
    assert sdo_download(rig, 0x6007, 0, struct.pack("<h", 0)) is None
    assert sdo_download(rig, 0x6007, 0, struct.pack("<h", 4)) == 0x06090031
    rig.enable(dac=500)
    rig.nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
    assert rig.drive.torque_enabled
    powered = []
    for _ in range(12):
        rig.cycle(ENABLE, 500)  # ignored: PDOs are not processed in PRE-OPERATIONAL
        powered.append(rig.drive.amplifier_input_V != 0.0)
    assert powered == [True] * 10 + [False] * 2  # 10 command-less cycles: the default hold
    assert rig.drive.drive_state is State.FAULT
    assert rig.drive.diagnostics.pdos_ignored == 12


@pytest.mark.parametrize("kind", [NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION])
def test_nmt_reset_goes_back_to_boot(rig, kind):
    rig.start()
    rig.enable(dac=300)
    assert sdo_download(rig, 0x2300, 1, struct.pack("<f", 2.0)) is None
    rig.cycle(ENABLE, 300)
    assert rig.plant.cfg.ripple.amp2_Nm == pytest.approx(2.0)
    frames = rig.nmt(kind)
    assert frames == [(BOOT, b"\x00")]
    assert rig.drive.nmt_state is NmtState.PRE_OPERATIONAL
    assert rig.drive.drive_state is State.SWITCH_ON_DISABLED
    assert not rig.drive.torque_enabled
    assert rig.drive.diagnostics.nmt_resets == 1
    rig.cycle(ENABLE, 300)
    expected = 0.6 if kind == NmtCommand.RESET_NODE else 2.0  # node: power-on values
    assert rig.plant.cfg.ripple.amp2_Nm == pytest.approx(expected)
    assert rig.drive.amplifier_input_V == 0.0
    # Up again: start and the CiA 402 walk.
    rig.nmt(NmtCommand.START)
    rig.enable(dac=300)
    assert rig.drive.torque_enabled


# ========================================================================= CiA 402


def test_every_transition_through_the_rpdo_with_statusword_frames(rig):
    """Controlwords in DRIVE_RPDO1 are actuated at the next SYNC; the statusword TPDO2
    follows each state change in that cycle, after the sensor TPDO, and only then."""
    rig.start()
    walk = [
        (SHUTDOWN, State.READY_TO_SWITCH_ON),
        (SWITCH_ON, State.SWITCHED_ON),
        (ENABLE, State.OPERATION_ENABLED),
        (SWITCH_ON, State.SWITCHED_ON),  # 5 disable operation
        (SHUTDOWN, State.READY_TO_SWITCH_ON),  # 6
        (DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED),  # 7
        (SHUTDOWN, State.READY_TO_SWITCH_ON),
        (ENABLE, State.OPERATION_ENABLED),  # 3 + 4
        (SHUTDOWN, State.READY_TO_SWITCH_ON),  # 8
        (SWITCH_ON, State.SWITCHED_ON),
        (DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED),  # 10
        (SHUTDOWN, State.READY_TO_SWITCH_ON),
        (ENABLE, State.OPERATION_ENABLED),
        (DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED),  # 9
        (SHUTDOWN, State.READY_TO_SWITCH_ON),
        (ENABLE, State.OPERATION_ENABLED),
        (QUICK_STOP, State.SWITCH_ON_DISABLED),  # 11 + 12 (option 2, no ramp)
    ]
    previous = rig.drive.state_machine.controlword
    rig.cycle(previous)
    for cw, state in walk:
        rig.cycle(cw, dac=400)  # the command is latched ...
        assert rig.drive.drive_state is not state or state is State.SWITCH_ON_DISABLED
        frames = rig.cycle(cw, dac=400)  # ... and actuated at this SYNC
        assert rig.drive.drive_state is state
        words = statuswords(frames)
        assert len(words) == 1, f"{cw:#x}: one statusword frame per change"
        assert state_from_statusword(words[0]) is state
        assert ids(frames)[:2] == [TPDO1, TPDO2]
        assert rig.drive.torque_enabled == (state is State.OPERATION_ENABLED)
        expected_V = 400 * 10 / 2048 if state is State.OPERATION_ENABLED else 0.0
        assert rig.drive.amplifier_input_V == pytest.approx(expected_V)
        # Same controlword again: no change, no statusword frame.
        assert statuswords(rig.cycle(cw, dac=400)) == []
    assert [t.number for t in rig.drive.state_machine.history][-4:] == [3, 4, 11, 12]


def test_immediate_actuation_applies_the_controlword_on_receipt():
    r = Rig(DriveConfig(actuation="immediate"))
    try:
        r.start()
        r.cycle()  # the statusword sent on NMT start holds off the next one for 1 ms
        words = []
        for cw in (SHUTDOWN, SWITCH_ON, ENABLE):
            words += statuswords(r.cycle(cw, dac=200))
        assert [state_from_statusword(w) for w in words] == [
            State.READY_TO_SWITCH_ON,
            State.SWITCHED_ON,
            State.OPERATION_ENABLED,
        ]
        assert r.drive.amplifier_input_V == pytest.approx(200 * 10 / 2048)
    finally:
        r.close()


def test_torque_only_in_operation_enabled_moves_the_motor():
    r = Rig(truth=False)
    try:
        r.start()
        for _ in range(50):
            r.cycle(SWITCH_ON, dac=1000)  # never enabled: shutdown was skipped
        assert r.plant.truth().omega_motor_radps == 0.0
        assert r.drive.drive_state is State.SWITCH_ON_DISABLED
        r.enable(dac=1000)
        for _ in range(50):
            r.cycle(ENABLE, dac=1000)
        assert r.plant.truth().omega_motor_radps > 1.0
    finally:
        r.close()


def test_quick_stop_option_5_stays_in_quick_stop_and_reenables(rig):
    rig.start()
    assert sdo_download(rig, 0x605A, 0, struct.pack("<h", 5)) is None
    rig.enable(dac=100)
    rig.cycle(QUICK_STOP, 100)
    rig.cycle(QUICK_STOP, 100)
    assert rig.drive.drive_state is State.QUICK_STOP_ACTIVE
    assert rig.drive.amplifier_input_V == 0.0
    rig.cycle(ENABLE, 100)
    rig.cycle(ENABLE, 100)
    assert rig.drive.drive_state is State.OPERATION_ENABLED  # transition 16


def test_modes_of_operation_via_sdo(rig):
    rig.start()
    assert sdo_download(rig, 0x6060, 0, struct.pack("<b", 3)) == 0x06090030  # not supported
    assert sdo_upload(rig, 0x6061, 0) == b"\x0a"
    assert sdo_download(rig, 0x6060, 0, struct.pack("<b", 0)) is None  # no mode
    assert sdo_upload(rig, 0x6061, 0) == b"\x00"
    rig.enable(dac=500)
    assert rig.drive.torque_enabled and rig.drive.amplifier_input_V == 0.0  # target ignored
    assert sdo_download(rig, 0x6060, 0, struct.pack("<b", 10)) is None
    rig.cycle(ENABLE, 500)
    assert rig.drive.amplifier_input_V == pytest.approx(500 * 10 / 2048)
    assert sdo_upload(rig, 0x6502, 0) == struct.pack("<I", 0x200)


def test_statusword_and_live_objects_read_by_sdo(rig):
    rig.start()
    rig.enable(dac=0)
    assert sdo_upload(rig, 0x6041, 0) == struct.pack("<H", rig.drive.statusword)
    assert state_from_statusword(rig.drive.statusword) is State.OPERATION_ENABLED
    assert sdo_upload(rig, 0x6040, 0) == struct.pack("<H", ENABLE)
    assert sdo_download(rig, 0x6041, 0, b"\x00\x00") == 0x06010002  # read-only
    counts = rig.drive.io.sample  # the latest sample, as sent in DRIVE_TPDO1
    assert sdo_upload(rig, 0x2100, 1) == struct.pack("<h", counts[0])
    assert sdo_upload(rig, 0x2101, 0) == struct.pack("<H", counts[3])


def test_statusword_inhibit_time_defers_a_second_change_to_the_next_cycle():
    """Two changes in one cycle (immediate actuation): the second waits out the 1 ms
    inhibit time and goes out at the next tick."""
    r = Rig(DriveConfig(actuation="immediate"))
    try:
        r.start()  # statusword sent at t = 0
        r.cycle()
        r.cycle()  # t = 1 ms
        r.send(RPDO1, codec("control", "DRIVE_RPDO1").encode(0, SHUTDOWN, 0))
        r.send(RPDO1, codec("control", "DRIVE_RPDO1").encode(0, SWITCH_ON, 1))
        r.drive.poll()
        first = statuswords(r.frames())
        assert [state_from_statusword(w) for w in first] == [State.READY_TO_SWITCH_ON]
        r.clock.now = r.now - 0.5 * Ts
        r.drive.tick(r.now - 0.5 * Ts)
        assert r.frames() == []  # still inside the inhibit time
        frames = r.cycle(sync=False)
        assert [state_from_statusword(w) for w in statuswords(frames)] == [State.SWITCHED_ON]
    finally:
        r.close()


# ======================================================================= heartbeat


def run_with_controller_heartbeat(r: Rig, until_s: float, period_s: float = 0.1) -> None:
    """Cycles with commands and a controller heartbeat every ``period_s``."""
    every = round(period_s / Ts)
    while r.now < until_s - 1e-12:
        r.cycle(ENABLE, 100, heartbeat=r.k % every == 0)


@pytest.mark.slow
def test_heartbeat_loss_faults_the_drive_one_cycle_after_the_timeout(rig):
    rig.start()
    rig.enable(dac=100)
    run_with_controller_heartbeat(rig, 0.5)
    last_heartbeat = 0.4
    assert rig.drive.services.heartbeat_consumer.monitored[1].last_heartbeat == pytest.approx(
        last_heartbeat
    )
    # The controller's heartbeat stops; its commands keep coming.
    lost_at = None
    emcy = []
    for _ in range(300):
        frames = rig.cycle(ENABLE, 100)
        emcy += emcys(frames)
        if lost_at is None and not rig.drive.torque_enabled:
            lost_at = rig.clock.now
            assert rig.drive.amplifier_input_V == 0.0  # off from this SYNC on
            assert rig.drive.drive_state is State.FAULT
            words = statuswords(frames)
            assert state_from_statusword(words[-1]) is State.FAULT
    reaction_cycles = round((lost_at - (last_heartbeat + 0.25)) / Ts)
    assert reaction_cycles == 1  # detected at the first tick after the 250 ms timeout
    assert emcy == [(0x8130, 0x11, b"\x01\x00\x00\x00\x00")]  # generic + communication
    assert rig.drive.diagnostics.heartbeat_losses == 1
    assert sdo_upload(rig, 0x603F, 0) == struct.pack("<H", 0x8130)
    # A fault reset is refused while the heartbeat is missing ...
    rig.cycle(FAULT_RESET, 0)
    rig.cycle(FAULT_RESET, 0)
    assert rig.drive.drive_state is State.FAULT
    # ... and accepted (0x80 edge) once it is back.
    frames = rig.cycle(DISABLE_VOLTAGE, 0, heartbeat=True)
    assert emcys(frames) == [(0x0000, 0x00, bytes(5))]
    rig.cycle(FAULT_RESET, 0)
    rig.cycle(FAULT_RESET, 0)
    assert rig.drive.drive_state is State.SWITCH_ON_DISABLED
    rig.enable(dac=100)
    assert rig.drive.torque_enabled


def test_no_heartbeat_monitoring_before_the_first_heartbeat(rig):
    rig.start()
    rig.enable()
    for _ in range(600):
        rig.cycle(ENABLE)
    assert rig.drive.torque_enabled
    assert rig.drive.diagnostics.heartbeat_losses == 0


# ==================================================================== command hold


@pytest.mark.parametrize("hold", [1, 3, 10])
def test_command_hold_faults_after_exactly_n_silent_cycles(hold):
    r = Rig(DriveConfig(command_hold_cycles=hold), truth=False)
    try:
        r.start()
        r.enable(dac=700)
        r.cycle(ENABLE, 700)  # the last command, in cycle j
        powered = []
        emcy = []
        for _ in range(hold + 3):
            frames = r.cycle()  # SYNC only: the controller went silent
            powered.append(r.drive.amplifier_input_V != 0.0)
            emcy += emcys(frames)
        # SYNCs j+1 .. j+hold keep the last command; the one that ends the hold-th silent
        # cycle (j+hold+1) turns the torque off.
        assert powered == [True] * hold + [False] * 3
        assert r.drive.drive_state is State.FAULT
        assert emcy == [(0x8250, 0x11, bytes((hold, 0, 0, 0, 0)))]
        assert r.drive.diagnostics.command_timeouts == 1
        # Commands resume: the EMCY clears, a fault reset recovers.
        frames = r.cycle(DISABLE_VOLTAGE)
        assert emcys(frames) == [(0x0000, 0x00, bytes(5))]
        r.cycle(FAULT_RESET)
        r.cycle(FAULT_RESET)
        assert r.drive.drive_state is State.SWITCH_ON_DISABLED
    finally:
        r.close()


def test_command_hold_holds_the_last_command_for_n_periods():
    """With synchronous actuation the last command drives the plant for N periods."""
    hold = 4
    r = Rig(DriveConfig(command_hold_cycles=hold), truth=False)
    try:
        r.start()
        r.enable(dac=0)
        r.cycle(ENABLE, 0)
        r.cycle(ENABLE, 800)  # last command: actuated at the next SYNC
        inputs = []
        for _ in range(hold + 2):
            r.cycle()
            inputs.append(r.drive.amplifier_input_V)
        assert sum(v != 0.0 for v in inputs) == hold
    finally:
        r.close()


def test_missed_syncs_advance_the_plant_and_are_counted(rig):
    rig.start()
    rig.enable()
    t0 = rig.plant.time
    rig.cycle(ENABLE)
    rig.sync_counter += 2  # two SYNCs lost on the bus
    rig.k += 2
    rig.cycle(ENABLE)
    assert rig.drive.diagnostics.missed_syncs == 2
    assert rig.plant.time - t0 == pytest.approx(4 * Ts)
    assert rig.drive.torque_enabled  # a lost SYNC is not a lost command


def test_sync_counter_restart_is_not_a_jump(rig):
    rig.start()
    for _ in range(10):
        rig.cycle()
    rig.sync_counter = 0  # the producer restarted
    t0 = rig.plant.time
    rig.cycle()
    assert rig.drive.diagnostics.missed_syncs == 0
    assert rig.plant.time - t0 == pytest.approx(Ts)


def test_duplicated_and_reordered_syncs_never_advance_the_plant(rig):
    """A repeated SYNC counter (duplicate) or one just behind the last (a SYNC overtaken
    on the bus) is ignored: the plant advances only by the periods that passed."""
    rig.start()
    for _ in range(5):
        rig.cycle()
    t0 = rig.plant.time
    sensors0 = rig.drive.diagnostics.sensor_frames
    rig.send(SYNC, bytes((rig.sync_counter,)))  # the same SYNC again
    rig.drive.poll()
    assert rig.plant.time == t0
    assert rig.drive.diagnostics.duplicate_syncs == 1
    rig.cycle()  # SYNC n+1
    rig.sync_counter += 1
    rig.cycle()  # SYNC n+3: n+2 was overtaken...
    rig.send(SYNC, bytes((rig.sync_counter - 1,)))  # ...and arrives late
    rig.drive.poll()
    assert rig.drive.diagnostics.stale_syncs == 1
    assert rig.drive.diagnostics.missed_syncs == 1
    assert rig.plant.time - t0 == pytest.approx(3 * Ts)  # n+1, n+2 (missed), n+3
    assert rig.drive.diagnostics.sensor_frames - sensors0 == 2  # one per accepted SYNC


# ============================================================================ EMCY


def test_adc_saturation_emcy_once_per_occurrence():
    # A bridge amplifier offset beyond full scale saturates the torque channel.
    cfg = PlantConfig(sensors=SensorConfig(torque_offset_V=12.0, torque_noise_Nm=0.0))
    r = Rig(plant_cfg=cfg, truth=False)

    def offset(volts: float) -> None:  # the offset drifts (test-only change of the plant)
        c = r.plant.cfg
        r.plant.cfg = dataclasses.replace(
            c, sensors=dataclasses.replace(c.sensors, torque_offset_V=volts)
        )

    try:
        r.start()
        emcy, words = [], []
        for _ in range(5):
            frames = r.cycle()
            emcy += emcys(frames)
            words += statuswords(frames)
        assert emcy == [(0x7300, 0x21, b"\x01\x00\x00\x00\x00")]  # generic + device profile
        assert words and words[-1] & SW_WARNING
        offset(0.0)
        frames = r.cycle()  # back in range: EMCY 0x0000 with the remaining error register
        assert emcys(frames) == [(0x0000, 0x00, bytes(5))]
        assert not r.drive.statusword & SW_WARNING
        assert emcys(r.cycle()) == []
        offset(-12.0)  # a second occurrence, at the other code limit
        assert emcys(r.cycle()) == [(0x7300, 0x21, b"\x01\x00\x00\x00\x00")]
        assert emcys(r.cycle()) == []
        assert r.drive.diagnostics.adc_saturations == 2
    finally:
        r.close()


def test_current_limit_emcy_and_internal_limit_bit(rig):
    rig.start()
    rig.enable(dac=2047)  # 10 V at 1 A/V: beyond the 6 A limit
    emcy = []
    for _ in range(5):
        emcy += emcys(rig.cycle(ENABLE, 2047))
    assert emcy == [(0x2310, 0x03, bytes(5))]  # generic + current
    assert rig.drive.statusword & SW_INTERNAL_LIMIT
    assert rig.drive.diagnostics.overcurrents == 1
    rig.cycle(ENABLE, 0)  # latched ...
    assert emcys(rig.cycle(ENABLE, 0)) == []  # ... actuated: the step after is the first at 0 V
    frames = rig.cycle(ENABLE, 0)
    assert emcys(frames) == [(0x0000, 0x00, bytes(5))]
    assert not rig.drive.statusword & SW_INTERNAL_LIMIT


# ============================================================================= SDO


def test_good_sdo_writes_change_the_running_plant(rig):
    rig.start()
    plant = rig.plant
    assert sdo_upload(rig, 0x2300, 1) == struct.pack("<f", 0.6)  # power-on = plant config
    writes = {
        1: 3.5,  # ripple amp2
        2: 1.25,  # ripple amp4
        3: 8.0,  # misalignment p-p
        4: 0.5,  # torque noise
        5: 0.25,  # tacho noise
        6: -2.0,  # load torque
    }
    for sub, value in writes.items():
        assert sdo_download(rig, 0x2300, sub, struct.pack("<f", value)) is None
        assert struct.unpack("<f", sdo_upload(rig, 0x2300, sub))[0] == value
    assert plant.cfg.ripple.amp2_Nm == 0.6  # applied at the next SYNC
    rig.cycle()
    assert plant.cfg.ripple == RippleConfig(
        amp2_Nm=3.5, amp4_Nm=1.25, misalignment_pp_Nm=8.0, phase2_rad=0.4, phase4_rad=1.3
    )
    assert plant.cfg.sensors.torque_noise_Nm == 0.5
    assert plant.cfg.sensors.tacho_noise_radps == 0.25
    assert plant.truth().tau_l_Nm == -2.0
    assert plant._sig_torque_V == pytest.approx(0.5 / plant.cfg.bridge.volt2Nm)


@pytest.mark.parametrize(
    ("index", "sub", "data", "code"),
    [
        (0x2300, 1, struct.pack("<f", 10.5), 0x06090031),  # HighLimit 10 Nm
        (0x2300, 1, struct.pack("<f", -0.1), 0x06090032),  # LowLimit 0
        (0x2300, 6, struct.pack("<f", 101.0), 0x06090031),
        (0x2300, 4, struct.pack("<f", math.nan), 0x06090030),
        (0x2300, 1, b"\x00\x00", 0x06070013),  # REAL32 written with 2 bytes
        (0x6041, 0, b"\x00\x00", 0x06010002),  # statusword is read-only
        (0x2300, 0, b"\x03", 0x06010002),  # highest sub-index is const
        (0x605A, 0, struct.pack("<h", 9), 0x06090031),
        (0x605E, 0, struct.pack("<h", -1), 0x06090032),
    ],
)
def test_bad_sdo_writes_leave_the_plant_unchanged(rig, index, sub, data, code):
    rig.start()

    def state() -> tuple:
        return rig.plant.cfg, rig.plant.truth().tau_l_Nm, rig.drive.state_machine.quick_stop_option

    before = state()
    assert sdo_download(rig, index, sub, data) == code
    rig.cycle()
    assert state() == before


def test_too_long_sdo_write_is_refused(rig):
    rig.start()
    cfg = rig.plant.cfg
    assert sdo_segmented_download(rig, 0x2300, 1, struct.pack("<d", 1.0)) == 0x06070012
    rig.cycle()
    assert rig.plant.cfg is cfg


def test_generic_length_abort_code_on_the_services(rig):
    """0x06070010 is the services' generic length code: never used by the drive, which
    answers the specific 0x06070012/13 (CiA 301 recommends them)."""
    rig.start()
    assert sdo_download(rig, 0x1017, 0, struct.pack("<I", 100)) == 0x06070012


def test_sdo_needs_pre_operational_or_operational(rig):
    rig.boot()
    assert sdo_upload(rig, 0x1017, 0) == struct.pack("<H", 100)
    assert sdo_upload(rig, 0x1016, 1) == struct.pack("<I", 0x000100FA)
    assert sdo_upload(rig, 0x1014, 0) == struct.pack("<I", 0x82)
    assert sdo_upload(rig, 0x1801, 3) == struct.pack("<H", 10)


def test_sdo_segments_of_no_open_transfer_are_aborted(rig):
    """CiA 301 §7.2.4.3.4: a segment when no segmented transfer of its kind is open is
    answered with abort 0x05040001, not with a segment (raw frames to the drive)."""
    rig.boot()

    def request(data: bytes) -> bytes:
        rig.send(SDO_RX, data)
        rig.drive.poll()
        ((_, response),) = rig.frames()
        return response

    aborted = (0x80, 0x05040001)
    for stray in (b"\x60" + bytes(7), b"\x00" + bytes(7)):  # upload / download segment
        answer = request(stray)
        assert (answer[0], struct.unpack_from("<I", answer, 4)[0]) == aborted
    # 0x1008 "hdhil drive" (11 bytes) is uploaded in two segments; a third is refused.
    assert request(struct.pack("<BHB4x", 0x40, 0x1008, 0)) == struct.pack(
        "<BHBI", 0x41, 0x1008, 0, 11
    )
    assert request(b"\x60" + bytes(7)) == b"\x00hdhil d"
    assert request(b"\x70" + bytes(7)) == b"\x17rive" + bytes(3)
    answer = request(b"\x60" + bytes(7))
    assert (answer[0], struct.pack("<HB", 0x1008, 0)) == (0x80, answer[1:4])
    assert struct.unpack_from("<I", answer, 4)[0] == 0x05040001
    assert rig.drive.services.counters.sdo_protocol_errors == 3


# ======================================================================= diagnostics


def test_late_and_malformed_commands_are_counted(rig):
    rig.start()
    rig.cycle()
    rig.send(RPDO1, bytes(3))
    rig.drive.poll()
    assert rig.drive.diagnostics.malformed_frames == 1
    rig.drive.tick(rig.now + 1.5 * Ts)  # a command 2.5 periods after its SYNC
    rig.send(RPDO1, codec("control", "DRIVE_RPDO1").encode(0, SHUTDOWN, 0))
    rig.drive.poll()
    assert rig.drive.diagnostics.late_commands == 1
    assert rig.drive.unknown_frames == {}


# ===================================================================== CiA 402 CST


def _remap_rpdo1_to_cst(drive: DriveNode) -> None:
    """CiA 301 mapping procedure, as a master does it by SDO: RPDO1 = target torque
    0x6071 + controlword 0x6040; TPDO1 = torque actual 0x6077 + position actual 0x6064."""
    s = drive.services
    s.write(0x1400, 1, 0x80000202)
    s.write(0x1600, 0, 0)
    s.write(0x1600, 1, 0x60710010)
    s.write(0x1600, 2, 0x60400010)
    s.write(0x1600, 0, 2)
    s.write(0x1400, 1, 0x00000202)
    s.write(0x1800, 1, 0x80000182)
    s.write(0x1A00, 0, 0)
    s.write(0x1A00, 1, 0x60770010)
    s.write(0x1A00, 2, 0x60640020)
    s.write(0x1A00, 0, 2)
    s.write(0x1800, 1, 0x00000182)


def test_cst_torque_through_0x6071_moves_the_joint_as_the_raw_dac_object_does():
    """The same torque commanded through the standard target torque (per mille of the
    rated torque) and through the seed's raw DAC object moves the emulated joint the same
    way (within the DAC's quantisation, which both paths share), and the CST TPDO reports
    torque actual and position actual."""
    cfg = PlantConfig(sensors=SensorConfig(torque_noise_Nm=0.0, tacho_noise_radps=0.0))
    runs = {}
    for how in ("raw", "cst"):
        r = Rig(plant_cfg=cfg, truth=False)
        try:
            r.start()
            if how == "cst":
                _remap_rpdo1_to_cst(r.drive)
            rated = r.drive.services.read(0x6076) * 1e-3  # Nm
            per_mille = 250
            torque = per_mille * 1e-3 * rated
            dac = r.plant.cfg.dac.to_counts(torque / r.plant.cfg.torque_per_volt)
            velocities, tpdo = [], []
            for k in range(300):
                cw = (SHUTDOWN, SWITCH_ON, ENABLE)[min(k, 2)]
                command = dac if k >= 4 else 0
                if how == "raw":
                    frames = r.cycle(cw, command)
                else:
                    frames = r.cycle()
                    tq = per_mille if k >= 4 else 0
                    r.send(RPDO1, tq.to_bytes(2, "little", signed=True) + cw.to_bytes(2, "little"))
                    r.drive.poll()
                    frames += r.frames()
                    tpdo += [d for i, d in frames if i == 0x182]
                velocities.append(r.plant.truth().omega_motor_radps)
            runs[how] = (velocities, tpdo, r.drive.state_machine.state)
        finally:
            r.close()
    raw, cst = runs["raw"][0], runs["cst"][0]
    assert runs["cst"][2] is State.OPERATION_ENABLED
    assert max(abs(v) for v in raw) > 1.0  # the joint moved
    assert (
        max(abs(a - b) for a, b in zip(raw, cst, strict=True)) <= 1e-9 * max(map(abs, raw)) + 1e-9
    )
    frames = runs["cst"][1]
    assert frames and {len(f) for f in frames} == {6}
    torque_actual = [int.from_bytes(f[:2], "little", signed=True) for f in frames]
    position = [int.from_bytes(f[2:6], "little", signed=True) for f in frames]
    assert abs(torque_actual[-1] - 250) <= 5  # per mille of rated torque
    assert position[-1] != position[0]


def test_a_synchronous_tpdo_mapped_at_run_time_is_sent_beside_the_default_tpdo1(rig):
    """TPDO3 mapped by the CiA 301 procedure (statusword, transmission type 2) goes out on
    every second SYNC while TPDO1 keeps its default mapping and goes out on every SYNC."""
    rig.boot()
    tpdo3 = 0x382
    writes = [
        (0x1A02, 0, b"\x00"),
        (0x1A02, 1, struct.pack("<I", 0x60410010)),
        (0x1A02, 0, b"\x01"),
        (0x1802, 2, b"\x02"),
        (0x1802, 1, struct.pack("<I", tpdo3)),  # valid
    ]
    for index, sub, data in writes:
        assert sdo_download(rig, index, sub, data) is None, hex(index)
    rig.nmt(NmtCommand.START)
    seen = [ids(rig.cycle(SHUTDOWN)) for _ in range(4)]
    assert [s.count(TPDO1) for s in seen] == [1, 1, 1, 1]
    assert [s.count(tpdo3) for s in seen] == [0, 1, 0, 1]

"""The drive node: the plant emulator behind a CiA 301 / CiA 402 CANopen device.

:class:`DriveNode` composes small parts, as a canopen node does: the CiA 301 services
(:class:`hdhil.canopen.services.CanopenServices`), the CiA 402 state machine
(:class:`hdhil.canopen.cia402.DriveStateMachine`), the process data and SYNC cycle
(:class:`~.cyclic.CyclicIO`), the CST objects (:class:`~.cst.CstObjects`), the
emulator's own objects (:class:`~.emulator.EmulatorObjects`) and the truth publisher
(:class:`~.truth_channel.TruthPublisher`). The node wires them to each other, to the
frames and to the plant, and answers what concerns the device as a whole: NMT states,
the heartbeat, EMCY, the CiA 402 objects and a lost connection. It holds no physics.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import can

from hdhil.can.node import CanNode
from hdhil.canopen.cia402 import (
    CONTROLWORD,
    CONTROLWORD_OBJECT,
    STATUSWORD_OBJECT,
    SUPPORTED_MODES,
    Command,
    DriveStateMachine,
    State,
)
from hdhil.canopen.od import index_of
from hdhil.canopen.services import (
    ABORT_INVALID_VALUE,
    CanopenServices,
    EmcyCode,
    NmtState,
    ResetKind,
)
from hdhil.dbc import eds_path
from hdhil.hostsim.drive.config import DriveConfig, DriveDiagnostics, EmcyRecord
from hdhil.hostsim.drive.cst import CstObjects
from hdhil.hostsim.drive.cyclic import CyclicIO
from hdhil.hostsim.drive.emulator import EmulatorObjects
from hdhil.hostsim.drive.truth_channel import TruthPublisher
from hdhil.hostsim.plant import Plant
from hdhil.hostsim.plant_model import PlantModel
from hdhil.hostsim.sensor_faults import SensorFaultSource

__all__ = [
    "OD_ABORT_CONNECTION",
    "OD_ERROR_CODE",
    "OD_FAULT_REACTION_OPTION",
    "OD_MODES_DISPLAY",
    "OD_MODES_OF_OPERATION",
    "OD_QUICK_STOP_OPTION",
    "DriveNode",
]

OD_ABORT_CONNECTION = 0x6007
OD_ERROR_CODE = 0x603F
OD_QUICK_STOP_OPTION = 0x605A
OD_FAULT_REACTION_OPTION = 0x605E
OD_MODES_OF_OPERATION = 0x6060
OD_MODES_DISPLAY = 0x6061

_OPERATIONAL = NmtState.OPERATIONAL


class DriveNode(CanNode):
    """Drive emulator node (CANopen node-ID 2, ``dbc/drive.eds``): amplifier, harmonic
    drive, sensors.

    Every received frame goes through ``services.handle`` first, timed with the ``now``
    of the latest :meth:`tick`; SYNC and PDOs go to the process data
    (:class:`~hdhil.hostsim.drive.cyclic.CyclicIO`, which documents the cycle's timing,
    the statusword TPDO, the command hold and the sensor EMCY).

    **Power-on and NMT** (CiA 301 §7.3.2).  :meth:`boot` sends the boot-up message
    (0x702, data 00) and enters PRE-OPERATIONAL; the CiA 402 self-initialisation completes
    at once (transition 1: NOT READY TO SWITCH ON -> SWITCH ON DISABLED).  What each NMT
    state allows (CiA 301 table "NMT states and communication objects"):

    =================  ==============================================================
    NMT state          drive behaviour
    =================  ==============================================================
    INITIALISING       before ``boot`` only: nothing is sent, frames are not processed
    PRE-OPERATIONAL    SDO, EMCY, heartbeat; no PDOs: no sensor TPDO, no statusword
                       TPDO, no truth frames, received DRIVE_RPDO1 frames are ignored
    OPERATIONAL        everything; entering it sends the statusword TPDO once
    STOPPED            heartbeat and NMT only (no SDO answers, no EMCY frames)
    =================  ==============================================================

    Leaving OPERATIONAL (NMT stop, enter pre-operational, a reset) is a lost connection
    for CiA 402: commands only arrive by PDO, and PDOs stop outside OPERATIONAL.  The
    drive reacts as its abort connection option code 0x6007 says (CiA 402-2,
    :meth:`react_to_connection_loss`): 2 (default) "disable voltage" (the last command is
    dropped, SWITCH ON DISABLED), 3 "quick stop", 1 "fault signal" (fault and EMCY 0x8100
    "communication - generic", cleared when OPERATIONAL is entered again), 0 "no action"
    (the last command stays until the command hold faults the drive).  An NMT reset node
    brings the application back to power-on: a new CiA 402 machine (SWITCH ON DISABLED),
    no command, the emulator parameters (0x2300) back to the values the plant was built
    with, errors cleared.  An NMT reset communication restores 0x1000-0x1FFF only (CiA 301
    §7.3.2.2.2).

    **CiA 402** (CiA 402-2, "PDS finite state automaton").  The controlword of
    DRIVE_RPDO1 drives ``DriveStateMachine.apply_controlword`` with the same timing as the
    DAC command: at the next SYNC with synchronous actuation (the whole synchronous RPDO
    is actuated at SYNC, CiA 301 §7.2.2.2), on receipt with immediate actuation.  The
    usual walk is shutdown 0x06 -> switch on 0x07 -> enable operation 0x0F; 0x80 (rising
    edge) resets a fault.  The amplifier follows the DAC command only in OPERATION ENABLED
    in mode CST (0x6060 = 10; ``DriveStateMachine.torque_output``), ramps it down during a
    quick stop or fault reaction with a ramp time (``DriveConfig.quick_stop_time_s``, 0 =
    torque off at once), and gets 0 V otherwise.  Quick stop behaviour follows 0x605A, the
    fault reaction 0x605E (0 = disable drive function; 1-4 = ramp over
    ``quick_stop_time_s``).

    **Heartbeat** (CiA 301 §7.2.8.3.2): producer 0x1017 = ``heartbeat_ms`` (100 ms); the
    consumer 0x1016 monitors the controller (node-ID 1) with
    ``controller_heartbeat_timeout_ms`` (250 ms), from its first heartbeat on.  On a loss:
    EMCY 0x8130 (manufacturer byte 0 = the lost node-ID), and a CiA 402 fault (0x603F =
    0x8130; FAULT REACTION ACTIVE -> FAULT, torque off) that cannot be reset while the
    heartbeat is missing.  Recovery: the heartbeat resumes (EMCY 0x0000), then the
    controller sends a fault reset (0x80 edge) and walks the drive up again.

    **SDO**: the checked server of ``CanopenServices`` (types, lengths, access, LowLimit
    / HighLimit of the EDS, with CiA 301 abort codes; a refused write changes nothing).
    Live values are read from the node: 0x6041 statusword, 0x6040 controlword (as last
    applied), 0x6061 mode display, 0x603F error code, 0x2100 ADC counts, 0x2101 encoder
    count and 0x2102 joint-torque sensor (mV) of the latest sample, the CST objects
    (:class:`~hdhil.hostsim.drive.cst.CstObjects`).
    Writable application objects: 0x2300 and 0x2310
    (:class:`~hdhil.hostsim.drive.emulator.EmulatorObjects`); 0x6040 controlword, an SDO
    write applied at once, like an immediate RPDO; 0x6007 abort connection option code
    (0..3), 0x605A quick stop option code (0..8), 0x605E fault reaction option code
    (0..4), 0x6060 modes of operation (0 or 10, else abort 0x06090030).
    """

    def __init__(
        self,
        bus: can.BusABC,
        plant: PlantModel,
        config: DriveConfig | None = None,
        truth_bus: can.BusABC | None = None,
        faults: SensorFaultSource | None = None,
    ) -> None:
        """``faults`` is the run's fault injector, the one whose ``sensors()`` hook the
        plant has (if any): its seed and log serve the faults switched on through object
        0x2310.  Without one the drive keeps its own (seed 0; the plant's hook's log).

        ``plant`` is any :class:`hdhil.hostsim.plant_model.PlantModel`; the emulator's
        extras (0x2300 and the sensor faults of 0x2310) need the emulator's own
        :class:`hdhil.hostsim.plant.Plant` and are refused (SDO abort) for another model."""
        cfg = config or DriveConfig()
        super().__init__(bus, drive_node_id=cfg.node_id, controller_node_id=cfg.controller_node_id)
        self.plant = plant
        self.config = cfg
        self.diagnostics = DriveDiagnostics()
        if isinstance(plant, Plant):  # its step map now, not in the middle of a cycle
            plant.prepare(cfg.sample_period_s)
        #: The node's time: the ``now`` of the latest :meth:`boot` or :meth:`tick`.
        self.now = 0.0
        self.truth_publisher = TruthPublisher(truth_bus, cfg.truth_joint_index)

        # CiA 301 services on the drive's object dictionary.
        consumers = (
            {cfg.controller_node_id: cfg.controller_heartbeat_timeout_ms}
            if cfg.controller_heartbeat_timeout_ms
            else {}
        )
        self.services = services = CanopenServices(
            bus,
            cfg.node_id,
            eds_path("drive"),
            heartbeat_producer_ms=cfg.heartbeat_ms,
            heartbeat_consumers=consumers,
        )
        self.emulator = EmulatorObjects(services, plant, bus, lambda: self.now, faults)
        # CiA 402 objects found by name in the drive's EDS.
        self._od_controlword = index_of(services.od, CONTROLWORD_OBJECT)
        self._od_statusword = index_of(services.od, STATUSWORD_OBJECT)
        self.cst = CstObjects(services, plant)
        services.on_state_change(self._on_nmt_state)
        services.on_reset(self._on_nmt_reset)
        services.on_heartbeat_lost(self._on_heartbeat_lost)
        services.on_heartbeat_resumed(self._on_heartbeat_resumed)
        self.io = CyclicIO(self)
        self._register_od_callbacks()
        #: The CiA 402 power drive system (a new one after an NMT reset node).
        self.machine = self._new_state_machine()
        self.io.load_pdos()

    # ------------------------------------------------------------------ public API

    def boot(self, now: float) -> None:
        """Power-on: boot-up message, NMT PRE-OPERATIONAL (CiA 301 §7.3.2.2), and the CiA 402
        self-initialisation (transition 1: NOT READY TO SWITCH ON -> SWITCH ON DISABLED)."""
        self.now = now
        self.services.boot(now)
        self.machine.complete_initialisation()
        self.io.step_V = self.machine.torque_output(self.io.active_V)

    def tick(self, now: float) -> None:
        """Advance the node's clock: heartbeat producer and consumer (CiA 301 §7.2.8.3.2),
        event-driven TPDOs held back by their inhibit time or due by their event timer,
        the RPDO event-timer deadlines and the SYNC timeout.  Call every cycle before
        polling."""
        self.now = now
        self.services.tick(now)
        if self.services.state is _OPERATIONAL:
            self.io.check_deadlines(now)
        self.io.flush_statusword()

    def on_message(self, msg: can.Message) -> None:
        """CANopen service frames to the services, SYNC and PDOs to this node."""
        services = self.services
        if msg.arbitration_id in services.service_ids and services.handle(msg):
            self.io.flush_statusword()
            return
        CanNode.on_message(self, msg)

    @property
    def nmt_state(self) -> NmtState:
        return self.services.state

    @property
    def drive_state(self) -> State:
        """The CiA 402 PDS state."""
        return self.machine.state

    @property
    def state_machine(self) -> DriveStateMachine:
        return self.machine

    @property
    def statusword(self) -> int:
        """Object 0x6041 now (what the next DRIVE_TPDO2 carries)."""
        return self.machine.statusword

    @property
    def torque_enabled(self) -> bool:
        """True only in OPERATION ENABLED (the amplifier follows the command)."""
        return self.machine.torque_enabled

    @property
    def amplifier_input_V(self) -> float:
        """The amplifier input over the plant step in progress (0 V unless enabled)."""
        return self.io.step_V

    @property
    def truth_bus(self) -> can.BusABC | None:
        """The truth channel (None: no truth is published)."""
        return self.truth_publisher.bus

    @truth_bus.setter
    def truth_bus(self, bus: can.BusABC | None) -> None:
        self.truth_publisher.bus = bus

    @property
    def faults(self) -> SensorFaultSource:
        """Where the faults switched on through 0x2310 come from (and are logged)."""
        return self.emulator.faults

    @property
    def silent(self) -> bool:
        """True while a silence written to 0x2310 sub 8 lasts (the drive sends nothing)."""
        return self.emulator.silent

    def emcy(self, code: int, manufacturer: bytes = b"") -> bool:
        """Signal an error: EMCY ``code`` (sent if NMT allows), recorded in the
        diagnostics.  True when the frame went out."""
        sent = self.services.emcy.raise_error(code, manufacturer=manufacturer)
        d = self.diagnostics
        d.emcy_sent += 1
        d.emcy_log.append(EmcyRecord(self.now, code, manufacturer.ljust(5, b"\0"), sent))
        return sent

    def react_to_connection_loss(self, emcy_sent: int | None) -> None:
        """The abort connection option code 0x6007 (CiA 402-2): 0 none, 1 fault, 2 disable
        voltage, 3 quick stop; for leaving OPERATIONAL, an RPDO deadline or a SYNC loss.
        ``emcy_sent`` is the EMCY already sent for the cause (None: leaving OPERATIONAL,
        option 1 sends 0x8100)."""
        option = self.services.read(OD_ABORT_CONNECTION)
        if option == 0:  # no action: the command hold still faults a drive left running
            return
        self.io.drop_command()
        machine = self.machine
        if machine.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return
        if option == 1:
            if emcy_sent is None:
                self.emcy(EmcyCode.COMMUNICATION)
            machine.fault(emcy_sent or EmcyCode.COMMUNICATION)
        elif option == 3:
            machine.apply_controlword(CONTROLWORD[Command.QUICK_STOP])
        else:
            machine.apply_controlword(CONTROLWORD[Command.DISABLE_VOLTAGE])

    # ------------------------------------------------------------------ NMT

    def _on_nmt_state(self, old: NmtState, new: NmtState) -> None:
        if old is NmtState.OPERATIONAL:
            self.react_to_connection_loss(None)  # PDOs stop
        if new is NmtState.OPERATIONAL:
            self.io.enter_operational()
            self.services.emcy.clear(EmcyCode.COMMUNICATION)

    def _on_nmt_reset(self, kind: ResetKind) -> None:
        """CiA 301 §7.3.2.2.2: reset node restores the application to power-on."""
        self.diagnostics.nmt_resets += 1
        self.io.reset_communication()
        if kind != "node":
            return
        self.machine = self._new_state_machine()
        self.machine.complete_initialisation()
        self.io.reset_application()
        self.emulator.reset()

    # ------------------------------------------------------------------ heartbeat

    def _on_heartbeat_lost(self, node_id: int) -> None:
        """Heartbeat consumer timeout (EMCY 0x8130 already sent by the services)."""
        d = self.diagnostics
        d.heartbeat_losses += 1
        d.emcy_sent += 1
        d.emcy_log.append(
            EmcyRecord(self.now, EmcyCode.HEARTBEAT, bytes((node_id,)).ljust(5, b"\0"),
                       self.services.emcy_allowed)
        )  # fmt: skip
        if node_id == self.config.controller_node_id:
            self.machine.fault(EmcyCode.HEARTBEAT, persists=True)

    def _on_heartbeat_resumed(self, node_id: int) -> None:
        if node_id == self.config.controller_node_id:
            self.machine.clear_fault_condition()

    # ------------------------------------------------------------------ CiA 402 objects

    def _new_state_machine(self) -> DriveStateMachine:
        read = self.services.read
        ramp = self.config.quick_stop_time_s
        return DriveStateMachine(
            quick_stop_option=read(OD_QUICK_STOP_OPTION),
            quick_stop_time_s=ramp,
            fault_reaction_time_s=ramp if read(OD_FAULT_REACTION_OPTION) else 0.0,
            mode=read(OD_MODES_OF_OPERATION),
        )

    def _register_od_callbacks(self) -> None:
        s = self.services
        s.add_validator(
            OD_MODES_OF_OPERATION,
            0,
            lambda mode: None if mode in SUPPORTED_MODES else ABORT_INVALID_VALUE,
        )
        s.on_write(OD_MODES_OF_OPERATION, 0, lambda mode: self.machine.set_mode(mode))
        s.on_write(OD_QUICK_STOP_OPTION, 0, self._set_quick_stop_option)
        s.on_write(OD_FAULT_REACTION_OPTION, 0, self._set_fault_reaction_option)
        s.on_write(self._od_controlword, 0, self._sdo_controlword)
        live: dict[tuple[int, int], Callable[[], int]] = {
            (self._od_statusword, 0): lambda: self.machine.statusword,
            (self._od_controlword, 0): lambda: self.machine.controlword,
            (OD_MODES_DISPLAY, 0): lambda: self.machine.modes_of_operation_display,
            (OD_ERROR_CODE, 0): lambda: self.machine.error_code,
            **self.io.live_values(),
            **self.cst.live_values(),
        }

        def read_live(index: int, subindex: int, od: Any, **_: Any) -> int | None:
            getter = live.get((index, subindex))
            return None if getter is None else getter()

        s.node.add_read_callback(read_live)

    def _set_quick_stop_option(self, value: int) -> None:
        self.machine.quick_stop_option = value

    def _set_fault_reaction_option(self, value: int) -> None:
        self.machine.fault_reaction_time_s = self.config.quick_stop_time_s if value else 0.0

    def _sdo_controlword(self, value: int) -> None:
        self.machine.apply_controlword(value)

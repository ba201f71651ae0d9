"""The controller node: the firmware's interrupt handler behind a CANopen link.

:class:`ControllerNode` is composed of parts, as canopen composes a node of its services:
the CANopen services (:class:`hdhil.canopen.services.CanopenServices`), its object
dictionary (:mod:`.objects`), the boot and stop sequencer (:mod:`.sequencer`), the cyclic
I/O of the 1 kHz path (:mod:`.cyclic`) and the supervision (:mod:`.supervision`).  The
node builds and wires them, owns the link phase and its changes (including the way into
"safe"), and keeps the entry points the runner drives: ``boot``, ``tick``, ``send_sync``,
``request_stop`` and the frame handler.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import can

from hdhil.can.node import CanNode, pdo_cob_id
from hdhil.canopen.cia402 import State
from hdhil.canopen.dcf import DcfConfigurator, configuration_writes
from hdhil.canopen.sdo import ABORT_DEVICE_STATE, SdoClient
from hdhil.canopen.services import CanopenServices, NmtCommand, NmtState
from hdhil.dbc import eds_path
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.controller.codecs import LinkCodecs, default_codecs, mapped_codecs
from hdhil.firmware.controller.cyclic import CycleProbe, CyclicIo
from hdhil.firmware.controller.diagnostics import ControllerDiagnostics
from hdhil.firmware.controller.objects import ControllerObjects
from hdhil.firmware.controller.phases import COMMANDING, FINAL, Phase, PhaseChange
from hdhil.firmware.controller.sequencer import Sequencer
from hdhil.firmware.controller.supervision import Supervision
from hdhil.firmware.interrupt import InterruptHandlerModel
from hdhil.firmware.isr import InterruptHandler
from hdhil.firmware.odlimits import check_od_limits
from hdhil.firmware.walk import Cia402Walk

__all__ = ["ControllerNode"]

# The phases the per-cycle code tests for, as module globals: an attribute of an Enum class
# (``Phase.OPERATIONAL``) is looked up through ``EnumType.__getattr__``'s slow path in
# Python 3.11, several times slower than a global.
_WAIT_BOOT = Phase.WAIT_BOOT
_STARTING = Phase.STARTING
_OPERATIONAL = Phase.OPERATIONAL
_STOPPING = Phase.STOPPING
_INITIALISING = NmtState.INITIALISING


class ControllerNode(CanNode):
    """SYNC producer, NMT master, CiA 402 controlling device and torque-sensing firmware
    (CANopen node-ID 1).

    The controller is an NMT slave itself (boot-up 0x701, heartbeat producer 0x701 every
    100 ms, SDO server on 0x601/0x581, EMCY producer 0x081) and the NMT master, SYNC
    producer and CiA 402 controlling device of the drive (node-ID 2, heartbeat consumer
    with 250 ms).  The runner drives it without threads::

        controller.boot(now)                   # boot-up 0x701, wait for the drive's boot-up
        every cycle k (now = k * Ts):
            controller.tick(now)               # heartbeats, timeouts, sequencer, parameters
            if controller.boot_error: fail with it (one line)
            if controller.phase in ("stopped", "safe"): end the run
            controller.send_sync()             # False when no SYNC went out
            poll the nodes until the cycle's frames are handled

    The phases are :class:`~hdhil.firmware.controller.phases.Phase`'s table.  On entering
    "safe" from a commanding phase the controller stops commanding at once (no further
    RPDO, no SYNC) and sends NMT "enter pre-operational" for the drive: a CiA 402 drive
    reacts to leaving OPERATIONAL with its abort-connection option (0x6007: fault, disable
    voltage or quick stop), the one torque-off path that works whether the drive takes its
    RPDO over on receipt or at the next SYNC (none follows).  A last "disable voltage"
    RPDO would not help: sent at the same instant, the NMT frame (identifier 0) wins
    arbitration and the drive, already pre-operational, drops the PDO.  The controller
    goes PRE-OPERATIONAL itself, so its heartbeat reports it.

    The parts are attributes: ``services``, ``objects`` (OD values, live parameters),
    ``sequencer`` (start-up and stop), ``io`` (SYNC, sensor frame, command, telemetry)
    and ``supervision`` (heartbeat, NMT, sensor EMCYs).  The node uses nothing but a
    python-can bus, so the same node drives the emulator on ``simbus`` or a real drive
    on SocketCAN/PCAN/Kvaser; it never subscribes to ground truth.  PDO COB-IDs come from
    the object dictionaries at the node-IDs: its own telemetry at ``node_id``'s
    (``$NODEID+0x180``, ``$NODEID+0x280`` in its EDS), the PDOs it exchanges with the
    drive at ``drive_node_id``'s (the drive's EDS or DCF there); the layouts are
    ``control.dbc``'s.

    Args:
        bus: the control bus (any python-can bus).
        config: the firmware configuration (the scenario's); written into the OD.
        sync_overflow: SYNC counter overflow, object 0x1019 (CiA 301: 2..240 here).
        node_id: this node's CANopen node-ID.
        drive_node_id: the drive's node-ID (NMT, heartbeat consumer, SDO client).
        heartbeat_ms: heartbeat producer time (0x1017).
        drive_heartbeat_timeout_ms: heartbeat consumer time for the drive (0x1016:1).
        boot_timeout_s: how long ``boot`` waits for the drive's boot-up.
        sensor_hold_cycles: SYNCs without a sensor frame tolerated in "operational".
        isr: the interrupt handler (default: the firmware's own,
            :class:`hdhil.firmware.isr.InterruptHandler`).
        drive_dcf: the drive's DCF: the controller configures the drive from it at boot
            and gives its own PDOs the matching mapping (:mod:`.objects`, :mod:`.codecs`);
            in the CiA 402 CST mapping it reads the drive's rated torque 0x6076 before NMT
            start and the [Vertechy] control laws are refused.
    """

    #: A walk step without statusword for this long reads the statusword by SDO.
    STATUSWORD_TIMEOUT_S = 0.02
    #: A start-up or stop walk must be done within this time.
    WALK_TIMEOUT_S = 1.0
    #: Automatic fault resets per node lifetime (CiA 402 transition 15).
    MAX_FAULT_RESETS = Cia402Walk.MAX_FAULT_RESETS

    def __init__(
        self,
        bus: can.BusABC,
        config: FirmwareConfig,
        sync_overflow: int = 240,
        *,
        node_id: int = 1,
        drive_node_id: int = 2,
        heartbeat_ms: int = 100,
        drive_heartbeat_timeout_ms: int = 250,
        boot_timeout_s: float = 2.0,
        sensor_hold_cycles: int = 10,
        isr: InterruptHandlerModel | None = None,
        drive_dcf: str | Path | None = None,
    ) -> None:
        _check_arguments(sync_overflow, node_id, drive_node_id, boot_timeout_s,
                         sensor_hold_cycles)  # fmt: skip
        super().__init__(bus, drive_node_id=drive_node_id, controller_node_id=node_id)
        check_od_limits(config)  # every OD parameter representable in its entry
        self.config = config
        #: The interrupt handler (:class:`firmware.interrupt.InterruptHandlerModel`): the
        #: firmware's own unless ``isr`` is given; the plausibility EMCYs and the SDO
        #: parameters that retune stages need the firmware's own (``own_isr``).
        self.isr: InterruptHandlerModel = InterruptHandler(config) if isr is None else isr
        self.own_isr = isinstance(self.isr, InterruptHandler)
        self.diagnostics = ControllerDiagnostics()
        self.sync_overflow = sync_overflow
        self.node_id = node_id
        self.drive_node_id = drive_node_id
        self.boot_timeout_s = boot_timeout_s
        self.sensor_hold_cycles = sensor_hold_cycles
        #: Why the drive never booted (one line for the user); None otherwise.
        self.boot_error: str | None = None
        #: The link phase (:class:`Phase`; changed by the node's parts only).
        self.phase = Phase.WAIT_BOOT
        #: The latest ``now`` given to ``boot``/``tick`` (s).
        self.now = 0.0
        #: True while the node changes its own NMT state (not a command of another master).
        self.own_nmt = False
        #: The drive's motor rated torque 0x6076 (Nm), read by SDO at boot in the CiA 402
        #: CST mapping; None in the raw mapping (or before the read).
        self.rated_torque_Nm: float | None = None

        self.services = CanopenServices(
            bus,
            node_id,
            eds_path("controller"),
            heartbeat_producer_ms=heartbeat_ms,
            heartbeat_consumers={drive_node_id: drive_heartbeat_timeout_ms},
        )
        _address_drive(self.services, drive_node_id, drive_dcf)
        self.objects = objects = ControllerObjects(self)
        self.supervision = Supervision(self)  # subscribes to the services' NMT events
        #: The SDO client of the drive's server (DCF writes, statusword and rated torque).
        self.sdo = SdoClient(bus, drive_node_id)
        #: Boot-time configuration of the drive from its DCF (CiA 306), by SDO, after its
        #: boot-up and before NMT start; None without a DCF.
        self.configurator = (
            DcfConfigurator(self.sdo, configuration_writes(drive_dcf, drive_node_id))
            if drive_dcf is not None
            else None
        )
        if drive_dcf is not None:
            objects.take_drive_mapping(drive_dcf)  # ValueError: a mapping it cannot run
        self.walk = Cia402Walk(drive_node_id, objects.mirror_controlword)
        codecs = self._codecs()
        #: Which sensor objects the drive sends: "raw" (the seed's ADC counts and encoder),
        #: "cst" (CiA 402 torque actual 0x6077 and position actual 0x6064) or "cst-sensor"
        #: (those and the joint-torque sensor 0x2102), as read from the live mapping.
        self.sensor_mapping = codecs.sensor_mapping
        self.sequencer = Sequencer(self, codecs.status)
        self.io = CyclicIo(self, codecs)
        #: CTRL_TPDO2 is valid (sent) only while a control law runs (COB-ID bit 31 clear).
        self.control_pdo_valid = config.control.active
        objects.store_control_pdo_validity()
        self._route(codecs)

    def _codecs(self) -> LinkCodecs:
        """``control.dbc``'s codecs, or those of the mapping taken from the drive's DCF; in
        the CST mapping no control law may be switched on later either.  Each at the
        identifier the object dictionary gives its PDO (RPDO1 0x1400, RPDO2 0x1401, TPDO1-3
        0x1800-0x1802: this node's own telemetry at its node-ID, the drive's PDOs at the
        drive's), its layout checked against the one the node encodes with."""
        services = self.services
        if not self.objects.pdo_writes:
            codecs = default_codecs()
        else:
            codecs = mapped_codecs(services.od, services.read, self.config.control.active)
            if codecs.sensor_mapping == "cst":
                services.add_validator(0x2420, 1, lambda law: ABORT_DEVICE_STATE if law else None)
        od, read = services.od, services.read
        return replace(
            codecs,
            sensor=codecs.sensor.at(pdo_cob_id(od, 0x1400, codecs.sensor, read)),
            status=codecs.status.at(pdo_cob_id(od, 0x1401, codecs.status, read)),
            telemetry=codecs.telemetry.at(pdo_cob_id(od, 0x1800, codecs.telemetry, read)),
            control_telemetry=codecs.control_telemetry.at(
                pdo_cob_id(od, 0x1801, codecs.control_telemetry, read)
            ),
            command=codecs.command.at(pdo_cob_id(od, 0x1802, codecs.command, read)),
        )

    def _route(self, codecs: LinkCodecs) -> None:
        """Frames to the parts, at the identifiers of :meth:`_codecs`."""
        self.handle(codecs.sensor.frame_id, self.io.on_sensor_frame)
        self.handle(codecs.status.frame_id, self.sequencer.on_statusword_frame)
        self.handle(self.sdo.response_id, self.sequencer.on_sdo_response)

    # ------------------------------------------------------------------ public API

    @property
    def probe(self) -> CycleProbe | None:
        """The instrumentation hook of the cycle
        (:class:`~hdhil.firmware.controller.cyclic.CycleProbe`): SYNC sent, sensor frame
        received, interrupt run, command sent, each with its time stamp.  None (the
        default) costs one check per event."""
        return self.io.probe

    @probe.setter
    def probe(self, probe: CycleProbe | None) -> None:
        self.io.probe = probe

    @property
    def done(self) -> bool:
        """True once ``num_samples`` interrupts have run (listing: ``samplecount < numsamples``)."""
        return self.isr.done

    @property
    def drive_state(self) -> State | None:
        """The drive's CiA 402 state from its latest statusword (None before the first)."""
        return self.walk.drive_state

    @property
    def controlword(self) -> int:
        """The controlword the next DRIVE_RPDO1 carries."""
        return self.walk.controlword

    def boot(self, now: float) -> None:
        """Power-on (CiA 301 §7.3.2.2): boot-up message 0x701, PRE-OPERATIONAL, and, as NMT
        master, start waiting ``boot_timeout_s`` for the drive's boot-up."""
        self.now = now
        self.services.boot(now)
        self.services.nmt.expect_boot(self.drive_node_id, now, self.boot_timeout_s)
        self.set_phase(Phase.WAIT_BOOT, "power on: waiting for the drive's boot-up")

    def tick(self, now: float) -> None:
        """Once per cycle, before polling: heartbeat producer and consumer (may enter
        "safe"), parameters written last cycle, the drive's boot-up wait and its timeout,
        the sensors' error flags."""
        self.now = now
        services = self.services
        services.tick(now)
        self.objects.apply_pending()
        if self.phase is _WAIT_BOOT and services.state is not _INITIALISING:
            self.sequencer.await_drive()
        if self.own_isr:  # our InterruptHandler: its plausibility and stuck-channel flags
            self.supervision.check_sensors()
        d = self.diagnostics
        d.emcy_sent = services.emcy.sent
        d.emcy_received = services.counters.emcy_received

    def send_sync(self) -> bool:
        """Start a cycle: SYNC with the CiA 301 counter (1..overflow, then 1 again).

        Sent in every phase but "stopped" and "safe", and only in an NMT state that allows
        it (not before ``boot``).  At this cycle boundary the node also applies new
        parameters, checks the sensor hold ("operational") and the walk's statusword
        timeouts ("starting"/"stopping").  Returns True if a SYNC went out.
        """
        self.objects.apply_pending()
        phase = self.phase
        if phase is _OPERATIONAL:
            if not self.io.sensor_hold_ok():
                return False
        elif phase is _STARTING or phase is _STOPPING:
            self.sequencer.watchdog()
            if self.phase in FINAL:
                return False
        elif phase in FINAL:
            return False
        return self.io.send_sync()

    def request_stop(self, reason: str = "stop requested") -> None:
        """Walk the drive back (controlword 0x0007, then 0x0006), then NMT pre-operational
        for the drive: phase "stopping", then "stopped".  No effect once stopping."""
        self.sequencer.request_stop(reason)

    def on_message(self, msg: can.Message) -> None:
        """CiA 301 service frames go to the services first; SYNC/PDOs to the handlers."""
        services = self.services
        if msg.arbitration_id not in services.service_ids or not services.handle(msg):
            CanNode.on_message(self, msg)

    # ------------------------------------------------------------ phases, faults

    def set_phase(self, phase: Phase, reason: str) -> None:
        """Enter ``phase`` (recorded in the diagnostics' phase history)."""
        self.phase = phase
        sequencer = self.sequencer
        sequencer.phase_cycles = 0
        sequencer.quiet_cycles = 0
        self.diagnostics.phase_history.append(PhaseChange(self.now, phase, reason))

    def enter_nmt(self, state: NmtState) -> None:
        """The controller changes its own NMT state (not a command from another master)."""
        services = self.services
        if services.state is _INITIALISING or services.state is state:
            return
        self.own_nmt = True
        try:
            services.enter_state(state)
        finally:
            self.own_nmt = False

    def enter_safe(self, reason: str, emcy: int | None = None, manufacturer: bytes = b"") -> None:
        """Stop commanding the drive for good (class docstring), with an EMCY if given."""
        if self.phase is Phase.SAFE:
            return
        services = self.services
        if emcy is not None:
            services.emcy.raise_error(emcy, manufacturer=manufacturer)
        if self.phase in COMMANDING and services.state is NmtState.OPERATIONAL:
            services.nmt.command(NmtCommand.ENTER_PRE_OPERATIONAL, self.drive_node_id)
        self.diagnostics.safe_reason = reason
        self.set_phase(Phase.SAFE, reason)
        if services.state is NmtState.OPERATIONAL:
            self.enter_nmt(NmtState.PRE_OPERATIONAL)
        self.diagnostics.emcy_sent = services.emcy.sent


def _check_arguments(
    sync_overflow: int,
    node_id: int,
    drive_node_id: int,
    boot_timeout_s: float,
    sensor_hold_cycles: int,
) -> None:
    if not 2 <= sync_overflow <= 240:
        raise ValueError(f"SYNC counter overflow must be 2..240 (CiA 301), got {sync_overflow}")
    if not 1 <= drive_node_id <= 127 or drive_node_id == node_id:
        raise ValueError(f"drive node-ID must be 1..127 and not {node_id}, got {drive_node_id}")
    if not (math.isfinite(boot_timeout_s) and boot_timeout_s > 0):
        raise ValueError(f"boot timeout must be > 0 s, got {boot_timeout_s}")
    if isinstance(sensor_hold_cycles, bool) or not (
        isinstance(sensor_hold_cycles, int) and sensor_hold_cycles >= 1
    ):
        raise ValueError(f"sensor_hold_cycles must be an integer >= 1, got {sensor_hold_cycles}")


#: The controller's PDOs that pair with the drive's: RPDO1 takes its TPDO1 (sensors),
#: RPDO2 its TPDO2 (statusword), TPDO3 is its RPDO1 (command).
_PEER_PDOS = ((0x1400, ("tpdo", 1)), (0x1401, ("tpdo", 2)), (0x1802, ("rpdo", 1)))


def _address_drive(
    services: CanopenServices, drive_node_id: int, drive_dcf: str | Path | None
) -> None:
    """Give the controller's PDOs that pair with the drive's the drive's COB-IDs as their
    power-on values: the drive's EDS or DCF at its node-ID
    (:func:`hdhil.canopen.rigdb.drive_pdo_layouts`; the pre-defined connection set moves
    with the node-ID), each PDO's validity as this node's EDS sets it."""
    from hdhil.canopen.rigdb import RigDrive, drive_pdo_layouts
    from hdhil.core.errors import UserError

    try:
        layouts = drive_pdo_layouts(RigDrive("", drive_node_id, dcf=drive_dcf))
    except UserError as exc:
        raise ValueError(str(exc)) from None
    for comm, key in _PEER_PDOS:
        layout = layouts.get(key)
        if layout is None:
            continue
        old = int(services.read(comm, 1))
        new = (old & ~0x7FF) | layout.cob_id
        if new != old:
            services.set_power_on_value(comm, 1, new)

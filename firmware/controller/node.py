"""The controller node: the firmware's interrupt handlers behind a CANopen link.

:class:`ControllerNode` is composed of parts, as canopen composes a node of its services:
the CANopen services (:class:`hdhil.canopen.services.CanopenServices`) and its object
dictionary (:mod:`.objects`), one per node, and per joint it serves
(:class:`~hdhil.firmware.controller.joint.ControllerJoint`) the boot and stop sequencer
(:mod:`.sequencer`), the cyclic I/O of the 1 kHz path (:mod:`.cyclic`) and the
supervision (:mod:`.supervision`).  The node builds and wires them, produces the bus's
SYNC, keeps its own NMT state, and keeps the entry points the runner drives: ``boot``,
``tick``, ``send_sync``, ``request_stop`` and the frame handler.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import can

from hdhil.can.node import CanNode
from hdhil.canopen.cia402 import State
from hdhil.canopen.dcf import DcfConfigurator
from hdhil.canopen.sdo import SdoClient
from hdhil.canopen.services import CanopenServices, NmtState, ResetKind
from hdhil.canopen.sync import SYNC_COB_ID
from hdhil.dbc import eds_path
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.controller.codecs import LinkCodecs
from hdhil.firmware.controller.cyclic import CycleProbe, CyclicIo
from hdhil.firmware.controller.diagnostics import ControllerDiagnostics
from hdhil.firmware.controller.joint import ControllerJoint, JointSetup
from hdhil.firmware.controller.link import MAX_JOINTS_PER_NODE, DriveLink
from hdhil.firmware.controller.objects import ControllerObjects
from hdhil.firmware.controller.phases import COMMANDING, FINAL, Phase
from hdhil.firmware.controller.sequencer import Sequencer
from hdhil.firmware.controller.supervision import Supervision
from hdhil.firmware.interrupt import InterruptHandlerModel
from hdhil.firmware.walk import Cia402Walk

__all__ = ["ControllerNode"]

# The phases the per-cycle code tests for, as module globals: an attribute of an Enum class
# (``Phase.OPERATIONAL``) is looked up through ``EnumType.__getattr__``'s slow path in
# Python 3.11, several times slower than a global.
_WAIT_BOOT = Phase.WAIT_BOOT
_STARTING = Phase.STARTING
_OPERATIONAL = Phase.OPERATIONAL
_STOPPING = Phase.STOPPING
_SAFE = Phase.SAFE
_INITIALISING = NmtState.INITIALISING
#: Which joint phase a node of several joints reports (the first found, in this order).
_NODE_PHASE_ORDER = (_WAIT_BOOT, _STARTING, _STOPPING, _OPERATIONAL)


class ControllerNode(CanNode):
    """SYNC producer, NMT master, CiA 402 controlling device and torque-sensing firmware
    (CANopen node-ID 1), for one joint or several on one bus.

    The controller is an NMT slave itself (boot-up 0x701, heartbeat producer 0x701 every
    100 ms, SDO server on 0x601/0x581, EMCY producer 0x081) and the NMT master, SYNC
    producer and CiA 402 controlling device of its drives (by default one, node-ID 2,
    heartbeat consumer with 250 ms).  The runner drives it without threads::

        controller.boot(now)                   # boot-up 0x701, wait for the drives' boot-ups
        every cycle k (now = k * Ts):
            controller.tick(now)               # heartbeats, timeouts, sequencers, parameters
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

    **Several joints** (``joints``, :class:`~hdhil.firmware.controller.joint.JointSetup`):
    one node per bus serves up to two joints (CiA 301: one NMT master and one SYNC
    producer per network; the pre-defined connection set gives the node four TPDOs, two
    telemetry frames per joint, :mod:`hdhil.canopen.rigdb`).  Each joint has its own
    firmware configuration and interrupt handler, link phase, sequencer, cyclic I/O,
    supervision and diagnostics (``joints[r]``); a joint's interrupt handler runs when
    that joint's sensor frame arrives.  The SYNC goes out once per cycle while any joint
    is in service; a joint that ends in "safe" (its drive never booted, lost its
    heartbeat, stopped sending) stops commanding its own drive only, and the node leaves
    OPERATIONAL once no joint commands its drive.  ``phase`` is then the node's: the
    first of "wait-boot", "starting", "stopping", "operational" that a joint in service
    is in, else "safe" if a joint is, else "stopped"; ``boot_error`` is set when every
    joint failed (each joint's in ``joints[r].boot_error``).  A further node on the bus
    (``sync_producer=False``) serves the joints beyond two: it follows the SYNC it
    receives (its joints' cycles start there) and commands its own drives only.

    The parts are attributes: ``services``, ``objects`` (OD values, live parameters) and
    ``joints``; joint 0's ``sequencer`` (start-up and stop), ``io`` (SYNC, sensor frame,
    command, telemetry), ``supervision`` (heartbeat, NMT, sensor EMCYs), ``isr``,
    ``config`` and ``diagnostics`` are the node's too, as in a node of one joint.  The
    node's object dictionary holds one joint's entries (PDOs 0x1400-0x1401 and
    0x1800-0x1802, the mirrors, the live parameters 0x2400-0x2430): joint 0's.  The
    node uses nothing but a python-can bus, so the same node drives the emulator on
    ``simbus`` or a real drive on SocketCAN/PCAN/Kvaser; it never subscribes to ground
    truth.  PDO COB-IDs come from the object dictionaries at the node-IDs: joint 0's
    from the node's, its telemetry at ``node_id``'s (``$NODEID+0x180``, ``$NODEID+0x280``
    in its EDS) and the PDOs it exchanges with its drive at the drive's node-ID (the
    drive's EDS or DCF there); a further joint's from its
    :class:`~hdhil.firmware.controller.link.DriveLink` (by default CiA 301's pre-defined
    connection set at its drive's node-ID and its rank, as :mod:`hdhil.canopen.rigdb`
    numbers the rig).  The layouts are ``control.dbc``'s.

    Args:
        bus: the control bus (any python-can bus).
        config: the firmware configuration (the scenario's); written into the OD.  Not
            with ``joints``.
        sync_overflow: SYNC counter overflow, object 0x1019 (CiA 301: 2..240 here).
        node_id: this node's CANopen node-ID.
        drive_node_id: the drive's node-ID (NMT, heartbeat consumer, SDO client, its PDOs).
        heartbeat_ms: heartbeat producer time (0x1017).
        drive_heartbeat_timeout_ms: heartbeat consumer time for each drive (0x1016).
        boot_timeout_s: how long ``boot`` waits for each drive's boot-up.
        sensor_hold_cycles: SYNCs without a sensor frame tolerated in "operational".
        isr: the interrupt handler (default: the firmware's own,
            :class:`hdhil.firmware.isr.InterruptHandler`).
        drive_dcf: the drive's DCF: the controller configures the drive from it at boot
            and gives its own PDOs the matching mapping (:mod:`.objects`, :mod:`.codecs`);
            in the CiA 402 CST mapping it reads the drive's rated torque 0x6076 before NMT
            start and the [Vertechy] control laws are refused.
        joints: the joints of a node serving several (instead of ``config``,
            ``drive_node_id``, ``isr`` and ``drive_dcf``), in rank order; each joint's
            link defaults to :meth:`DriveLink.predefined` for its node-ID and rank.
        sync_producer: this node produces the bus's SYNC (False: it follows it).
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
        config: FirmwareConfig | None = None,
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
        joints: Sequence[JointSetup] | None = None,
        sync_producer: bool = True,
    ) -> None:
        setups, links = _joint_links(config, node_id, drive_node_id, isr, drive_dcf, joints)
        for link in links:
            _check_arguments(sync_overflow, node_id, link.node_id, boot_timeout_s,
                             sensor_hold_cycles)  # fmt: skip
        # the frames it knows: its drives' at their node-IDs, its own at its node-ID
        drive_ids = tuple(link.node_id for link in links)
        super().__init__(bus, drive_node_id=drive_ids, controller_node_id=node_id)
        self.sync_overflow = sync_overflow
        self.node_id = node_id
        #: This node produces the bus's SYNC (else it follows the SYNC it receives).
        self.sync_producer = sync_producer
        self.boot_timeout_s = boot_timeout_s
        self.sensor_hold_cycles = sensor_hold_cycles
        #: Why the drives never booted (one line for the user); None otherwise.
        self.boot_error: str | None = None
        #: The link phase (:class:`Phase`): the joint's, or the node's of several joints.
        self.phase = Phase.WAIT_BOOT
        #: The latest ``now`` given to ``boot``/``tick`` (s).
        self.now = 0.0
        #: True while the node changes its own NMT state (not a command of another master).
        self.own_nmt = False

        self.services = CanopenServices(
            bus,
            node_id,
            eds_path("controller"),
            heartbeat_producer_ms=heartbeat_ms,
            heartbeat_consumers={link.node_id: drive_heartbeat_timeout_ms for link in links},
        )
        # joint 0's PDOs that pair with its drive's at the drive's COB-IDs (power-on values)
        _address_drive(self.services, links[0].node_id, drive_dcf)
        if setups[0].link is not None:
            _address_link(self.services, links[0])
        #: The joints, in rank order (:class:`~hdhil.firmware.controller.joint.
        #: ControllerJoint`).
        self.joints: tuple[ControllerJoint, ...] = tuple(
            ControllerJoint(self, rank, setup, link, drive_dcf if rank == 0 else None)
            for rank, (setup, link) in enumerate(zip(setups, links, strict=True))
        )
        first = self.joints[0]
        #: The only joint of a one-joint node (its cycle takes the shortest path).
        self._single: ControllerJoint | None = first if len(self.joints) == 1 else None
        #: Joint 0's diagnostics (every joint's: ``joints[r].diagnostics``).
        self.diagnostics: ControllerDiagnostics = first.diagnostics
        self.objects = ControllerObjects(self)  # joint 0's live parameters
        for joint in self.joints:
            joint.build()
        self.services.on_reset(self._on_reset)
        self.objects.store_control_pdo_validity()
        for joint in self.joints:
            self._route(joint)
        if not sync_producer:
            self.handle(SYNC_COB_ID, self._on_sync)

    def _route(self, joint: ControllerJoint) -> None:
        """A joint's frames to its parts, at the identifiers of its codecs
        (:meth:`ControllerJoint._codecs
        <hdhil.firmware.controller.joint.ControllerJoint._codecs>`)."""
        codecs: LinkCodecs = joint.codecs
        self.handle(codecs.sensor.frame_id, joint.io.on_sensor_frame)
        self.handle(codecs.status.frame_id, joint.sequencer.on_statusword_frame)
        self.handle(joint.sdo.response_id, joint.sequencer.on_sdo_response)

    # ------------------------------------------------------------------ public API

    @property
    def probe(self) -> CycleProbe | None:
        """The instrumentation hook of the cycle
        (:class:`~hdhil.firmware.controller.cyclic.CycleProbe`): SYNC sent, sensor frame
        received, interrupt run, command sent, each with its time stamp (joint 0's
        frames).  None (the default) costs one check per event."""
        return self.joints[0].io.probe

    @probe.setter
    def probe(self, probe: CycleProbe | None) -> None:
        self.joints[0].io.probe = probe

    @property
    def done(self) -> bool:
        """True once every joint has run ``num_samples`` interrupts (listing:
        ``samplecount < numsamples``)."""
        return all(joint.isr.done for joint in self.joints)

    @property
    def drive_state(self) -> State | None:
        """Joint 0's drive's CiA 402 state from its latest statusword (None before)."""
        return self.joints[0].walk.drive_state

    @property
    def controlword(self) -> int:
        """The controlword joint 0's next DRIVE_RPDO1 carries."""
        return self.joints[0].walk.controlword

    # Joint 0's parts and values, as the node's (a node of one joint is that joint).

    @property
    def config(self) -> FirmwareConfig:
        return self.joints[0].config

    @config.setter
    def config(self, config: FirmwareConfig) -> None:
        self.joints[0].config = config

    @property
    def control_pdo_valid(self) -> bool:
        return self.joints[0].control_pdo_valid

    @control_pdo_valid.setter
    def control_pdo_valid(self, valid: bool) -> None:
        self.joints[0].control_pdo_valid = valid

    @property
    def isr(self) -> InterruptHandlerModel:
        return self.joints[0].isr

    @property
    def own_isr(self) -> bool:
        return self.joints[0].own_isr

    @property
    def drive_node_id(self) -> int:
        return self.joints[0].drive_node_id

    @property
    def rated_torque_Nm(self) -> float | None:
        return self.joints[0].rated_torque_Nm

    @property
    def sensor_mapping(self) -> str:
        return self.joints[0].sensor_mapping

    @property
    def io(self) -> CyclicIo:
        return self.joints[0].io

    @property
    def sequencer(self) -> Sequencer:
        return self.joints[0].sequencer

    @property
    def supervision(self) -> Supervision:
        return self.joints[0].supervision

    @property
    def walk(self) -> Cia402Walk:
        return self.joints[0].walk

    @property
    def sdo(self) -> SdoClient:
        return self.joints[0].sdo

    @property
    def configurator(self) -> DcfConfigurator | None:
        return self.joints[0].configurator

    def boot(self, now: float) -> None:
        """Power-on (CiA 301 §7.3.2.2): boot-up message 0x701, PRE-OPERATIONAL, and, as NMT
        master, start waiting ``boot_timeout_s`` for each drive's boot-up."""
        self.now = now
        services = self.services
        services.boot(now)
        for joint in self.joints:
            services.nmt.expect_boot(joint.drive_node_id, now, self.boot_timeout_s)
            joint.set_phase(Phase.WAIT_BOOT, "power on: waiting for the drive's boot-up")

    def tick(self, now: float) -> None:
        """Once per cycle, before polling: heartbeat producer and consumer (may enter
        "safe"), parameters written last cycle, the drives' boot-up wait and its timeout,
        the sensors' error flags."""
        self.now = now
        services = self.services
        services.tick(now)
        self.objects.apply_pending()
        for joint in self.joints:
            if joint.phase is _WAIT_BOOT and services.state is not _INITIALISING:
                joint.sequencer.await_drive()
            if joint.own_isr:  # our InterruptHandler: its plausibility and stuck-channel flags
                joint.supervision.check_sensors()
            d = joint.diagnostics
            d.emcy_sent = services.emcy.sent
            d.emcy_received = services.counters.emcy_received

    def send_sync(self) -> bool:
        """Start a cycle: SYNC with the CiA 301 counter (1..overflow, then 1 again).

        Sent while a joint is in a phase but "stopped" and "safe", and only in an NMT
        state that allows it (not before ``boot``).  At this cycle boundary the node also
        applies new parameters, checks each joint's sensor hold ("operational") and its
        walk's statusword timeouts ("starting"/"stopping").  Returns True if a SYNC went
        out.
        """
        if not self.sync_producer:
            return False
        self.objects.apply_pending()
        joint = self._single
        if joint is None:
            return self._send_sync_joints()
        phase = joint.phase
        if phase is _OPERATIONAL:
            if not joint.io.sensor_hold_ok():
                return False
        elif phase is _STARTING or phase is _STOPPING:
            joint.sequencer.watchdog()
            if joint.phase in FINAL:
                return False
        elif phase in FINAL:
            return False
        return joint.io.send_sync()

    def _send_sync_joints(self) -> bool:
        """``send_sync`` of a node of several joints: the checks per joint, one SYNC."""
        serving = self._serving()
        if not serving or not self.joints[0].io.send_sync_frame():
            return False
        for joint in serving:
            joint.io.synced()
        return True

    def _on_sync(self, msg: can.Message) -> None:
        """A node that follows the bus's SYNC: the SYNC starts its joints' cycle, after
        the same checks as a SYNC of its own (in PRE-OPERATIONAL and OPERATIONAL)."""
        if not self.services.sync_allowed:
            return
        self.objects.apply_pending()
        for joint in self._serving():
            joint.io.synced()

    def _serving(self) -> list[ControllerJoint]:
        """At a cycle boundary: each joint's sensor hold or walk watchdog; the joints
        still in service."""
        serving = []
        for joint in self.joints:
            phase = joint.phase
            if phase is _OPERATIONAL:
                if not joint.io.sensor_hold_ok():
                    continue
            elif phase is _STARTING or phase is _STOPPING:
                joint.sequencer.watchdog()
                if joint.phase in FINAL:
                    continue
            elif phase in FINAL:
                continue
            serving.append(joint)
        return serving

    def request_stop(self, reason: str = "stop requested") -> None:
        """Walk the drives back (controlword 0x0007, then 0x0006), then NMT
        pre-operational for each: phase "stopping", then "stopped".  No effect once
        stopping."""
        for joint in self.joints:
            joint.sequencer.request_stop(reason)

    def on_message(self, msg: can.Message) -> None:
        """CiA 301 service frames go to the services first; SYNC/PDOs to the handlers."""
        services = self.services
        if msg.arbitration_id not in services.service_ids or not services.handle(msg):
            CanNode.on_message(self, msg)

    # ------------------------------------------------------------ phases, faults

    def commanding(self) -> bool:
        """Whether a joint commands its drive (starting, operational or stopping)."""
        return any(joint.phase in COMMANDING for joint in self.joints)

    def joint_phase_changed(self) -> None:
        """A joint changed its phase: the node's phase and boot error follow (class
        docstring)."""
        joint = self._single
        if joint is not None:
            self.phase = joint.phase
            self.boot_error = joint.boot_error
            return
        phases = {j.phase for j in self.joints}
        self.phase = next(
            (p for p in _NODE_PHASE_ORDER if p in phases),
            _SAFE if _SAFE in phases else Phase.STOPPED,
        )
        errors = [j.boot_error for j in self.joints]
        self.boot_error = (
            "; ".join(f"{j.name}: {e}" for j, e in zip(self.joints, errors, strict=True))
            if all(errors)
            else None
        )

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
        """Stop commanding every drive for good (class docstring), with an EMCY if given."""
        for joint in self.joints:
            joint.enter_safe(reason, emcy, manufacturer)
            emcy = None  # one EMCY for the node

    def _on_reset(self, kind: ResetKind) -> None:
        """NMT reset of the node by another master: every joint's supervision."""
        for joint in self.joints:
            joint.supervision.on_reset(kind)


def _joint_links(
    config: FirmwareConfig | None,
    node_id: int,
    drive_node_id: int,
    isr: InterruptHandlerModel | None,
    drive_dcf: str | Path | None,
    joints: Sequence[JointSetup] | None,
) -> tuple[tuple[JointSetup, ...], tuple[DriveLink, ...]]:
    """The joints' setups and links: the one joint of the arguments, or ``joints``."""
    if joints is None:
        if config is None:
            raise ValueError("a controller node needs a firmware configuration or joints")
        if not 1 <= drive_node_id <= 127 or drive_node_id == node_id:
            raise ValueError(f"drive node-ID must be 1..127 and not {node_id}, got {drive_node_id}")
        return (JointSetup(config, drive_node_id, isr=isr),), (
            DriveLink.predefined(drive_node_id, node_id),
        )
    if config is not None or isr is not None or drive_dcf is not None or drive_node_id != 2:
        raise ValueError(
            "give a controller node its joints, or one joint's config, drive_node_id, "
            "isr and drive_dcf; not both"
        )
    setups = tuple(joints)
    if not setups:
        raise ValueError("a controller node serves at least one joint")
    if len(setups) > MAX_JOINTS_PER_NODE:
        names = ", ".join(s.name or str(s.node_id) for s in setups)
        raise ValueError(
            f"one controller node reports the telemetry of at most {MAX_JOINTS_PER_NODE} "
            f"joints (its four pre-defined TPDOs), got {len(setups)} ({names}): give the "
            "others a controller node of their own"
        )
    for s in setups:
        if s.node_id == node_id:
            raise ValueError(f"drive node-ID must not be the controller's ({node_id})")
        if s.link is not None and s.link.node_id != s.node_id:
            raise ValueError(
                f"joint {s.name or s.node_id}: its link addresses node {s.link.node_id}, "
                f"its node-ID is {s.node_id}"
            )
    links = tuple(
        s.link if s.link is not None else DriveLink.predefined(s.node_id, node_id, rank)
        for rank, s in enumerate(setups)
    )
    ids = [link.node_id for link in links]
    if len(set(ids)) != len(ids):
        raise ValueError(f"the joints' drives need distinct node-IDs, got {ids}")
    cobs = [cob for link in links for cob in link.cob_ids]
    if len(set(cobs)) != len(cobs):
        raise ValueError("two joints' PDOs share an identifier")
    periods = {s.config.sample_period_s for s in setups}
    if len(periods) > 1:
        raise ValueError(
            "the joints of one controller node share its SYNC, so one sample period; got "
            + ", ".join(f"{p:g} s" for p in sorted(periods))
        )
    return setups, links


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


def _address_link(services: CanopenServices, link: DriveLink) -> None:
    """Joint 0's link given in its setup: its identifiers as the power-on COB-IDs of the
    node's PDOs of joint 0 (sensor RPDO1, statusword RPDO2, command TPDO3, telemetry
    TPDO1 and TPDO2), each PDO's validity as before."""
    for comm, cob_id in ((0x1400, link.sensor_cob_id), (0x1401, link.status_cob_id),
                         (0x1802, link.command_cob_id), (0x1800, link.telemetry_cob_id),
                         (0x1801, link.control_cob_id)):  # fmt: skip
        old = int(services.read(comm, 1))
        new = (old & ~0x7FF) | cob_id
        if new != old:
            services.set_power_on_value(comm, 1, new)

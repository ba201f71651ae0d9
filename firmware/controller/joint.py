"""One joint of a controller node: a drive, its interrupt handler and everything per drive.

A :class:`~hdhil.firmware.controller.node.ControllerNode` is one CANopen node per bus
(CiA 301: one NMT master and one SYNC producer per network) serving one or more joints.
Each :class:`ControllerJoint` holds what belongs to one drive: its
:class:`~hdhil.firmware.config.FirmwareConfig` (filter, law, gains, calibration) and
interrupt handler, its link phase, its boot and stop sequencer, its cyclic I/O, its
supervision and its diagnostics, and the :class:`~hdhil.firmware.controller.link.
DriveLink` that says which node and which identifiers are the drive's.  The node holds
what is one per bus: the CANopen services (NMT state, heartbeat, SDO server, EMCY, the
SYNC), the object dictionary, and the node's own NMT state, which leaves OPERATIONAL
only once no joint commands its drive any more.

The parts (:mod:`.cyclic`, :mod:`.sequencer`, :mod:`.supervision`) see a joint as they
would see a one-joint node: the same attributes, read without any indirection on the
1 kHz path (each joint's sensor frame goes straight to its own handler).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from hdhil.can.node import pdo_cob_id
from hdhil.canopen.cia402 import State
from hdhil.canopen.dcf import DcfConfigurator, configuration_writes
from hdhil.canopen.sdo import ABORT_DEVICE_STATE, SdoClient
from hdhil.canopen.services import NmtCommand, NmtState, ResetKind
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.controller.codecs import LinkCodecs, default_codecs, mapped_codecs
from hdhil.firmware.controller.cyclic import CyclicIo
from hdhil.firmware.controller.diagnostics import ControllerDiagnostics
from hdhil.firmware.controller.link import DriveLink
from hdhil.firmware.controller.phases import COMMANDING, Phase, PhaseChange
from hdhil.firmware.controller.sequencer import Sequencer
from hdhil.firmware.controller.supervision import Supervision
from hdhil.firmware.interrupt import InterruptHandlerModel
from hdhil.firmware.isr import InterruptHandler
from hdhil.firmware.odlimits import check_od_limits
from hdhil.firmware.walk import Cia402Walk

if TYPE_CHECKING:
    from hdhil.firmware.controller.node import ControllerNode

__all__ = ["ControllerJoint", "JointSetup"]


@dataclass(frozen=True)
class JointSetup:
    """One joint a controller node serves: its firmware configuration, its drive's
    node-ID, a name for messages, its interrupt handler (None: the firmware's own,
    :class:`hdhil.firmware.isr.InterruptHandler`) and its link (None: the CiA 301
    pre-defined connection set for the node-ID and the joint's rank,
    :meth:`DriveLink.predefined`, as :mod:`hdhil.canopen.rigdb` numbers the rig; joint
    0's link sets the power-on COB-IDs of its PDOs in the node's object dictionary).

    ``telemetry_every``: the joint's telemetry (``CTRL_TPDO1``, ``CTRL_TPDO2``) goes out
    in every this many SYNC cycles only (decimated telemetry, a bus's
    ``telemetry_every``), ``CTRL_TPDO1`` in the cycles c with c % ``telemetry_every`` ==
    ``telemetry_phases[0]``, ``CTRL_TPDO2`` with ``telemetry_phases[1]`` (c counts the
    joint's SYNC cycles from 0; :func:`hdhil.canopen.rigdb.telemetry_phases` gives a
    rig's phases): what a synchronous TPDO of CiA 301 transmission type
    ``telemetry_every`` (1..240) does.  The interrupt runs every cycle all the same."""

    config: FirmwareConfig
    node_id: int = 2
    name: str = ""
    isr: InterruptHandlerModel | None = None
    link: DriveLink | None = None
    telemetry_every: int = 1
    telemetry_phases: tuple[int, int] = (0, 0)

    def __post_init__(self) -> None:
        every = self.telemetry_every
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ValueError(f"telemetry every >= 1 SYNC cycles, got {every!r}")
        if len(self.telemetry_phases) != 2 or not all(
            0 <= p < every for p in self.telemetry_phases
        ):
            raise ValueError(
                f"telemetry phases must be two cycles 0..{every - 1}, got {self.telemetry_phases!r}"
            )


class ControllerJoint:
    """One drive of the node and the firmware loop that commands it (module docstring).

    ``rank`` is the joint's place among the node's joints (0-based).  Joint 0 owns the
    node's object dictionary entries of one joint (its PDOs 0x1400-0x1401 and
    0x1800-0x1802, the controlword and statusword mirrors, the live parameters
    0x2400-0x2430, a drive DCF); a further joint's PDOs are its link's identifiers.
    """

    def __init__(
        self,
        controller: ControllerNode,
        rank: int,
        setup: JointSetup,
        link: DriveLink,
        drive_dcf: str | Path | None = None,
    ) -> None:
        check_od_limits(setup.config)  # every OD parameter representable in its entry
        self.controller = controller
        self.rank = rank
        self.name = setup.name or f"joint {rank}"
        self.link = link
        self.bus = controller.bus
        self.services = controller.services
        self.config = setup.config
        self.telemetry_every = setup.telemetry_every
        self.telemetry_phases = setup.telemetry_phases
        #: The interrupt handler (:class:`firmware.interrupt.InterruptHandlerModel`): the
        #: firmware's own unless the setup gives one; the plausibility EMCYs and the SDO
        #: parameters that retune stages need the firmware's own (``own_isr``).
        self.isr: InterruptHandlerModel = (
            InterruptHandler(setup.config) if setup.isr is None else setup.isr
        )
        self.own_isr = isinstance(self.isr, InterruptHandler)
        self.diagnostics = ControllerDiagnostics()
        self.drive_node_id = link.node_id
        self.boot_timeout_s = controller.boot_timeout_s
        self.sensor_hold_cycles = controller.sensor_hold_cycles
        #: Why the drive never booted (one line for the user); None otherwise.
        self.boot_error: str | None = None
        #: The joint's link phase (:class:`Phase`; changed by its parts only).
        self.phase = Phase.WAIT_BOOT
        #: The drive's motor rated torque 0x6076 (Nm), read by SDO at boot in the CiA 402
        #: CST mapping; None in the raw mapping (or before the read).
        self.rated_torque_Nm: float | None = None
        self._drive_dcf = drive_dcf
        #: The joint's PDOs have the mapping of the drive's DCF (joint 0 only).
        self.mapped = False

    def build(self) -> None:
        """The joint's parts, once the node's object dictionary exists (joint 0 takes the
        drive's DCF mapping into it)."""
        controller = self.controller
        drive = self.drive_node_id
        self.supervision = Supervision(self)  # subscribes to the services' NMT events
        #: The SDO client of the drive's server (DCF writes, statusword and rated torque).
        self.sdo = SdoClient(self.bus, drive)
        dcf = self._drive_dcf
        #: Boot-time configuration of the drive from its DCF (CiA 306), by SDO, after its
        #: boot-up and before NMT start; None without a DCF.
        self.configurator = (
            DcfConfigurator(self.sdo, configuration_writes(dcf, drive)) if dcf is not None else None
        )
        if dcf is not None:
            controller.objects.take_drive_mapping(dcf)  # ValueError: a mapping it cannot run
            self.mapped = bool(controller.objects.pdo_writes)
        mirror = controller.objects.mirror_controlword if self.rank == 0 else _no_mirror
        self.walk = Cia402Walk(drive, mirror)
        codecs = self._codecs()
        #: Which sensor objects the drive sends: "raw" (the seed's ADC counts and encoder),
        #: "cst" (CiA 402 torque actual 0x6077 and position actual 0x6064) or "cst-sensor"
        #: (those and the joint-torque sensor 0x2102), as read from the live mapping.
        self.sensor_mapping = codecs.sensor_mapping
        self.sequencer = Sequencer(self, codecs.status)
        self.io = CyclicIo(self, codecs)
        #: CTRL_TPDO2 is valid (sent) only while a control law runs (COB-ID bit 31 clear).
        self.control_pdo_valid = self.config.control.active
        self.codecs = codecs
        if self.rank == 0:  # the identifiers the object dictionary gave joint 0's PDOs
            self.link = DriveLink(drive, codecs.sensor.frame_id, codecs.status.frame_id,
                                  codecs.command.frame_id, codecs.telemetry.frame_id,
                                  codecs.control_telemetry.frame_id)  # fmt: skip

    def _codecs(self) -> LinkCodecs:
        """Joint 0: ``control.dbc``'s codecs, or those of the mapping taken from the
        drive's DCF (in the CST mapping no control law may be switched on later either),
        each at the identifier the node's object dictionary gives its PDO (RPDO1 0x1400,
        RPDO2 0x1401, TPDO1-3 0x1800-0x1802: the node's own telemetry at its node-ID, the
        drive's PDOs at the drive's), its layout checked against the one the node encodes
        with.  A further joint: ``control.dbc``'s layouts at its link's identifiers."""
        if self.rank:
            return _on_link(default_codecs(), self.link)
        services = self.services
        if not self.mapped:
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

    # -------------------------------------------------------------- what parts use

    @property
    def now(self) -> float:
        """The node's time (the latest ``boot``/``tick``)."""
        return self.controller.now

    @property
    def own_nmt(self) -> bool:
        return self.controller.own_nmt

    @property
    def STATUSWORD_TIMEOUT_S(self) -> float:
        return self.controller.STATUSWORD_TIMEOUT_S

    @property
    def WALK_TIMEOUT_S(self) -> float:
        return self.controller.WALK_TIMEOUT_S

    @property
    def done(self) -> bool:
        """True once ``num_samples`` interrupts have run."""
        return self.isr.done

    @property
    def drive_state(self) -> State | None:
        """The drive's CiA 402 state from its latest statusword (None before the first)."""
        return self.walk.drive_state

    def mirror_statusword(self, statusword: int) -> None:
        """The drive's statusword into the OD's mirror 0x2011 (joint 0's)."""
        if self.rank == 0:
            self.controller.objects.mirror_statusword(statusword)

    def restore_after_reset(self, kind: ResetKind) -> None:
        """After an NMT reset of the node by another master: its OD values back (once)."""
        if self.rank == 0:
            self.controller.objects.restore_after_reset(kind)

    def request_stop(self, reason: str = "stop requested") -> None:
        """Walk this drive back (controlword 0x0007, then 0x0006), then NMT
        pre-operational for it."""
        self.sequencer.request_stop(reason)

    def set_phase(self, phase: Phase, reason: str) -> None:
        """Enter ``phase`` (recorded in the joint's phase history)."""
        self.phase = phase
        sequencer = self.sequencer
        sequencer.phase_cycles = 0
        sequencer.quiet_cycles = 0
        self.diagnostics.phase_history.append(PhaseChange(self.now, phase, reason))
        self.controller.joint_phase_changed()

    def enter_nmt(self, state: NmtState) -> None:
        """The node's own NMT state: OPERATIONAL when a joint starts its drive,
        PRE-OPERATIONAL once no joint commands its drive any more."""
        controller = self.controller
        if state is NmtState.PRE_OPERATIONAL and controller.commanding():
            return
        controller.enter_nmt(state)

    def enter_safe(self, reason: str, emcy: int | None = None, manufacturer: bytes = b"") -> None:
        """Stop commanding this drive for good (:class:`ControllerNode`), with an EMCY if
        given; the node leaves OPERATIONAL once no joint commands its drive."""
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


def _no_mirror(_: int) -> None:
    """A further joint has no controlword mirror in the node's object dictionary."""


def _on_link(codecs: LinkCodecs, link: DriveLink) -> LinkCodecs:
    """``codecs`` at the frame identifiers of ``link``."""
    return replace(
        codecs,
        sensor=codecs.sensor.at(link.sensor_cob_id),
        command=codecs.command.at(link.command_cob_id),
        telemetry=codecs.telemetry.at(link.telemetry_cob_id),
        control_telemetry=codecs.control_telemetry.at(link.control_cob_id),
        status=codecs.status.at(link.status_cob_id),
    )

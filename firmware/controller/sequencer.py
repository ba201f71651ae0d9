"""The controller's boot and stop sequencer: bring the drive up, walk it down.

From the drive's boot-up to OPERATION ENABLED (configuration from its DCF by SDO, its
rated torque in the CST mapping, NMT start, the CiA 402 walk) and back (the walk down,
NMT pre-operational), with the timeouts that end a walk.  The walk's decisions are
:class:`hdhil.firmware.walk.Cia402Walk`'s; this module moves them onto the bus and into
the node's phases.  It runs once per phase change and per statusword, never per sample.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, cast

import can

from hdhil.canopen.cia402 import STATUSWORD_OBJECT
from hdhil.canopen.od import eds_index
from hdhil.canopen.sdo import abort_text
from hdhil.canopen.services import NmtCommand, NmtState
from hdhil.dbc import FrameCodec, eds_path
from hdhil.firmware.controller.phases import COMMANDING, Phase, seconds
from hdhil.firmware.isr import InterruptHandler
from hdhil.firmware.walk import CONTROLWORD_ENABLE_OPERATION, WalkStep

if TYPE_CHECKING:
    from hdhil.firmware.controller.joint import ControllerJoint

__all__ = ["Sequencer"]

_WAIT_BOOT = Phase.WAIT_BOOT


class Sequencer:
    """Start-up and stop of the drive (CiA 301 §7.3.2 NMT, CiA 402 PDS state machine).

    Start-up: on the drive's boot-up (or its heartbeat, if it booted before the
    controller) the controller configures it from its DCF by SDO (if any), reads its motor
    rated torque 0x6076 in the CiA 402 CST mapping, sends NMT "start remote node" (0x000:
    01 02), enters OPERATIONAL itself and walks the drive's state machine with the
    controlword of ``DRIVE_RPDO1`` (sent on every sensor frame, DAC 0); which controlword
    for which state, and one fault reset per node, is :mod:`hdhil.firmware.walk`'s table.

    The statusword comes in ``DRIVE_TPDO2`` (0x282, event-driven; RPDO2 of the controller,
    mirrored in object 0x2011).  An event-driven PDO is sent on change only, so right after
    NMT start the controller also reads the drive's statusword once by SDO (expedited
    upload on 0x602/0x582, :class:`hdhil.canopen.sdo.SdoClient`; the index looked up by
    name in ``drive.eds``): a drive that comes up in FAULT is fault-reset from the first
    command on.  A walk step without a statusword for ``STATUSWORD_TIMEOUT_S`` (20 ms)
    counts as missed: NMT start is sent again (start-up only) and 0x6041 read by SDO
    again, which recovers a lost event-driven PDO.  The whole walk must finish within
    ``WALK_TIMEOUT_S`` (1 s): a start-up that does not ends in "safe", a stop that does
    not ends in "stopped" anyway (counted in ``stop_timeouts``).

    Timing in lockstep (boot-ups at t = 0; ``diagnostics.startup_cycles`` counts the SYNCs
    from NMT start to OPERATION ENABLED): the drive's boot-up is handled in cycle 0 (NMT
    start, SDO read of the statusword).  A drive that applies the controlword on receipt
    (``actuation = "immediate"``) answers each step in the same cycle: the walk takes the
    SYNCs of cycles 1, 2, 3 (0x0006, 0x0007, 0x000F) and the first operational sample is
    cycle 4.  A drive that takes the RPDO over at the next SYNC (``"next-sync"``, the
    default: CiA 301 synchronous RPDO) changes state at SYNC k+1 and its statusword
    follows its sensor frame, so each step takes two cycles: 6 SYNCs, first sample in
    cycle 7.  The stop takes 2 (immediate) or 3 (next-sync) cycles.

    Stop (``request_stop``, or once ``num_samples`` interrupts have run, as the listing's
    ``main`` leaves its loop and writes DAC 0): controlword 0x0007 "disable operation"
    (transition 5), then 0x0006 "shutdown" (transition 6), then NMT "enter
    pre-operational" (0x80) for the drive (it keeps its heartbeat and SDO server, so it
    can still be inspected, but takes no PDOs); the controller goes PRE-OPERATIONAL too.
    """

    def __init__(self, node: ControllerJoint, status: FrameCodec) -> None:
        self.node = node
        self.status = status
        #: The drive's statusword in the drive's EDS (what the SDO client reads).
        self.drive_statusword_index = eds_index(str(eds_path("drive")), STATUSWORD_OBJECT)
        # 0x6076, looked up by name in the drive's EDS when a mapping may need it
        self.rated_index = (
            eds_index(str(eds_path("drive")), "motor_rated_torque") if node.mapped else 0
        )
        self.rated_requested = False
        self.configure_deadline = 0.0
        #: SYNCs in the present phase, and walk cycles since the last statusword.
        self.phase_cycles = 0
        self.quiet_cycles = 0
        self.nmt_start_syncs = 0
        Ts = node.config.sample_period_s
        self.statusword_timeout_cycles = max(1, math.ceil(node.STATUSWORD_TIMEOUT_S / Ts - 1e-9))
        self.walk_timeout_cycles = max(1, math.ceil(node.WALK_TIMEOUT_S / Ts - 1e-9))

    # ------------------------------------------------------------------- boot

    def await_drive(self) -> None:
        """In "wait-boot", once per tick: the drive's boot-up (or heartbeat), or the end
        of the wait."""
        node = self.node
        drive = node.drive_node_id
        nmt = node.services.nmt
        if nmt.boot_seen(drive) or nmt.remote_states.get(drive) is not None:
            self.drive_seen()
        elif drive in nmt.boot_timed_out(node.now):
            node.boot_error = (
                f"drive (node {drive}) sent no boot-up within "
                f"{seconds(node.boot_timeout_s)} s: check power, node-ID and bit rate"
            )
            node.enter_safe(node.boot_error)

    def drive_seen(self) -> None:
        """The drive is up: configure it from its DCF first (if any), then start it."""
        node = self.node
        conf = node.configurator
        if conf is None or conf.done:
            self.after_configuration()
        elif not conf.started:
            self.configure_deadline = node.now + node.WALK_TIMEOUT_S
            conf.start()
            if conf.done:  # an empty DCF
                self.after_configuration()
        elif conf.busy and node.now > self.configure_deadline:
            node.enter_safe(
                f"drive (node {node.drive_node_id}) did not answer the DCF configuration "
                f"within {seconds(node.WALK_TIMEOUT_S)} s "
                f"({conf.position} of {len(conf.writes)} writes done)"
            )

    def after_configuration(self) -> None:
        """In the CiA 402 CST mapping, read the drive's motor rated torque 0x6076 by SDO
        first (0x6071 and 0x6077 are per mille of it); then start the drive."""
        node = self.node
        if node.sensor_mapping == "raw" or node.rated_torque_Nm is not None:
            self.start_drive()
        elif not self.rated_requested:
            self.rated_requested = True
            self.configure_deadline = node.now + node.WALK_TIMEOUT_S
            node.sdo.upload(self.rated_index, 0)
        elif node.now > self.configure_deadline:
            node.boot_error = (
                f"drive (node {node.drive_node_id}) did not answer the read of its motor "
                f"rated torque 0x{self.rated_index:04X} within {seconds(node.WALK_TIMEOUT_S)} s"
            )
            node.enter_safe(node.boot_error)

    def on_rated_torque(self, result: Any) -> None:
        """The answer to the 0x6076 read: the CST sensor source and command scale."""
        node = self.node
        what = f"drive (node {node.drive_node_id}) motor rated torque 0x{self.rated_index:04X}"
        value = int.from_bytes(bytes(result.data[:4]).ljust(4, b"\0"), "little") if result.ok else 0
        if not result.ok or value <= 0:
            code = result.abort or 0
            node.boot_error = (
                f"{what}: read aborted 0x{code:08X} ({abort_text(code)})"
                if not result.ok
                else f"{what} is {value} mNm: the CST mapping needs a rated torque > 0"
            )
            node.enter_safe(node.boot_error)
            return
        node.rated_torque_Nm = value * 1e-3
        if node.own_isr:
            cast(InterruptHandler, node.isr).use_cst_source(
                node.rated_torque_Nm, node.sensor_mapping == "cst-sensor"
            )
        self.start_drive()

    def start_drive(self) -> None:
        """NMT start of the drive, controller OPERATIONAL, walk from "shutdown"."""
        node = self.node
        drive = node.drive_node_id
        services = node.services
        boot = services.nmt.boot_times.get(drive)
        node.diagnostics.boot_time_s = node.now if boot is None else boot
        how = "boot-up" if boot is not None else "heartbeat (booted earlier)"
        services.nmt.command(NmtCommand.START, drive)
        node.enter_nmt(NmtState.OPERATIONAL)
        node.walk.restart()
        self.nmt_start_syncs = node.diagnostics.syncs_sent
        node.set_phase(Phase.STARTING, f"{how} of drive (node {drive}): NMT start")
        # Event-driven PDOs are sent on change only: read the present state once.
        self.read_statusword()

    # ------------------------------------------------------------------- walk

    def on_statusword_frame(self, msg: can.Message) -> None:
        """``DRIVE_TPDO2``: the drive's statusword, event-driven."""
        node = self.node
        status = self.status
        if msg.is_remote_frame or len(msg.data) != status.length:
            node.diagnostics.malformed_frames += 1
            return
        if node.phase not in COMMANDING or not node.services.pdo_allowed:
            node.diagnostics.pdos_ignored += 1
            return
        node.diagnostics.statusword_frames += 1
        (statusword,) = status.decode(msg.data)
        self.on_statusword(int(statusword))

    def on_sdo_response(self, msg: can.Message) -> None:
        """Answer to an SDO request of the sequencer: a DCF write, the rated torque read or
        a statusword read (expedited upload, CiA 301 §7.2.4.3.6)."""
        node = self.node
        result = node.sdo.on_response(msg)
        if result is None:
            return
        conf = node.configurator
        if conf is not None and conf.busy and node.phase is _WAIT_BOOT:
            conf.on_result(result)
            if conf.error is not None:
                node.boot_error = conf.error
                node.enter_safe(conf.error)
            elif conf.done:
                node.diagnostics.dcf_writes = len(conf.writes)
                self.after_configuration()
            return
        if self.rated_requested and node.rated_torque_Nm is None and node.phase is _WAIT_BOOT:
            self.on_rated_torque(result)
            return
        if not result.ok:
            node.diagnostics.sdo_aborts += 1
        elif len(result.data) >= 2:
            node.diagnostics.statusword_sdo_answers += 1
            if node.phase in COMMANDING:
                self.on_statusword(int.from_bytes(result.data[:2], "little"))

    def on_statusword(self, statusword: int) -> None:
        node = self.node
        self.quiet_cycles = 0
        node.mirror_statusword(statusword)
        if not node.walk.on_statusword(statusword):
            node.diagnostics.invalid_statuswords += 1
            return
        self.sequence()

    def sequence(self) -> None:
        """The CiA 402 walk: the next controlword (or phase) for the drive's state."""
        node = self.node
        phase = node.phase
        walk = node.walk
        if phase is Phase.OPERATIONAL:
            step = walk.in_operation()
        elif phase is Phase.STARTING:
            step = walk.up()
        elif phase is Phase.STOPPING:
            step = walk.down()
        else:
            return
        node.diagnostics.fault_resets = walk.fault_resets
        self.take(step)

    def take(self, step: WalkStep) -> None:
        action = step.action
        if action == "walk":
            return
        node = self.node
        if action == "operational":
            self.enter_operational()
        elif action == "restart":
            node.set_phase(Phase.STARTING, step.reason)
            self.sequence()
        elif action == "stopped":
            self.finish_stop(step.reason)
        else:
            node.enter_safe(step.reason)

    def enter_operational(self) -> None:
        node = self.node
        d = node.diagnostics
        node.walk.set_controlword(CONTROLWORD_ENABLE_OPERATION)
        if d.operational_at_s is None:
            d.operational_at_s = node.now
            d.startup_cycles = d.syncs_sent - self.nmt_start_syncs
        node.io.operational()
        node.set_phase(Phase.OPERATIONAL, "drive reports OPERATION ENABLED")

    def request_stop(self, reason: str) -> None:
        """Walk the drive back: phase "stopping" (no effect once stopping)."""
        node = self.node
        phase = node.phase
        if phase is Phase.WAIT_BOOT:
            node.set_phase(Phase.STOPPED, f"{reason} before the drive booted")
        elif phase is Phase.STARTING or phase is Phase.OPERATIONAL:
            node.set_phase(Phase.STOPPING, reason)
            self.sequence()

    def finish_stop(self, reason: str) -> None:
        node = self.node
        node.services.nmt.command(NmtCommand.ENTER_PRE_OPERATIONAL, node.drive_node_id)
        node.set_phase(Phase.STOPPED, f"{reason}; drive NMT pre-operational")
        node.enter_nmt(NmtState.PRE_OPERATIONAL)

    def watchdog(self) -> None:
        """At each SYNC of a walk: SDO read of a missing statusword, walk timeout."""
        node = self.node
        self.phase_cycles += 1
        self.quiet_cycles += 1
        if self.phase_cycles >= self.walk_timeout_cycles:
            what = f"within {seconds(node.WALK_TIMEOUT_S)} s ({node.walk.state_text()})"
            if node.phase is Phase.STARTING:
                node.enter_safe(
                    f"drive (node {node.drive_node_id}) did not reach OPERATION ENABLED {what}"
                )
            else:
                node.diagnostics.stop_timeouts += 1
                self.finish_stop(f"drive did not confirm the stop {what}")
            return
        if self.quiet_cycles >= self.statusword_timeout_cycles:
            self.quiet_cycles = 0
            node.diagnostics.statusword_timeouts += 1
            if node.phase is Phase.STARTING:
                node.services.nmt.command(NmtCommand.START, node.drive_node_id)
            self.read_statusword()

    def read_statusword(self) -> None:
        """SDO upload of the drive's statusword (CiA 301 §7.2.4.3.5), answered later."""
        self.node.sdo.upload(self.drive_statusword_index, 0)
        self.node.diagnostics.statusword_sdo_reads += 1

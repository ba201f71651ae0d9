"""The controller's cyclic I/O: SYNC out, sensor PDO in, command and telemetry PDOs out.

This is the 1 kHz path.  Over CAN the DSP's timer interrupt of [Taghirad97] becomes the
SYNC the controller produces, and the ADC read the drive's synchronous sensor PDO: SYNC k
starts cycle k, the drive answers with ``DRIVE_TPDO1``, the interrupt body runs on those
counts (:class:`hdhil.firmware.isr.InterruptHandler`) and the command (``DRIVE_RPDO1``)
and the telemetry go out before SYNC k+1.  Everything the cycle needs is bound once, at
construction; an optional :class:`CycleProbe` time-stamps the cycle's events for the
real-time statistics at the cost of one ``None`` check per event when there is none.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, Protocol, cast

import can

from hdhil.canopen.services import EmcyCode
from hdhil.firmware.controller.codecs import LinkCodecs
from hdhil.firmware.controller.phases import COMMANDING, Phase
from hdhil.firmware.interrupt import AdcSample, CstSample
from hdhil.firmware.isr import InterruptHandler
from hdhil.firmware.stages import torque_command_per_mille
from hdhil.firmware.walk import CONTROLWORD_ENABLE_OPERATION

if TYPE_CHECKING:
    from hdhil.firmware.controller.joint import ControllerJoint

__all__ = ["CycleProbe", "CyclicIo"]

# The phase the per-frame code tests for, as a module global: an attribute of an Enum class
# (``Phase.OPERATIONAL``) is looked up through ``EnumType.__getattr__``'s slow path in
# Python 3.11, several times slower than a global.
_OPERATIONAL = Phase.OPERATIONAL
_now_ns = time.perf_counter_ns
_tuple_new = tuple.__new__


class CycleProbe(Protocol):
    """Instrumentation of the cycle (``ControllerNode.probe``): each method gets
    :func:`time.perf_counter_ns` taken as the event happened.  Called from the 1 kHz
    path, so it must be quick and must not raise."""

    def on_sync_sent(self, t_ns: int) -> None:
        """The SYNC was handed to the bus (``t_ns``: just before the hand-over)."""

    def on_sensor(self, t_ns: int) -> None:
        """A sensor frame reached the controller's handler."""

    def on_interrupt(self, start_ns: int, end_ns: int) -> None:
        """The interrupt handler ran on a sensor sample from ``start_ns`` to ``end_ns``."""

    def on_command_sent(self, t_ns: int) -> None:
        """A command frame was handed to the bus (``t_ns``: just before the hand-over)."""


class CyclicIo:
    """SYNC producer, sensor-frame handler, command and telemetry sender of the node.

    With a torque-control law active ([Vertechy],
    :class:`hdhil.firmware.config.ControlConfig`) ``CTRL_TPDO1.T_filtered`` carries the
    LQG estimate ``τ̂s`` instead of the ripple filter's torque, and a second telemetry
    frame ``CTRL_TPDO2`` (0x281) follows with ``τ̂s'``, ``τ̂lgd``, ``τsD`` and the
    estimated error ``e``.  Without a law ``CTRL_TPDO2`` is not sent at all: the PDO is
    not valid, as CANopen marks it with bit 31 of its COB-ID (``dbc/controller.eds``
    object 0x1801 defaults to 0x80000281, and the node keeps that bit in step with the
    law), and the bus carries exactly the [Taghirad97] schedule.  Worst-case control-bus
    load: 42.8 % without, 56.0 % with a law.

    In the walk phases a sensor frame is answered with DAC 0 and the walk's controlword.
    In "operational" the interrupt runs once per SYNC (a second sensor frame in a cycle is
    counted and ignored); ``sensor_hold_cycles`` SYNCs in a row without a sensor frame
    end in "safe" with EMCY 0x8250 "RPDO timeout" (manufacturer bytes: the drive's
    node-ID and the number of SYNCs); until then the drive holds the last command, and a
    cycle without a sensor frame widens the next sample's plausibility bounds by one
    period.  In the CiA 402 CST mapping the command goes out as the target torque 0x6071
    in per mille of the drive's rated torque
    (:func:`hdhil.firmware.stages.torque_command_per_mille`).
    """

    def __init__(self, node: ControllerJoint, codecs: LinkCodecs) -> None:
        self.node = node
        self.bus = node.bus
        self.services = node.services
        self.diagnostics = node.diagnostics
        self.walk = node.walk
        self.sensor = codecs.sensor
        self.command = codecs.command
        self.telemetry = codecs.telemetry
        self.control_telemetry = codecs.control_telemetry
        self.raw = codecs.sensor_mapping == "raw"
        #: The sensor frame carries the joint-torque sensor 0x2102 (the mapping "cst-sensor").
        self.gauge = codecs.sensor_mapping == "cst-sensor"
        self.sensor_picks = codecs.sensor_picks
        self.command_picks = codecs.command_picks
        self.dbc_command = codecs.dbc_command
        self.torque_per_volt = node.config.control.torque_per_volt
        self.command_msg = _message(self.command.frame_id, self.command.length)
        self.telemetry_msg = _message(self.telemetry.frame_id, self.telemetry.length)
        self.control_msg = _message(self.control_telemetry.frame_id, self.control_telemetry.length)
        #: Decimated telemetry: every ``telemetry_every`` cycles, at the joint's phases.
        self.telemetry_every = node.telemetry_every
        self.telemetry_phases = node.telemetry_phases
        self.decimated = self.telemetry_every > 1
        #: The instrumentation hook (:class:`CycleProbe`), None when not instrumented.
        self.probe: CycleProbe | None = None
        self.sensor_seen = True
        self.isr_ran = False  # the interrupt ran in this cycle (once per SYNC)
        self.missing_sensor = 0
        self.settle_left = 0  # start-up pause cycles left (listing main())
        self.cycle = 0
        # The raw mapping with the sensor objects in AdcSample's order and nothing else
        # (control.dbc's DRIVE_TPDO1): the decoded tuple is retyped into the sample, no
        # copy (AdcSample is a named tuple).
        self._values_are_sample = (
            self.raw
            and tuple(self.sensor_picks) == (0, 1, 2, 3)
            and len(self.sensor.signal_names) == len(AdcSample._fields)
        )

    def operational(self) -> None:
        """The drive reports OPERATION ENABLED: the sensor hold starts afresh, and the
        listing's start-up pause (the firmware's own handler only) begins."""
        node = self.node
        self.sensor_seen = True
        self.missing_sensor = 0
        self.settle_left = node.config.startup_settle_cycles if node.own_isr else 0

    # -------------------------------------------------------------------- SYNC

    def send_sync(self) -> bool:
        """SYNC with the CiA 301 counter, if the NMT state allows it; a new cycle."""
        probe = self.probe
        if probe is None:
            if not self.services.send_sync():
                return False
        else:
            t = _now_ns()
            if not self.services.send_sync():
                return False
            probe.on_sync_sent(t)
        self.sensor_seen = False
        self.isr_ran = False
        self.diagnostics.syncs_sent += 1
        return True

    def send_sync_frame(self) -> bool:
        """The SYNC of a node of several joints, sent through joint 0's I/O (its probe):
        True if it went out; every joint in service then starts its cycle (``synced``)."""
        probe = self.probe
        if probe is None:
            return self.services.send_sync()
        t = _now_ns()
        if not self.services.send_sync():
            return False
        probe.on_sync_sent(t)
        return True

    def synced(self) -> None:
        """The node's SYNC went out: a new cycle of this joint."""
        self.sensor_seen = False
        self.isr_ran = False
        self.diagnostics.syncs_sent += 1

    def sensor_hold_ok(self) -> bool:
        """Sensor hold in "operational": False (and "safe") after ``sensor_hold_cycles``
        SYNCs in a row without a sensor frame."""
        if self.sensor_seen:
            self.missing_sensor = 0
            return True
        node = self.node
        self.missing_sensor += 1
        node.isr.sample_missed()
        d = self.diagnostics
        d.sensor_frames_missed += 1
        d.sensor_hold_longest = max(d.sensor_hold_longest, self.missing_sensor)
        if self.missing_sensor < node.sensor_hold_cycles:
            return True
        n = self.missing_sensor
        node.enter_safe(
            f"no sensor frame from drive (node {node.drive_node_id}) for {n} SYNCs",
            EmcyCode.RPDO_TIMEOUT,
            bytes((node.drive_node_id, min(n, 255))),
        )
        return False

    # ------------------------------------------------------------ sensor frame

    def on_sensor_frame(self, msg: can.Message) -> None:
        probe = self.probe
        if probe is not None:
            probe.on_sensor(_now_ns())
        sensor = self.sensor
        d = self.diagnostics
        data = msg.data
        if msg.is_remote_frame or len(data) != sensor.length:
            d.malformed_frames += 1
            return
        node = self.node
        phase = node.phase
        if phase not in COMMANDING or not self.services.pdo_allowed:
            d.pdos_ignored += 1
            return
        if phase is _OPERATIONAL and self.isr_ran:
            # A second sensor frame in one cycle (duplicated on the bus): the interrupt
            # runs once per SYNC, as the seed's timer interrupt does.
            d.extra_sensor_frames += 1
            return
        self.sensor_seen = True
        d.sensor_frames += 1
        isr = node.isr
        if phase is not _OPERATIONAL:
            self.send_command(isr.shutdown_dac_counts, self.walk.controlword)
            return
        self.isr_ran = True
        if self.settle_left:
            # listing main(): write_dac0( Vbias ); then the settling pause before the
            # first interrupt (FirmwareConfig.startup_settle_s)
            self.settle_left -= 1
            own = cast(InterruptHandler, isr)
            self.send_command(own.startup_dac_counts, CONTROLWORD_ENABLE_OPERATION)
            return
        values = sensor.decode(data)
        sample: AdcSample | CstSample
        if self._values_are_sample:
            sample = _tuple_new(AdcSample, values)
        elif self.raw:
            a, b, c, e = self.sensor_picks
            sample = AdcSample(values[a], values[b], values[c], values[e])
        elif self.gauge:
            a, b, c = self.sensor_picks
            sample = CstSample(values[a], values[b], values[c])
        else:
            a, b = self.sensor_picks
            sample = CstSample(values[a], values[b])
        if probe is None:
            out = isr(sample)
        else:
            t0 = _now_ns()
            out = isr(sample)
            probe.on_interrupt(t0, _now_ns())
        self.send_command(out.dac_counts, CONTROLWORD_ENABLE_OPERATION, out.reference_V)
        send = self.bus.send
        telemetry_msg = self.telemetry_msg
        if self.decimated:
            self._send_decimated(out)
        elif node.control_pdo_valid:
            telemetry_msg.data = self.telemetry.encode(
                out.T_meas, out.tau_s_hat, out.velocity, out.current
            )
            send(telemetry_msg)
            self.control_msg.data = self.control_telemetry.encode(
                out.dtau_s_hat, out.tau_lgd_hat, out.tau_sD, out.e_hat
            )
            send(self.control_msg)
            d.control_frames_sent += 1
        else:
            telemetry_msg.data = self.telemetry.encode(
                out.T_meas, out.T_filtered, out.velocity, out.current
            )
            send(telemetry_msg)
        if isr.done:
            node.request_stop(f"num_samples = {node.config.num_samples} reached")

    def _send_decimated(self, out: Any) -> None:
        """Decimated telemetry (:class:`~hdhil.firmware.controller.joint.JointSetup`):
        each telemetry frame only in its own cycles of every ``telemetry_every``."""
        node = self.node
        cycle = self.diagnostics.syncs_sent - 1  # this SYNC cycle, from 0
        every = self.telemetry_every
        tele_phase, control_phase = self.telemetry_phases
        valid = node.control_pdo_valid
        if cycle % every == tele_phase:
            self.telemetry_msg.data = self.telemetry.encode(
                out.T_meas, out.tau_s_hat if valid else out.T_filtered, out.velocity, out.current
            )
            self.bus.send(self.telemetry_msg)
        if valid and cycle % every == control_phase:
            self.control_msg.data = self.control_telemetry.encode(
                out.dtau_s_hat, out.tau_lgd_hat, out.tau_sD, out.e_hat
            )
            self.bus.send(self.control_msg)
            self.diagnostics.control_frames_sent += 1

    # ----------------------------------------------------------------- command

    def send_command(self, dac_counts: int, controlword: int, volts: float | None = None) -> None:
        cycle = self.cycle
        if self.dbc_command:
            data = self.command.encode(dac_counts, controlword, cycle & 0xFF)
        else:
            data = self._encode_mapped_command(dac_counts, controlword, volts)
        msg = self.command_msg
        msg.data = data
        probe = self.probe
        if probe is None:
            self.bus.send(msg)
        else:
            t = _now_ns()
            self.bus.send(msg)
            probe.on_command_sent(t)
        self.diagnostics.commands_sent += 1
        self.walk.cw_sends += 1
        self.cycle = cycle + 1

    def _encode_mapped_command(
        self, dac_counts: int, controlword: int, volts: float | None
    ) -> bytes:
        """The command PDO of a mapping from the DCF: the DAC code, or in the CST mapping
        the target torque 0x6071 in per mille of the drive's rated torque (from the
        handler's amplifier voltage, else the DAC code's), then the controlword and the
        cycle counter if mapped."""
        command: int = dac_counts
        if not self.raw:
            node = self.node
            rated = node.rated_torque_Nm
            if volts is None:
                volts = node.config.dac.to_volts(dac_counts)
            command = torque_command_per_mille(volts, self.torque_per_volt, rated) if rated else 0
        values = [0] * len(self.command.signal_names)
        for position, value in zip(
            self.command_picks, (command, controlword, self.cycle & 0xFF), strict=False
        ):
            values[position] = value
        return self.command.encode(*values)


def _message(frame_id: int, length: int) -> can.Message:
    return can.Message(arbitration_id=frame_id, is_extended_id=False, dlc=length, check=False)
